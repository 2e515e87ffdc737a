"""Videos of a trained avatar: driven by a motion file (``rmavatar animate``) or turning in a rest pose
(``rmavatar render RUN --turntable``)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import torch
from tqdm import tqdm

from rmavatar.animate.camera import (
    framing_distance,
    intrinsics,
    orbit_viewmats,
    preset_viewmat,
)
from rmavatar.animate.motion import recenter_motion
from rmavatar.animate.video import frame_writer, to_uint8
from rmavatar.avatar.trained import TrainedAvatar
from rmavatar.body import PoseSequence
from rmavatar.render.camera import Camera
from rmavatar.utils import UserError


@dataclass
class VideoOptions:
    """How a video is shot: ``size`` image height (width follows ``aspect``; both rounded up to even),
    vertical field of view, background RGB, frame rate."""

    size: int = 512  # frame height in pixels (rounded up to even)
    aspect: float = 1.0  # frame width / height
    fov_deg: float = 30.0  # vertical field of view in degrees
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # background RGB in 0..1 (white)
    fps: float = 30.0  # frame rate of the video file
    progress: bool = True  # show a progress bar while rendering
    overwrite: bool = False  # replace an output rmavatar cannot prove it wrote (see utils.outputs)

    def validate(self) -> "VideoOptions":
        """UserError for a value no video can be shot with (checked before any rendering)."""
        if not 2 <= self.size <= 8192:
            raise UserError(f"--size must be in 2..8192 pixels, got {self.size}")
        if not (math.isfinite(self.aspect) and self.aspect > 0):
            raise UserError(f"aspect must be a positive number, got {self.aspect}")
        if not (math.isfinite(self.fov_deg) and 0.0 < self.fov_deg < 180.0):
            raise UserError(f"--fov must be between 0 and 180 degrees (exclusive), got {self.fov_deg}")
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise UserError(f"--fps must be a positive number, got {self.fps}")
        if len(self.background) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in self.background):
            raise UserError(f"background must be three values in 0..1, got {tuple(self.background)}")
        return self


def _frame_size(opts: VideoOptions) -> tuple[int, int]:
    return even_size(opts.size, opts.aspect)


def frame_the_body(vertices: torch.Tensor, opts: VideoOptions) -> tuple[torch.Tensor, float]:
    """Camera target [3] (the bounding-box centre) and distance that keep ``vertices`` [n,V,3] in view."""
    pts = vertices.reshape(-1, 3).detach().cpu().double()
    center = 0.5 * (pts.min(0).values + pts.max(0).values)
    width, height = _frame_size(opts)
    return center, framing_distance(pts, center, opts.fov_deg, width / height)


def _sample_frames(n: int, most: int = 32) -> list[int]:
    return sorted({round(i * (n - 1) / max(most - 1, 1)) for i in range(min(n, most))})


def animate_video(trained: TrainedAvatar, seq: PoseSequence, out: str | os.PathLike, camera: str = "fixed",
                  opts: VideoOptions | None = None) -> int:
    """Render ``seq`` (already frame-selected) re-centred in front of the camera into ``out``.

    ``camera``: 'fixed' (in front) or 'orbit' (one full turn around the body over the clip).
    Returns the number of frames written.
    """
    opts = (opts or VideoOptions()).validate()
    seq = recenter_motion(seq, trained.root_rest())
    n = len(seq)
    width, height = _frame_size(opts)
    K = intrinsics(width, height, opts.fov_deg)
    sample = trained.vertices(seq.select(_sample_frames(n)))
    center, distance = frame_the_body(sample, opts)
    if camera == "orbit":
        views = orbit_viewmats(center, distance, n)
    elif camera == "fixed":
        views = preset_viewmat("front", center, distance)[None].expand(n, 4, 4)
    else:
        raise ValueError(f"camera must be 'fixed' or 'orbit', got {camera!r}")
    with frame_writer(out, opts.fps, width, height, overwrite=opts.overwrite) as write:
        for i in tqdm(range(n), desc="animate", unit="frame", disable=not opts.progress):
            gs = trained.pose(seq, i, keep=False)  # one replayed graph per frame on a GPU, drawn at once
            write(to_uint8(trained.render(gs, Camera(K, views[i], width, height), opts.background)))
    return n


def turntable_video(trained: TrainedAvatar, out: str | os.PathLike, num_frames: int = 90, pose: str = "tpose",
                    opts: VideoOptions | None = None, elevation_deg: float = 0.0) -> int:
    """A 360-degree orbit around the avatar standing in a rest pose ('tpose', 'apose' or 'train', see
    :meth:`TrainedAvatar.rest_pose`) into ``out``."""
    opts = (opts or VideoOptions()).validate()
    seq = trained.rest_pose(pose)
    verts = trained.vertices(seq)
    gs = trained.gaussians(verts[0], seq.body_pose[0], seq.hand(0))
    width, height = _frame_size(opts)
    K = intrinsics(width, height, opts.fov_deg)
    center, distance = frame_the_body(verts, opts)
    views = orbit_viewmats(center, distance, num_frames, elevation_deg=elevation_deg)
    with frame_writer(out, opts.fps, width, height, overwrite=opts.overwrite) as write:
        for view in tqdm(views, desc="turntable", unit="frame", disable=not opts.progress):
            write(to_uint8(trained.render(gs, Camera(K, view, width, height), opts.background)))
    return num_frames


def parse_background(text: str) -> tuple[float, float, float]:
    """'white', 'black', or 'R,G,B' in 0..1 -> RGB."""
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5)}
    if text in named:
        return named[text]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise UserError(f"--bg must be white, black, gray or R,G,B with values in 0..1, got {text!r}")
    return rgb


def even_size(size: int, aspect: float = 1.0) -> tuple[int, int]:
    """(width, height) of an image ``size`` pixels high, rounded up to even numbers (H.264 needs them)."""
    if size < 2:
        raise UserError(f"--size must be at least 2, got {size}")
    height = size + size % 2
    width = int(round(size * aspect))
    return width + width % 2, height
