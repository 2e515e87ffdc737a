"""Synthetic Gaussian scenes for benchmarks, demos and tests: a coarse human-sized figure."""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Body parts as ellipsoids (centre xyz, radii xyz) in metres, OpenCV-like world: y down, z away from camera.
_PARTS = (
    ((0.0, -0.72, 0.0), (0.10, 0.12, 0.11)),  # head
    ((0.0, -0.57, 0.0), (0.05, 0.05, 0.05)),  # neck
    ((0.0, -0.25, 0.0), (0.18, 0.28, 0.11)),  # torso
    ((0.0, 0.07, 0.0), (0.17, 0.11, 0.11)),  # hips
    ((-0.24, -0.30, 0.0), (0.05, 0.22, 0.05)),  # upper arms
    ((0.24, -0.30, 0.0), (0.05, 0.22, 0.05)),
    ((-0.27, 0.08, 0.02), (0.04, 0.20, 0.04)),  # forearms
    ((0.27, 0.08, 0.02), (0.04, 0.20, 0.04)),
    ((-0.09, 0.42, 0.0), (0.08, 0.28, 0.08)),  # thighs
    ((0.09, 0.42, 0.0), (0.08, 0.28, 0.08)),
    ((-0.09, 0.85, 0.0), (0.06, 0.24, 0.06)),  # shins
    ((0.09, 0.85, 0.0), (0.06, 0.24, 0.06)),
)


def figure_scene(
    n: int, seed: int = 0, sh_degree: int | None = 3, dtype=torch.float32, disc_scale: float = 1.5
) -> dict[str, Tensor]:
    """``n`` surface Gaussians on a 1.8 m figure at the origin, sized like a trained avatar's:
    flat discs whose standard deviation is ``disc_scale`` times the point spacing (log-normal
    spread). Returns means, quats, scales, opacities and colors ([N,3] if sh_degree is None, else SH [N,(d+1)^2,3])."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.tensor([p[0] for p in _PARTS], dtype=torch.float64)
    radii = torch.tensor([p[1] for p in _PARTS], dtype=torch.float64)
    # Approximate ellipsoid areas (Knud Thomsen) to spread points evenly.
    a, b, c = radii.unbind(-1)
    p = 1.6075
    area = 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    part = torch.multinomial(area / area.sum(), n, replacement=True, generator=g)
    u = torch.randn(n, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    means = centres[part] + u * radii[part]
    normal = u / radii[part]
    normal = normal / normal.norm(dim=-1, keepdim=True)
    # Rotation taking local z to the surface normal, with a random spin about it.
    spin = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    axis = torch.cross(z, normal, dim=-1)
    s = axis.norm(dim=-1).clamp_min(1e-9)
    ang = torch.atan2(s, normal[:, 2])
    q_align = torch.cat([torch.cos(ang / 2)[:, None], torch.sin(ang / 2)[:, None] * axis / s[:, None]], -1)
    q_spin = torch.stack([torch.cos(spin / 2), torch.zeros(n, dtype=torch.float64),
                          torch.zeros(n, dtype=torch.float64), torch.sin(spin / 2)], -1)
    quats = _qmul(q_align, q_spin)
    spacing = math.sqrt(float(area.sum()) / n)
    # Trained avatars overlap their neighbours, hence discs wider than the spacing by default.
    tang = disc_scale * spacing * torch.exp(0.4 * torch.randn(n, 2, generator=g, dtype=torch.float64))
    scales = torch.cat([tang, 0.15 * tang[:, :1]], -1)
    opacities = torch.sigmoid(2.0 + 1.5 * torch.randn(n, generator=g, dtype=torch.float64))
    # Skin-and-cloth palette varied per part, plus noise.
    palette = torch.rand(len(_PARTS), 3, generator=g, dtype=torch.float64) * 0.6 + 0.2
    rgb = (palette[part] + 0.08 * torch.randn(n, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    if sh_degree is None:
        colors = rgb
    else:
        colors = 0.05 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
        colors[:, 0] = (rgb - 0.5) / 0.28209479177387814
    out = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors)
    return {k: v.to(dtype) for k, v in out.items()}


def _qmul(p: Tensor, q: Tensor) -> Tensor:
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], -1)


def orbit_camera(size: int, angle_deg: float = 20.0, distance: float = 3.0, dtype=torch.float32) -> tuple[Tensor, Tensor]:
    """A square ``size`` camera looking at the origin from ``distance`` metres, turned ``angle_deg``
    about the vertical axis, framing a 1.8 m figure. Returns viewmat [4,4] (OpenCV) and K [3,3]."""
    th = math.radians(angle_deg)
    # Camera centre on a circle in the x-z plane; it looks toward the origin along +z_cam.
    centre = torch.tensor([-distance * math.sin(th), 0.0, -distance * math.cos(th)], dtype=torch.float64)
    fwd = -centre / centre.norm()
    down = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    right = torch.cross(down, fwd, dim=-1)
    right = right / right.norm()
    R = torch.stack([right, down, fwd])  # rows: camera axes in world coordinates
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ centre
    f = 0.85 * size * distance / 1.8
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float64)
    return viewmat.to(dtype), K.to(dtype)
