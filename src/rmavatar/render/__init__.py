"""Differentiable 3D Gaussian rasterization: Numba CPU kernels, gsplat on CUDA, one function.

``rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, background=None,
sh_degree=None, backend="auto") -> (image [H,W,3], alpha [H,W,1], info)``; see its docstring.
``GaussianSet`` is the one type for world-space Gaussians; ``render_gaussians(gs, viewmat, K, width,
height, background)`` draws one with its view-dependent colours; ``composite(image, mask, background)``
makes a frame's target.
"""

from rmavatar.render.camera import Camera
from rmavatar.render.composite import composite
from rmavatar.render.gaussians import GaussianSet, render_gaussians
from rmavatar.render.rasterize import RasterInputError, rasterize

__all__ = ["Camera", "GaussianSet", "RasterInputError", "composite", "rasterize", "render_gaussians"]
