"""CUDA backend: gsplat 1.5's ``rasterization`` (Apache-2.0), imported only when used.

Outputs are reshaped to the CPU backend's layout: image [H,W,3], alpha [H,W,1], info with
"means2d" [N,2] (gradient filled by backward), "radii" [N] int32, "visible" [N], "depths" [N].
"""

from __future__ import annotations

import weakref

import torch
from torch import Tensor

from rmavatar.utils import UserError


def _import_gsplat():
    try:
        import gsplat
    except ImportError as exc:
        raise UserError(
            "backend 'gsplat' needs the gsplat package (CUDA only): pip install 'rmavatar[cuda]' "
            f"or pip install gsplat==1.5.3 ({exc})"
        ) from exc
    return gsplat


def _check_device(means: Tensor) -> None:
    if not means.is_cuda:
        raise UserError("backend 'gsplat' needs CUDA tensors; use backend='cpu' (or 'auto') on the CPU")


def rasterize_gsplat(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int,
    background: Tensor | None, sh_degree: int | None,
) -> tuple[Tensor, Tensor, dict]:
    """Arguments as ``rasterize`` (already validated); tensors must be on a CUDA device."""
    _check_device(means)
    gsplat = _import_gsplat()
    dtype, device = means.dtype, means.device
    f32 = torch.float32
    bg = None if background is None else background.to(device, f32)[None]
    render, alphas, meta = gsplat.rasterization(
        means.to(f32), quats.to(f32), scales.to(f32), opacities.to(f32), colors.to(f32),
        viewmat.to(device, f32)[None], K.to(device, f32)[None], width, height,
        near_plane=0.01, eps2d=0.3, sh_degree=sh_degree, packed=False, tile_size=16,
        backgrounds=bg, render_mode="RGB", rasterize_mode="classic",
    )
    means2d_c = meta["means2d"]  # [1,N,2]
    radii = meta["radii"][0]  # [N,2] in gsplat >= 1.5, [N] before
    visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
    if radii.dim() == 2:
        radii = radii.amax(dim=-1)
    means2d = means2d_c[0]
    if means2d_c.requires_grad:
        # gsplat composites with the batched tensor, so the [N,2] view is not on the loss path;
        # copy the batched gradient onto it so callers read info["means2d"].grad as on the CPU.
        mirror_grad(means2d_c, means2d)
    info = {
        "means2d": means2d,
        "radii": radii.to(torch.int32),
        "visible": visible,
        "depths": meta["depths"][0],
        "backend": "gsplat",
    }
    return render[0].to(dtype), alphas[0].to(dtype), info


def mirror_grad(batched: Tensor, view: Tensor) -> None:
    """Give ``view`` (= ``batched[0]``, not itself on the loss path) the gradient that reaches ``batched``
    [1,...], in ``view.grad``. The hook holds ``view`` weakly: a closure holding the view would make a
    cycle through the autograd graph (view -> its grad_fn -> batched's grad_fn -> the hook) that the
    collector cannot see, and every step's graph, parameters' gradient accumulators included, would
    live on."""
    view.retain_grad()
    ref = weakref.ref(view)

    def _copy_grad(grad: Tensor) -> None:
        v = ref()
        if v is not None:
            g = grad[0].detach()
            v.grad = g.clone() if v.grad is None else v.grad + g

    batched.register_hook(_copy_grad)
