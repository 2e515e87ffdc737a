"""Dense pure-PyTorch reference rasterizer: every pixel against every Gaussian, float64, autograd.

Written independently of the CPU kernels (no tiles, no hand-written backward) to check them. It applies
the same rules: gsplat 1.5 projection and culling, depth order (stable), pixel centres at +0.5,
``alpha = min(0.999, opacity exp(-sigma))``, skip ``alpha < 1/255``, stop before the Gaussian that
would bring the transmittance to ``<= 1e-4``. Memory is O(H W N): small scenes only.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rmavatar.render.project import sh_to_rgb


def _rotation(q: Tensor) -> Tensor:
    """[N,3,3] from wxyz quaternions via the matrix form of q v q* (independent of project.py)."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, v = q[:, :1, None], q[:, 1:]
    eye = torch.eye(3, dtype=q.dtype).expand(len(q), 3, 3)
    vx = torch.zeros(len(q), 3, 3, dtype=q.dtype)
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx = vx - vx.transpose(1, 2)
    return eye + 2 * w * vx + 2 * vx @ vx


def reference_project(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
    width: int, height: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The projection alone (float64 CPU tensors): means2d [N,2], inverse 2D covariances [N,2,2]
    (identity where culled), depths [N] and the kept mask [N] (gsplat's culling)."""
    f64 = torch.float64
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    pc = torch.einsum("ij,nj->ni", Rv, means) + tv
    z = pc[:, 2]
    in_depth = (z >= 0.01) & (z <= 1e10)
    zs = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * pc[:, 0] / zs + cx
    v = fy * pc[:, 1] / zs + cy
    means2d = torch.stack([u, v], -1)

    Rw = Rv @ _rotation(quats)  # camera-from-Gaussian rotation
    L = Rw * scales[:, None, :]
    # Jacobian at the point clamped to 1.3x the frustum, the clamp differentiated (gsplat 1.5.3: a
    # clamped component no longer depends on x or y, only on z through z * limit).
    limx = torch.stack([-(cx / fx + 0.15 * width / fx), (width - cx) / fx + 0.15 * width / fx])
    limy = torch.stack([-(cy / fy + 0.15 * height / fy), (height - cy) / fy + 0.15 * height / fy])
    xc = zs * torch.clamp(pc[:, 0] / zs, limx[0], limx[1])
    yc = zs * torch.clamp(pc[:, 1] / zs, limy[0], limy[1])
    J = torch.zeros(len(means), 2, 3, dtype=f64)
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * xc / zs**2
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * yc / zs**2
    JL = J @ L
    cov = JL @ JL.transpose(1, 2) + 0.3 * torch.eye(2, dtype=f64)
    det = torch.linalg.det(cov) if len(means) else torch.zeros(0, dtype=f64)
    ok = in_depth & (det > 0) & (opacities >= 1 / 255)
    cov = torch.where(ok[:, None, None], cov, torch.eye(2, dtype=f64))
    inv = torch.linalg.inv(cov) if len(means) else cov

    with torch.no_grad():  # culling, as gsplat: opacity-aware box off-screen or empty
        ext = torch.sqrt(2 * torch.log(opacities.clamp_min(1 / 255) * 255)).clamp_max(3.33)
        rx = torch.ceil(ext * cov[:, 0, 0].sqrt())
        ry = torch.ceil(ext * cov[:, 1, 1].sqrt())
        ok = ok & ((rx > 0) | (ry > 0))
        ok = ok & (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
    return means2d, inv, z, ok


def reference_rasterize(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int,
    background: Tensor | None = None, sh_degree: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Same arguments as ``rasterize`` (CPU tensors). Returns image [H,W,3], alpha [H,W,1] and
    means2d [N,2], all float64 and differentiable."""
    f64 = torch.float64
    means, quats, scales, opacities, colors = (t.to(f64) for t in (means, quats, scales, opacities, colors))
    viewmat, K = viewmat.to(f64), K.to(f64)
    bg = torch.zeros(3, dtype=f64) if background is None else background.to(f64)
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    means2d, inv, z, ok = reference_project(means, quats, scales, opacities, viewmat, K, width, height)

    if sh_degree is not None or colors.dim() == 3:
        deg = sh_degree if sh_degree is not None else int(round(colors.shape[1] ** 0.5)) - 1
        rgb = sh_to_rgb(colors, deg, means, -Rv.T @ tv)
    else:
        rgb = colors

    order = torch.sort(z.detach(), stable=True).indices
    order = order[ok[order]]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=f64) + 0.5, torch.arange(width, dtype=f64) + 0.5, indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)  # [P,2]
    d = means2d[order][None, :, :] - pix[:, None, :]  # [P,M,2]
    sigma = 0.5 * torch.einsum("pmi,mij,pmj->pm", d, inv[order], d)
    alpha = torch.clamp(opacities[order][None, :] * torch.exp(-sigma), max=0.999)
    with torch.no_grad():
        used = (sigma >= 0) & (alpha >= 1 / 255)
        t_incl = torch.cumprod(torch.where(used, 1 - alpha, torch.ones_like(alpha)), dim=1)
        used = used & (t_incl > 1e-4)  # transmittance is monotone, so this keeps exactly the prefix
    a = torch.where(used, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(1 - a, dim=1)
    t_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
    weights = a * t_before
    t_final = trans[:, -1] if trans.shape[1] else torch.ones(len(pix), dtype=f64)
    image = weights @ rgb[order] + t_final[:, None] * bg
    return image.reshape(height, width, 3), (1 - t_final).reshape(height, width, 1), means2d
