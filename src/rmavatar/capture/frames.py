"""Decoding the input of ``rmavatar capture``: a video file (imageio-ffmpeg) or a folder of images,
optionally subsampled in time and resized, as uint8 RGB frames.

Every problem with the input (missing, unreadable, empty, frames of different sizes) is a UserError
that names it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from rmavatar.data.dataset import target_size
from rmavatar.data.io import read_image, resample
from rmavatar.utils import UserError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".webm", ".mkv", ".m4v")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp", ".tif", ".tiff")
# A folder of images has no frame rate; this one is written into meta.yaml.
FOLDER_FPS = 30.0


@dataclass
class Source:
    """What is known about the input before decoding.

    path; kind ("video" or "folder"); fps of the source (a folder: FOLDER_FPS); size (width, height)
    of the source frames; estimated frame count (None if unknown); files (a folder's images, sorted).
    """

    path: Path
    kind: str
    fps: float
    size: tuple[int, int]
    count: int | None
    files: list[Path] | None = None


def open_source(path: str | Path) -> Source:
    """Look at the input (a video file or a folder of images) without decoding every frame."""
    path = Path(path).expanduser()
    if not path.exists():
        raise UserError(f"input {path} does not exist")
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise UserError(f"input folder {path} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        first = read_image(files[0])
        return Source(path, "folder", FOLDER_FPS, (first.shape[1], first.shape[0]), len(files), files)
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise UserError(f"input {path} is a single image: give a video or a folder of frames")
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    try:
        meta = next(gen)
    except (OSError, RuntimeError, StopIteration, IndexError, AttributeError) as exc:
        # ffmpeg found no video stream or could not parse the file (the header parser fails in
        # several ways on non-videos)
        raise UserError(f"cannot read video {path}: not a video ffmpeg can decode "
                        f"({_first_line(exc)})") from None
    finally:
        gen.close()
    fps = float(meta.get("fps") or 0.0)
    duration = float(meta.get("duration") or 0.0)
    count = int(round(fps * duration)) if fps > 0 and duration > 0 else None
    return Source(path, "video", fps if fps > 0 else FOLDER_FPS, tuple(meta["size"]), count)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def output_size(source: Source, size: int | None) -> tuple[int, int]:
    """The frame size written: ``size`` is the longer side (None: the source's size)."""
    return target_size(*source.size, size)


def keep_frame(i: int, src_fps: float, out_fps: float | None) -> bool:
    """Whether source frame ``i`` is kept when ``src_fps`` is subsampled to ``out_fps`` (None: all):
    frame i is kept when it is the first one at or after the next output time step."""
    if out_fps is None or out_fps >= src_fps:
        return True
    step = src_fps / out_fps
    return math.floor(i / step) != math.floor((i - 1) / step) if i > 0 else True


def read_frames(source: Source, size: int | None = None, fps: float | None = None
                ) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (source frame index, uint8 RGB [H,W,3]) for every kept frame, resized to ``size`` (the
    longer side; area averaging when shrinking, as datasets are resized)."""
    width, height = output_size(source, size)
    if source.kind == "folder":
        frames = ((i, None, p) for i, p in enumerate(source.files))
    else:
        frames = ((i, raw, None) for i, raw in enumerate(_video_frames(source)))
    for i, raw, file in frames:
        if not keep_frame(i, source.fps, fps):
            continue
        if file is not None:
            image = read_image(file)
            if (image.shape[1], image.shape[0]) != source.size:
                raise UserError(f"image {file} is {image.shape[1]}x{image.shape[0]}, the first image of "
                                f"{source.path} is {source.size[0]}x{source.size[1]}")
            image = (resample(image, width, height) * 255.0 + 0.5).astype(np.uint8)
        else:
            image = raw
            if (width, height) != source.size:
                image = (resample(image.astype(np.float32) / 255.0, width, height) * 255.0 + 0.5).astype(np.uint8)
        yield i, image


def _video_frames(source: Source) -> Iterator[np.ndarray]:
    import imageio_ffmpeg

    w, h = source.size
    gen = imageio_ffmpeg.read_frames(str(source.path))
    try:
        next(gen)
        for raw in gen:
            yield np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3)
    except RuntimeError as exc:
        raise UserError(f"cannot decode video {source.path}: {_first_line(exc)}") from None
    finally:
        gen.close()
