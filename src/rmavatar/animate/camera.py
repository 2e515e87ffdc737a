"""Cameras for showing an avatar: look-at view matrices, pinhole intrinsics, fixed and orbit paths.

World convention is SMPL's (y up, the body faces +z, metres); cameras are OpenCV (x right, y down,
z forward) world->camera ``viewmat`` [4,4], as the rasterizer takes them.
"""

from __future__ import annotations

import math

import torch

UP = (0.0, 1.0, 0.0)


def look_at(eye, target, up=UP) -> torch.Tensor:
    """World->camera OpenCV view matrix [4,4] of a camera at ``eye`` [3] looking at ``target`` [3]."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    up = torch.as_tensor(up, dtype=torch.float64)
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    return view.float()


def intrinsics(width: int, height: int, fov_y_deg: float) -> torch.Tensor:
    """Pinhole K [3,3] with square pixels, the principal point at the image centre."""
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def framing_distance(points: torch.Tensor, center, fov_y_deg: float, aspect: float, margin: float = 1.1) -> float:
    """Camera distance from ``center`` at which all ``points`` [P,3] fit the view from any side.

    Uses the bounding sphere about ``center`` so the distance does not change while orbiting.
    """
    center = torch.as_tensor(center, dtype=points.dtype)
    radius = float((points - center).norm(dim=-1).max()) * margin
    half = math.radians(fov_y_deg) / 2
    half = min(half, math.atan(math.tan(half) * aspect))  # the narrower field of view decides
    return radius / math.sin(half)


def orbit_viewmats(center, distance: float, num: int, start_deg: float = 0.0, turns: float = 1.0,
                   elevation_deg: float = 0.0) -> torch.Tensor:
    """``num`` cameras [num,4,4] circling ``center`` about the y axis, looking at it.

    Azimuth 0 is in front of the body (on +z); ``turns`` = 1 is a full circle over the path without
    repeating the first view at the end, so the path loops seamlessly.
    """
    center = torch.as_tensor(center, dtype=torch.float64)
    elev = math.radians(elevation_deg)
    views = []
    for i in range(num):
        az = math.radians(start_deg) + 2 * math.pi * turns * i / max(num, 1)
        offset = torch.tensor([math.sin(az) * math.cos(elev), math.sin(elev), math.cos(az) * math.cos(elev)],
                              dtype=torch.float64)
        views.append(look_at(center + distance * offset, center))
    return torch.stack(views)


def preset_viewmat(name: str, center, distance: float) -> torch.Tensor:
    """A named camera [4,4]: 'front' (on +z), 'back' (-z), 'left'/'side' (the body's left, +x), 'right' (-x)."""
    az = {"front": 0.0, "side": 90.0, "left": 90.0, "back": 180.0, "right": -90.0}[name]
    return orbit_viewmats(center, distance, 1, start_deg=az)[0]


def frame_camera(means, size: int, azimuth: float = 20.0, elevation: float = 0.0, fov: float = 30.0):
    """A square ``size`` camera (viewmat [4,4] OpenCV world -> camera, K [3,3]) looking at Gaussians at
    ``means`` [N,3] in a y-up world.

    It looks at the centre of their robust bounding box (the 1% and 99% quantiles per axis) from
    ``azimuth`` degrees about the vertical (0: from +z, an avatar's front; positive: towards +x, its
    left) and ``elevation`` degrees above the horizontal, at the distance where a sphere 10% larger than
    the one about that centre holding 99% of the Gaussians fills the ``fov`` (vertical field of view,
    degrees). Outliers (a stray Gaussian, a far background) do not move the camera away; depends on
    the positions only, so the same Gaussians read from a PLY get the very same camera.
    """
    pts = means.detach().to("cpu", torch.float64).reshape(-1, 3)
    pts = pts[:: max(1, math.ceil(len(pts) / 1_000_000))]  # torch.quantile takes at most 16M values
    if len(pts) == 0:
        centre, radius = torch.zeros(3, dtype=torch.float64), 1.0
    else:
        q = torch.tensor([0.01, 0.99], dtype=torch.float64)
        lo, hi = torch.quantile(pts, q, dim=0)
        centre = 0.5 * (lo + hi)
        radius = float(torch.quantile((pts - centre).norm(dim=-1), 0.99))
    radius = max(1.1 * radius, 1e-3)
    distance = radius / math.sin(math.radians(fov) / 2)
    viewmat = orbit_viewmats(centre, distance, 1, start_deg=azimuth, elevation_deg=elevation)[0]
    return viewmat, intrinsics(size, size, fov)
