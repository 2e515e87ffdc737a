"""How solid an avatar is: the share of the pixels it covers that it covers opaquely, from every side.

A person is opaque. An avatar trained over one fixed background can instead be semi-transparent with
darkened colours (over white, ``0.75 c + 0.25`` looks like a darker ``c``), which shows as a ghost over
any other background and from other sides. Measured on the avatar in its rest pose, seen from
``views`` azimuths all round at its framing: of the pixels with alpha > COVERED, the share with alpha >
OPAQUE, and the mean alpha over them. (Rendering over black and over white and taking
``alpha = 1 - (white - black)`` gives the same alpha; the rasterizer returns it directly.)
"""

from __future__ import annotations

import numpy as np
import torch

COVERED = 0.1  # a pixel the avatar covers at all
OPAQUE = 0.9  # a pixel it covers solidly


@torch.no_grad()
def solidity(trained, views: int = 8, size: int = 256, pose: str = "tpose") -> dict:
    """{"opaque_share", "mean_alpha", "views", "size", "pose", "per_view": [opaque share per azimuth]} of
    ``trained`` (a TrainedAvatar) in its ``pose`` ("tpose", "apose", "train"), seen from ``views``
    azimuths 0, 360/views, ... at the framing ``rmavatar render`` uses, ``size`` pixels square."""
    from rmavatar.animate.camera import frame_camera
    from rmavatar.render import render_gaussians

    gs = trained.pose(trained.rest_pose(pose), 0)
    covered = opaque = 0
    alpha_sum = 0.0
    per_view = []
    for k in range(views):
        viewmat, K = frame_camera(gs.means, size, azimuth=360.0 * k / views, elevation=0.0)
        _, alpha, _ = render_gaussians(gs, viewmat, K, size, size, background=None)
        a = alpha.reshape(-1).double().cpu().numpy()
        on = a > COVERED
        covered += int(on.sum())
        opaque += int((a > OPAQUE).sum())
        alpha_sum += float(a[on].sum())
        per_view.append(float((a > OPAQUE).sum() / max(on.sum(), 1)))
    return {"opaque_share": opaque / max(covered, 1), "mean_alpha": alpha_sum / max(covered, 1),
            "views": views, "size": size, "pose": pose, "covered_above": COVERED, "opaque_above": OPAQUE,
            "per_view": [round(v, 4) for v in per_view]}


__all__ = ["solidity", "COVERED", "OPAQUE"]
