"""The one forward path: a frame's posed body -> Gaussians on the mesh -> rectifier -> rasterizer.

Training, evaluation, test-time pose fitting, the benchmarks and the viewer all draw an avatar through
:func:`render_frame`, so a frame is rendered the same way wherever it is scored or looked at.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from rmavatar.avatar.model import Avatar, AvatarExtras
from rmavatar.render.gaussians import GaussianSet, render_gaussians


@dataclass
class RenderedFrame:
    """One rendered frame and what made it."""

    image: torch.Tensor  # [H,W,3] over the background
    alpha: torch.Tensor  # [H,W,1] accumulated opacity
    info: dict  # the rasterizer's (density control reads its screen-space gradients)
    gaussians: GaussianSet  # the world-space Gaussians drawn
    extras: AvatarExtras  # what the training losses read besides the Gaussians
    colors: torch.Tensor | None  # [N,3] the view-dependent colours, when held (``hold_colors``) or given


def pose_frame(avatar: Avatar, vertices: torch.Tensor | None, body_pose: torch.Tensor | None,
               viewmat: torch.Tensor | None, *, table: torch.Tensor | None = None,
               rectified: tuple | None = None) -> tuple[GaussianSet, AvatarExtras, torch.Tensor | None]:
    """The first half of :func:`render_frame`: (world-space Gaussians, extras, view-dependent colours
    [N,3] seen from ``viewmat`` [4,4] on the Gaussians' device and dtype; None without ``viewmat``).
    Only tensor operations, no host reads: a training step replays it as a CUDA graph."""
    gs, extras = avatar.forward_with_extras(vertices, body_pose, rectified=rectified, table=table)
    return gs, extras, None if viewmat is None else gs.colors(viewmat)


def render_frame(avatar: Avatar, vertices: torch.Tensor | None, body_pose: torch.Tensor | None, camera: Any,
                 background: torch.Tensor | None, *, table: torch.Tensor | None = None,
                 rectified: tuple | None = None, colors: torch.Tensor | None = None,
                 hold_colors: bool = False, check: bool = True) -> RenderedFrame:
    """``avatar`` posed on the mesh ``vertices`` [V,3] for ``body_pose`` [69], seen by ``camera``
    (anything with viewmat [4,4], K [3,3], width, height: a :class:`rmavatar.render.Camera`, or the
    tensors a training step keeps on its device), over ``background`` [3] (None: transparent black).

    table, rectified: as :meth:`Avatar.forward_with_extras` (a cached face table; the rectifier's
    held outputs); colors [N,3]: the view-dependent colours, when held; ``hold_colors``: compute them
    without gradient (returned in ``colors``, for the caller to hold; test-time pose fitting does);
    check: as :func:`rmavatar.render.rasterize`'s (False in training, whose guard stays on the device).
    Differentiable; wrap in ``torch.no_grad()`` to only look."""
    gs, extras, _ = pose_frame(avatar, vertices, body_pose, None, table=table, rectified=rectified)
    if colors is None and hold_colors:
        with torch.no_grad():
            colors = gs.colors(torch.as_tensor(camera.viewmat).to(gs.means))
    image, alpha, info = render_gaussians(gs, camera.viewmat, camera.K, camera.width, camera.height,
                                          background=background, check=check, colors=colors)
    return RenderedFrame(image, alpha, info, gs, extras, colors)
