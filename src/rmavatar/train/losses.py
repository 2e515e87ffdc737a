"""RMAvatar's training loss (paper Eq. 13-17; docs/model.md).

L = rgb L1 + ssim (1 - SSIM) + lpips LPIPS + pos L_pos + scaling L_scaling + offset L_offset, with
  L_pos     = mean_i max(|mu_i| - eps_pos, 0)                (face-local position, eps_pos = 1)
  L_scaling = mean_i || max(exp(log_s_i) - eps_scaling, 0) ||  (face-local scale, eps_scaling = 0.6)
  L_offset  = mean(d_mu^2) + mean(d_r^2) + mean(d_s^2)         (the rectifier's outputs)
The paper writes each regulariser as an L2 norm; per Gaussian we take that norm and average over the
Gaussians so the terms do not grow with the Gaussian count. The offset term is the mean of squares, as
the public release computes it (one mean per offset kind, summed).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

import torch

from rmavatar.utils import UserError
from rmavatar.utils.device import constant
from rmavatar.utils.config import check_fields


@dataclass
class LossConfig:
    """Loss weights: L = rgb L1 + ssim (1-SSIM) + lpips LPIPS + pos L_pos + scaling L_scaling + offset L_offset."""

    rgb: float = 1.5
    ssim: float = 0.2
    lpips: float = 0.05
    pos: float = 0.01
    scaling: float = 1.0
    offset: float = 1.0
    eps_pos: float = 1.0  # L_pos threshold on |mu| (triangle-local units)
    eps_scaling: float = 0.6  # L_scaling threshold on the local (pre-w) scale

    def validate(self) -> "LossConfig":
        check_fields(self, "loss", nonnegative=tuple(f.name for f in dataclasses.fields(self)))
        return self


ImageFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def position_loss(local_means: torch.Tensor, eps: float = 1.0) -> torch.Tensor:
    """mean over Gaussians of max(|mu| - eps, 0); local_means [N,3] in units of the triangle scale."""
    return torch.relu(torch.linalg.vector_norm(local_means, dim=-1) - eps).mean()


def scaling_loss(local_log_scales: torch.Tensor, eps: float = 0.6) -> torch.Tensor:
    """mean over Gaussians of || max(exp(log_s) - eps, 0) ||; local_log_scales [N,3]."""
    return torch.linalg.vector_norm(torch.relu(torch.exp(local_log_scales) - eps), dim=-1).mean()


def offset_loss(d_mu: torch.Tensor, d_s: torch.Tensor, d_r: torch.Tensor) -> torch.Tensor:
    """mean(d_mu^2) + mean(d_r^2) + mean(d_s^2) of the rectifier's outputs [N,3], [N,3], [N,4]."""
    return d_mu.square().mean() + d_r.square().mean() + d_s.square().mean()


def _default_ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    from rmavatar.evaluate import ssim

    return ssim(a, b, check_range=False)


def _default_lpips(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    from rmavatar.evaluate import lpips

    # Renders may overshoot [0, 1] (SH colours are unbounded above); LPIPS sees what the image shows.
    return lpips(a.clamp(0.0, 1.0), b, check_range=False)


def total_loss(
    render: torch.Tensor,
    target: torch.Tensor,
    gaussians: Any,
    weights: LossConfig | None = None,
    lpips_fn: ImageFn | None = None,
    ssim_fn: ImageFn | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The weighted sum of all terms, and each unweighted term (detached) by name.

    render, target [H,W,3]; gaussians: a ``GaussianSet`` (its local_means, local_log_scales and
    offsets feed the regularisers); weights: a ``LossConfig`` (None = the paper's weights; the
    ablations set ``offset`` or ``scaling`` to 0).
    ssim_fn / lpips_fn (a, b) -> scalar similarity / distance; None = ``rmavatar.evaluate``'s.
    Terms with weight 0 are not computed.
    """
    if render.shape != target.shape:
        raise ValueError(f"render {tuple(render.shape)} and target {tuple(target.shape)} differ in shape")
    weights = weights or LossConfig()
    w = {f: float(getattr(weights, f)) for f in ("rgb", "ssim", "lpips", "pos", "scaling", "offset")}

    terms: dict[str, torch.Tensor] = {}
    if w["rgb"]:
        terms["l1"] = (render - target).abs().mean()
    if w["ssim"]:
        terms["ssim"] = 1.0 - (ssim_fn or _default_ssim)(render, target)
    if w["lpips"]:
        terms["lpips"] = (lpips_fn or _default_lpips)(render, target)
    if w["pos"] and getattr(gaussians, "local_means", None) is not None:
        terms["pos"] = position_loss(gaussians.local_means, weights.eps_pos)
    if w["scaling"] and getattr(gaussians, "local_log_scales", None) is not None:
        terms["scaling"] = scaling_loss(gaussians.local_log_scales, weights.eps_scaling)
    if w["offset"] and getattr(gaussians, "offsets", None) is not None:
        terms["offset"] = offset_loss(*gaussians.offsets)
    key_weight = {"l1": "rgb", "ssim": "ssim", "lpips": "lpips", "pos": "pos", "scaling": "scaling", "offset": "offset"}
    if not terms:
        return render.new_zeros(()), {}
    # One dot product instead of a multiply and an add per term (each a kernel launch on a GPU).
    weight = constant(tuple(w[key_weight[name]] for name in terms), render.dtype, render.device)
    loss = torch.stack(tuple(terms.values())) @ weight
    return loss, {k: v.detach() for k, v in terms.items()}
