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
# frames_at decodes a video of up to this many frames whole (one ffmpeg run), and enters a longer one at
# each frame's time stamp (an ffmpeg run per frame, each decoding from the key frame before it): eight
# frames of a 100-frame 1088x1920 clip took 1.2 s one way and 7.3 s the other on 2 busy cores, while a
# minute of video at 30 frames/s decoded whole would take longer than eight entries.
SEEK_FROM = 300


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


def shrink(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """uint8 RGB [H,W,3] -> [height,width,3] uint8 by area averaging (the box filter of
    :func:`rmavatar.data.io.resample`, on 8 bits: about ten times cheaper than through floats)."""
    if (image.shape[1], image.shape[0]) == (width, height):
        return image
    from PIL import Image

    method = Image.Resampling.BOX if width <= image.shape[1] and height <= image.shape[0] else Image.Resampling.BILINEAR
    return np.asarray(Image.fromarray(np.ascontiguousarray(image)).resize((width, height), method))


def kept_frames(source: Source, fps: float | None) -> list[int] | None:
    """The source frame numbers ``read_frames`` keeps at ``fps`` (None: all), or None when the clip's
    length is unknown (a video without a duration)."""
    if source.count is None:
        return None
    return [i for i in range(source.count) if keep_frame(i, source.fps, fps)]


def read_frames(source: Source, size: int | None = None, fps: float | None = None
                ) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (source frame index, uint8 RGB [H,W,3]) for every kept frame, resized to ``size`` (the
    longer side; area averaging when shrinking, as datasets are resized). The index is the frame's
    0-based number in the video (a folder: in the sorted file list)."""
    width, height = output_size(source, size)
    if source.kind == "folder":
        frames = ((i, None, p) for i, p in enumerate(source.files))
    else:
        frames = ((i, raw, None) for i, raw in enumerate(_video_frames(source)))
    for i, raw, file in frames:
        if not keep_frame(i, source.fps, fps):
            continue
        yield i, _frame(source, raw, file, width, height)


def frames_at(source: Source, indices: list[int], size: int | None = None, seek: bool | None = None
              ) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (i, uint8 RGB [H,W,3]) for the source frames ``indices`` (ascending) only, as
    :func:`read_frames` gives them; indices past the clip's end are skipped. A video of at most
    SEEK_FROM frames is decoded in one ffmpeg run that hands over only those frames (ffmpeg decodes
    the others but does not convert or send them); a longer one (or ``seek``) is entered at each
    frame's time stamp, so looking at a few frames of a long clip costs a few frames, not the clip."""
    width, height = output_size(source, size)
    if source.kind == "folder":
        for i in indices:
            if i < len(source.files):
                yield i, _frame(source, None, source.files[i], width, height)
        return
    if seek is None:
        seek = source.count is None or source.count > SEEK_FROM
    if not seek:
        for i, raw in zip(indices, _video_frames(source, indices)):
            yield i, _frame(source, raw, None, width, height)
        return
    for i in indices:
        raw = _video_frame_at(source, i)
        if raw is not None:
            yield i, _frame(source, raw, None, width, height)


def _frame(source: Source, raw: np.ndarray | None, file: Path | None, width: int, height: int) -> np.ndarray:
    if file is not None:
        image = read_image(file)
        if (image.shape[1], image.shape[0]) != source.size:
            raise UserError(f"image {file} is {image.shape[1]}x{image.shape[0]}, the first image of "
                            f"{source.path} is {source.size[0]}x{source.size[1]}")
        return (resample(image, width, height) * 255.0 + 0.5).astype(np.uint8)
    return shrink(raw, width, height)


def _video_frame_at(source: Source, i: int) -> np.ndarray | None:
    """Frame ``i`` of a video (uint8 [H,W,3]), or None past its end. ffmpeg's input seek is exact: it
    decodes from the key frame before the time asked for and drops the frames stamped before it; the
    time asked for lies a quarter frame before frame i's stamp, so rounding cannot drop frame i itself."""
    import imageio_ffmpeg

    w, h = source.size
    params = ["-ss", f"{(i - 0.25) / source.fps:.6f}"] if i > 0 else None
    gen = imageio_ffmpeg.read_frames(str(source.path), input_params=params, output_params=["-frames:v", "1"])
    try:
        next(gen)
        raw = next(gen, None)
    except RuntimeError as exc:
        raise UserError(f"cannot decode video {source.path}: {_first_line(exc)}") from None
    finally:
        gen.close()
    return None if raw is None else np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3)


def _video_frames(source: Source, only: list[int] | None = None) -> Iterator[np.ndarray]:
    """The video's frames in order (uint8 [H,W,3]); ``only``: just the frames with these numbers."""
    import imageio_ffmpeg

    w, h = source.size
    params = None
    if only is not None:  # ffmpeg's select filter (a backslash escapes the comma inside the filter graph)
        params = ["-vf", "select=" + "+".join(f"eq(n\\,{int(i)})" for i in only), "-fps_mode", "passthrough"]
    gen = imageio_ffmpeg.read_frames(str(source.path), output_params=params)
    try:
        next(gen)
        for raw in gen:
            yield np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3)
    except RuntimeError as exc:
        raise UserError(f"cannot decode video {source.path}: {_first_line(exc)}") from None
    finally:
        gen.close()
