"""Writing rendered frames as an H.264 MP4 (imageio-ffmpeg's bundled ffmpeg) or a folder of PNGs.

Both writers are atomic: the output appears only when every frame was written; on any error (or
Ctrl-C) the temporary file or folder is removed and an existing output is left untouched.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from rmavatar.utils import UserError
from rmavatar.utils.outputs import check_output_file, check_output_folder, output_file, output_folder

VIDEO_SUFFIXES = (".mp4",)


def is_frames_dir(out: str | os.PathLike) -> bool:
    """True when ``out`` names a folder of PNG frames: it ends with a path separator or is a folder."""
    text = str(out)
    return text.endswith("/") or text.endswith(os.sep) or Path(text).is_dir()


FRAMES_KIND = "frames"
FRAME_NAMES = ("frame_*.png",)


def check_output(out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Validate an output path before any work is done; raise :class:`UserError` if it cannot be written,
    or holds something rmavatar did not write (see :mod:`rmavatar.utils.outputs`)."""
    path = Path(str(out).rstrip("/" + os.sep) or ".")
    if is_frames_dir(out):
        return check_output_folder(path, FRAMES_KIND, option="--out", overwrite=overwrite, writes=FRAME_NAMES)
    return check_output_file(path, option="--out", overwrite=overwrite, suffixes=VIDEO_SUFFIXES)


@contextlib.contextmanager
def frame_writer(out: str | os.PathLike, fps: float, width: int, height: int,
                 overwrite: bool = False) -> Iterator[Callable]:
    """Yield ``write(frame [H,W,3] uint8)``; the MP4 / PNG folder appears when the block ends cleanly.

    MP4s are H.264 in yuv420p (what browsers and phones play), so ``width`` and ``height`` must be even.
    """
    path = check_output(out, overwrite)
    try:
        if is_frames_dir(out):
            with output_folder(path, FRAMES_KIND, option="--out", overwrite=overwrite, writes=FRAME_NAMES) as tmp:
                yield _png_writer(Path(tmp), width, height)
        else:
            if width % 2 or height % 2:
                raise ValueError(f"H.264 yuv420p needs even sizes, got {width}x{height}")
            with output_file(path, option="--out", overwrite=overwrite) as tmp, \
                    _mp4_writer(Path(tmp), fps, width, height) as write:
                yield write
    except OSError as exc:  # permissions, a read-only or full file system, ffmpeg unable to write
        raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None


def _png_writer(folder: Path, width: int, height: int) -> Callable:
    from PIL import Image

    count = [0]

    def write(frame: np.ndarray) -> None:
        _check_frame(frame, width, height)
        Image.fromarray(frame).save(folder / f"frame_{count[0]:05d}.png")
        count[0] += 1

    return write


@contextlib.contextmanager
def _mp4_writer(path: Path, fps: float, width: int, height: int) -> Iterator[Callable]:
    import imageio_ffmpeg

    gen = imageio_ffmpeg.write_frames(
        str(path), (width, height), fps=fps, codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
        quality=8, macro_block_size=2, ffmpeg_log_level="error",
        output_params=["-movflags", "+faststart"],
    )
    gen.send(None)  # starts ffmpeg

    def write(frame: np.ndarray) -> None:
        _check_frame(frame, width, height)
        gen.send(np.ascontiguousarray(frame))

    try:
        yield write
    except BaseException:
        # Ctrl-C can land inside the generator's own send(); closing it then may raise again (a
        # SystemError or ValueError from the half-run generator): the first error is the one to report.
        with contextlib.suppress(Exception):
            gen.close()
        raise
    gen.close()  # flushes and waits for ffmpeg


def _check_frame(frame: np.ndarray, width: int, height: int) -> None:
    if frame.dtype != np.uint8 or frame.shape != (height, width, 3):
        raise ValueError(f"frame must be uint8 [{height},{width},3], got {frame.dtype} {frame.shape}")


def to_uint8(image) -> np.ndarray:
    """An image [H,W,3] float in [0,1] (tensor or array) as uint8, rounded."""
    if hasattr(image, "detach"):
        image = image.detach().cpu().numpy()
    return (np.clip(np.asarray(image, np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
