"""``GaussianSet``, the one type for world-space Gaussians, and :func:`render_gaussians`, which draws one.

An avatar posed for a frame, a PLY read from disk and a synthetic scene are all a GaussianSet; every
part of rmavatar that draws Gaussians goes through :func:`render_gaussians`, so view-dependent colour
is evaluated the same way everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from rmavatar.render.project import rotate_sh, sh_rotation_matrices, view_colors
from rmavatar.render.rasterize import rasterize


@dataclass
class GaussianSet:
    """World-space Gaussians ready for ``rasterize``.

    means [N,3], quats [N,4] (wxyz, unit), scales [N,3] (linear), opacities [N] in [0,1],
    sh [N,K,3] with K = (sh_degree+1)^2 (colour = 0.5 + SH evaluation, the gsplat convention),
    expressed in the axes of ``frames`` [N,3,3] (each Gaussian's local -> world rotation; None means
    world axes, as in a 3DGS file): :meth:`colors` evaluates them along each Gaussian's local view
    direction; :meth:`world_sh` gives them in world axes for standard 3DGS files.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    sh_degree: int
    frames: torch.Tensor | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return self.means.shape[0]

    def colors(self, viewmat: torch.Tensor) -> torch.Tensor:
        """RGB [N,3] seen by the camera ``viewmat`` [4,4] (world -> camera), for ``rasterize``.

        With ``frames`` the view dependence lives in the Gaussians' own axes, so it turns with the body:
        a fixed camera watching a turning person shows each surface from many local directions (in world
        axes it would only ever see one, and every other view would extrapolate)."""
        return view_colors(self.sh, self.sh_degree, self.means, viewmat, self.frames)

    def world_sh(self) -> torch.Tensor:
        """``sh`` [N,K,3] turned into world axes, as standard 3DGS readers evaluate them (for export)."""
        if self.frames is None or self.sh_degree == 0:
            return self.sh
        return rotate_sh(self.sh, sh_rotation_matrices(self.frames, self.sh_degree))


def render_gaussians(gs: GaussianSet, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                     background: torch.Tensor | None = None, backend: str = "auto", check: bool = True,
                     colors: torch.Tensor | None = None):
    """Rasterize ``gs`` seen by the camera (viewmat [4,4] world -> camera, K [3,3]) into a
    ``width`` x ``height`` image: returns (image [H,W,3], alpha [H,W,1], info) as :func:`rasterize` does.

    viewmat, K and background [3] may live on any device or be numpy arrays: they are moved to the
    Gaussians' device and dtype. Differentiable; wrap in ``torch.no_grad()`` to only look.
    ``check``: as :func:`rasterize`'s (False in training, whose guard stays on the device).
    ``colors`` [N,3]: ``gs.colors(viewmat)`` when the caller already has it (test-time pose fitting holds
    the view-dependent colours between refreshes).
    """
    like = gs.means
    viewmat, K = _like(viewmat, like), _like(K, like)
    if background is not None:
        background = _like(background, like)
    colors = gs.colors(viewmat) if colors is None else colors
    return rasterize(gs.means, gs.quats, gs.scales, gs.opacities, colors, viewmat, K, width, height,
                     background=background, backend=backend, check=check)


def _like(x, like: torch.Tensor) -> torch.Tensor:
    """``x`` (a tensor, numpy array or sequence) as a tensor of ``like``'s dtype and device."""
    if isinstance(x, torch.Tensor):
        return x.to(like)
    return torch.tensor(np.asarray(x), dtype=like.dtype, device=like.device)  # a copy: x may be read-only
