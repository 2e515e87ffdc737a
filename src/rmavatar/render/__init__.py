"""Differentiable 3D Gaussian rasterization: Numba CPU kernels, gsplat on CUDA, one function.

``rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, background=None,
sh_degree=None, backend="auto") -> (image [H,W,3], alpha [H,W,1], info)``; see its docstring.
"""

from rmavatar.render.rasterize import RasterInputError, rasterize

__all__ = ["rasterize", "RasterInputError"]
