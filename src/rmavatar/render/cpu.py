"""CPU backend: projection, tile binning and compositing in Numba, wrapped as torch autograd functions."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rmavatar.render import kernels, kernels_project
from rmavatar.render._numba import numba
from rmavatar.render.project import Projection


# The kernels work in float64 on numpy arrays: the dtype conversions to and from the tensors' dtype are
# done in numpy, where this backend's data lives, not as tensor operations (a CPU-only path: CUDA
# tensors take gsplat, which never converts).
def _np64(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


def _grad64(g: Tensor | None, shape: tuple) -> np.ndarray:
    """An incoming gradient for the kernels; None (the output was not used) is zeros, made here in numpy
    rather than by autograd (``set_materialize_grads(False)``)."""
    return np.zeros(shape) if g is None else _np64(g)


_NUMPY_DTYPES = {torch.float16: np.float16, torch.float32: np.float32, torch.float64: np.float64}


def _tensor(a: np.ndarray, device: torch.device, dtype: torch.dtype) -> Tensor:
    """A kernel output as a tensor of ``dtype`` on ``device``."""
    if dtype not in _NUMPY_DTYPES:  # bfloat16 has no numpy dtype
        return torch.from_numpy(a).to(device, dtype)
    return torch.from_numpy(np.ascontiguousarray(a, dtype=_NUMPY_DTYPES[dtype])).to(device)


class _Binning:
    """Depth-sorted tile lists for one view (plain numpy, not differentiable)."""

    def __init__(self, means2d: Tensor, radii_xy: Tensor, depths: Tensor, visible: Tensor, width: int, height: int):
        self.width, self.height = int(width), int(height)
        self.tiles_x = math.ceil(self.width / kernels.TILE)
        self.tiles_y = math.ceil(self.height / kernels.TILE)
        vis_ids = np.flatnonzero(visible.cpu().numpy())
        d = _np64(depths)[vis_ids]
        # Stable sort: equal depths keep index order, matching a stable global sort.
        order = vis_ids[np.argsort(d, kind="stable")].astype(np.int64)
        radii = np.ascontiguousarray(radii_xy.detach().cpu().numpy().astype(np.int64))
        self.offsets, self.ids = kernels.bin_tiles(_np64(means2d), radii, order, self.tiles_x, self.tiles_y)
        self.tile_order = kernels.interleaved_tiles(self.tiles_x * self.tiles_y, numba.get_num_threads())


class _Composite(torch.autograd.Function):
    """(means2d [N,2], conics [N,3], colors [N,3], opacities [N], background [3]) -> image [H,W,3],
    alpha [H,W,1], with an analytic backward."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, background, binning: _Binning):
        arrays = (_np64(means2d), _np64(conics), _np64(colors), _np64(opacities), _np64(background))
        image, t_final, n_last = kernels.composite_forward(
            *arrays, binning.offsets, binning.ids, binning.width, binning.height, binning.tiles_x,
            binning.tile_order,
        )
        ctx.set_materialize_grads(False)
        ctx.arrays = arrays
        ctx.binning = binning
        ctx.t_final = t_final
        ctx.n_last = n_last
        ctx.device = means2d.device
        ctx.dtypes = [t.dtype for t in (means2d, conics, colors, opacities, background)]
        dtype = means2d.dtype
        image_t = _tensor(image, means2d.device, dtype)
        alpha_t = _tensor(1.0 - t_final, means2d.device, dtype)[..., None]
        return image_t, alpha_t

    @staticmethod
    def backward(ctx, v_image, v_alpha):
        b = ctx.binning
        grads, v_bg = kernels.composite_backward(
            *ctx.arrays, b.offsets, b.ids, b.width, b.height, b.tiles_x, b.tile_order, ctx.t_final, ctx.n_last,
            _grad64(v_image, (b.height, b.width, 3)), _grad64(None if v_alpha is None else v_alpha[..., 0],
                                                             (b.height, b.width)),
        )
        n = ctx.arrays[0].shape[0]
        per_g = kernels.sum_per_gaussian(grads, b.ids, n)
        grads = (per_g[:, 0:2], per_g[:, 2:5], per_g[:, 5:8], per_g[:, 8], v_bg)
        return tuple(_tensor(g, ctx.device, d) for g, d in zip(grads, ctx.dtypes)) + (None,)


class _Project(torch.autograd.Function):
    """(means [N,3], quats [N,4], scales [N,3]) -> means2d [N,2], conics [N,3], depths [N], plus
    radii_xy [N,2] and visible [N] (not differentiable); opacities only shape the pixel box."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height):
        arrays = (_np64(means), _np64(quats), _np64(scales))
        view, intr = _np64(viewmat), _np64(K)
        means2d, conics, depths, radii, visible, has_2d = kernels_project.project_forward(
            *arrays, _np64(opacities), view, intr, width, height
        )
        ctx.set_materialize_grads(False)
        ctx.saved = (arrays, view, intr, width, height, conics, has_2d)
        ctx.dtypes = [t.dtype for t in (means, quats, scales)]
        ctx.device = means.device
        dev, dt = means.device, means.dtype
        radii_t = torch.from_numpy(radii).to(dev)
        visible_t = torch.from_numpy(visible).to(dev)
        ctx.mark_non_differentiable(radii_t, visible_t)
        return (
            _tensor(means2d, dev, dt), _tensor(conics, dev, dt), _tensor(depths, dev, dt), radii_t, visible_t,
        )

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii, _v_visible):
        arrays, view, intr, width, height, conics, has_2d = ctx.saved
        grads = kernels_project.project_backward(
            *arrays, view, intr, width, height, conics, has_2d, _grad64(v_means2d, (len(conics), 2)),
            _grad64(v_conics, conics.shape), _grad64(v_depths, (len(conics),)),
        )
        out = tuple(_tensor(g, ctx.device, d) for g, d in zip(grads, ctx.dtypes))
        return out + (None, None, None, None, None)


def project(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
            width: int, height: int) -> Projection:
    """Numba version of ``project.project_gaussians`` (same rules and outputs), with an analytic
    backward w.r.t. means, quats and scales."""
    means2d, conics, depths, radii, visible = _Project.apply(means, quats, scales, opacities, viewmat, K, width, height)
    return Projection(means2d, conics, depths, radii, visible)


def composite(
    means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, background: Tensor,
    radii_xy: Tensor, depths: Tensor, visible: Tensor, width: int, height: int,
) -> tuple[Tensor, Tensor]:
    """Alpha-composite projected Gaussians front to back. Shapes as in ``project.Projection``;
    colors [N,3], opacities [N], background [3]. Returns image [H,W,3] and alpha [H,W,1]."""
    binning = _Binning(means2d, radii_xy, depths, visible, width, height)
    return _Composite.apply(means2d, conics, colors, opacities, background, binning)
