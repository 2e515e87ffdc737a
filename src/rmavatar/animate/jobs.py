"""Videos of an avatar: driven by a motion file (``rmavatar animate``) or turning in a rest pose
(``rmavatar render RUN --turntable``)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
from tqdm import tqdm

from rmavatar.animate.camera import framing_distance, intrinsics, orbit_viewmats, preset_viewmat
from rmavatar.animate.drive import Poser, even_size, render_image
from rmavatar.animate.motion import PoseSequence, recenter_motion
from rmavatar.animate.video import frame_writer, to_uint8


@dataclass
class VideoOptions:
    """How a video is shot: ``size`` image height (width follows ``aspect``; both rounded up to even),
    vertical field of view, background RGB, frame rate."""

    size: int = 512
    aspect: float = 1.0
    fov_deg: float = 30.0
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    fps: float = 30.0
    progress: bool = True


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


def animate_video(poser: Poser, seq: PoseSequence, out: str | os.PathLike, camera: str = "fixed",
                  opts: VideoOptions | None = None) -> int:
    """Render ``seq`` (already frame-selected) re-centred in front of the camera into ``out``.

    ``camera``: 'fixed' (in front) or 'orbit' (one full turn around the body over the clip).
    Returns the number of frames written.
    """
    opts = opts or VideoOptions()
    seq = recenter_motion(seq, poser.root_rest())
    n = len(seq)
    width, height = _frame_size(opts)
    K = intrinsics(width, height, opts.fov_deg)
    sample = poser.vertices(seq.select(_sample_frames(n)))
    center, distance = frame_the_body(sample, opts)
    if camera == "orbit":
        views = orbit_viewmats(center, distance, n)
    elif camera == "fixed":
        views = preset_viewmat("front", center, distance)[None].expand(n, 4, 4)
    else:
        raise ValueError(f"camera must be 'fixed' or 'orbit', got {camera!r}")
    chunk = 16
    with frame_writer(out, opts.fps, width, height) as write:
        bar = tqdm(total=n, desc="animate", unit="frame", disable=not opts.progress)
        for s in range(0, n, chunk):
            part = seq.select(slice(s, s + chunk))
            verts = poser.vertices(part)
            for j in range(len(part)):
                gs = poser.gaussians(verts[j], part.body_pose[j])
                write(to_uint8(render_image(gs, views[s + j], K, width, height, opts.background)))
                bar.update(1)
        bar.close()
    return n


def turntable_video(poser: Poser, out: str | os.PathLike, num_frames: int = 90, pose: str = "tpose",
                    opts: VideoOptions | None = None, elevation_deg: float = 0.0) -> int:
    """A 360-degree orbit around the avatar standing in a rest pose ('tpose', 'apose' or 'train', see
    :meth:`Poser.rest_pose`) into ``out``."""
    opts = opts or VideoOptions()
    seq = poser.rest_pose(pose)
    verts = poser.vertices(seq)
    gs = poser.gaussians(verts[0], seq.body_pose[0])
    width, height = _frame_size(opts)
    K = intrinsics(width, height, opts.fov_deg)
    center, distance = frame_the_body(verts, opts)
    views = orbit_viewmats(center, distance, num_frames, elevation_deg=elevation_deg)
    with frame_writer(out, opts.fps, width, height) as write:
        for view in tqdm(views, desc="turntable", unit="frame", disable=not opts.progress):
            write(to_uint8(render_image(gs, view, K, width, height, opts.background)))
    return num_frames
