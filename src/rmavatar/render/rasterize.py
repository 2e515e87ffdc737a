"""``rasterize``: the one differentiable Gaussian rasterizer every part of rmavatar calls."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rmavatar.render.project import sh_to_rgb
from rmavatar.utils import UserError

BACKENDS = ("auto", "cpu", "gsplat")


class RasterInputError(UserError, ValueError):
    """An argument of ``rasterize`` has the wrong shape or holds NaN/Inf."""


def _check(name: str, t, shape: tuple) -> None:
    _check_shape(name, t, shape)
    if t.numel() and not bool(torch.isfinite(t.detach()).all()):
        bad = int((~torch.isfinite(t.detach())).sum())
        raise RasterInputError(f"{name} holds {bad} NaN/Inf value(s)")


def _check_shape(name: str, t, shape: tuple) -> None:
    if not isinstance(t, Tensor):
        raise RasterInputError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
        raise RasterInputError(f"{name} must have shape {want}, got {list(t.shape)}")
    if not t.is_floating_point():
        raise RasterInputError(f"{name} must be a floating-point tensor, got {t.dtype}")


def _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree,
              values: bool = True) -> int | None:
    check = _check if values else _check_shape
    check("means", means, (None, 3))
    n = means.shape[0]
    check("quats", quats, (n, 4))
    check("scales", scales, (n, 3))
    check("opacities", opacities, (n,))
    if colors is None or not isinstance(colors, Tensor) or colors.dim() not in (2, 3):
        raise RasterInputError("colors must be a tensor [N,3] (RGB) or [N,K,3] (SH coefficients)")
    check("colors", colors, (n, 3) if colors.dim() == 2 else (n, None, 3))
    check("viewmat", viewmat, (4, 4))
    check("K", K, (3, 3))
    if background is not None:
        check("background", background, (3,))
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise RasterInputError(f"{name} must be a positive int, got {v!r}")
    if values and n and bool((quats.detach().norm(dim=-1) == 0).any()):
        raise RasterInputError("quats has zero-length rows; rotations need a non-zero quaternion")
    if colors.dim() == 2:
        if sh_degree is not None:
            raise RasterInputError(f"sh_degree={sh_degree} needs SH colors [N,K,3], got RGB {list(colors.shape)}")
        return None
    k = colors.shape[1]
    if sh_degree is None:
        sh_degree = math.isqrt(k) - 1
        if (sh_degree + 1) ** 2 != k:
            raise RasterInputError(f"colors has K={k} SH coefficients, not a square number; pass sh_degree")
    if not 0 <= sh_degree <= 3:
        raise RasterInputError(f"sh_degree must be 0..3, got {sh_degree}")
    if (sh_degree + 1) ** 2 > k:
        raise RasterInputError(f"sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} SH coefficients, colors has {k}")
    return sh_degree


def _cull_non_finite(means, quats, scales, opacities, colors):
    """Gaussians with a non-finite value or a zero quaternion made harmless on the device (no sync):
    opacity 0 (culled by the opacity-aware box), finite placeholders elsewhere. Gradients of the kept
    rows are unchanged; the culled rows get none from their placeholders."""
    bad = ~(torch.isfinite(means).all(-1) & torch.isfinite(quats).all(-1) & torch.isfinite(scales).all(-1)
            & torch.isfinite(opacities) & torch.isfinite(colors.flatten(1)).all(-1)
            & (quats.detach().abs().amax(-1) > 0))
    col = bad[:, None]
    means = torch.where(col, 0.0, means)
    quats = torch.where(col, quats.new_tensor([1.0, 0.0, 0.0, 0.0]), quats)
    scales = torch.where(col, 1.0, scales)
    opacities = torch.where(bad, 0.0, opacities)
    colors = torch.where(col.view((-1,) + (1,) * (colors.dim() - 1)), 0.0, colors)
    return means, quats, scales, opacities, colors


def rasterize(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int,
    background: Tensor | None = None, sh_degree: int | None = None, backend: str = "auto",
    check: bool = True,
) -> tuple[Tensor, Tensor, dict]:
    """Render 3D Gaussians to an image, differentiably, with gsplat 1.5's conventions.

    Args:
        means [N,3] world positions; quats [N,4] wxyz (normalised here); scales [N,3] linear;
        opacities [N] in [0,1]; colors [N,3] RGB or [N,K,3] SH coefficients (evaluated along the
        camera->Gaussian direction, then ``max(value + 0.5, 0)``);
        viewmat [4,4] world->camera (OpenCV: x right, y down, z forward); K [3,3] pinhole
        intrinsics; width, height in pixels; background [3] colour behind the Gaussians (black
        when None); sh_degree: SH bands to use (default: all of K); backend: "auto" (gsplat for CUDA
        tensors, else the CPU kernels), "cpu" or "gsplat"; check: also refuse NaN/Inf values and
        zero quaternions (each check reads the device: a host sync). With check=False shapes are still
        checked, and Gaussians with a non-finite or zero-length parameter are culled instead (the
        image is then as if they were absent; a training loop's own guard decides what to do).

    Returns:
        image [H,W,3], alpha [H,W,1], and info with "means2d" [N,2] (its ``.grad`` is filled by
        backward: densification reads it), "radii" [N] int32 (largest half extent of the pixel box,
        0 for culled Gaussians), "visible" [N] bool, "depths" [N] camera-space z.

    Raises:
        RasterInputError (a ValueError) naming the argument on bad shapes or NaN/Inf values.
    """
    if backend not in BACKENDS:
        raise RasterInputError(f"backend must be one of {BACKENDS}, got {backend!r}")
    sh_degree = _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree,
                          values=check)
    if backend == "gsplat" or (backend == "auto" and means.is_cuda):
        from rmavatar.render.gsplat_backend import rasterize_gsplat

        if not check:
            means, quats, scales, opacities, colors = _cull_non_finite(means, quats, scales, opacities, colors)
        return rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree
        )

    from rmavatar.render.cpu import composite, project

    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    K = K.to(dtype)
    proj = project(means, quats, scales, opacities, viewmat, K, width, height)
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        rgb = sh_to_rgb(colors, sh_degree, means, campos)
    else:
        rgb = colors
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=means.device)
    image, alpha = composite(
        proj.means2d, proj.conics, rgb, opacities, background,
        proj.radii_xy, proj.depths, proj.visible, width, height,
    )
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    info = {
        "means2d": proj.means2d,
        "radii": proj.radii_xy.amax(dim=-1) if len(means) else proj.radii_xy.new_zeros(0),
        "visible": proj.visible,
        "depths": proj.depths,
        "backend": "cpu",
    }
    return image, alpha, info
