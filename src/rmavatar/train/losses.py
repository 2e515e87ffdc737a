"""RMAvatar's training loss (paper Eq. 13-17; docs/model.md).

L = rgb L1 + ssim (1 - SSIM) + lpips LPIPS + pos L_pos + scaling L_scaling + offset L_offset
    + mask L_mask, with
  L_pos     = mean_i max(|mu_i| - eps_pos, 0)                (face-local position, eps_pos = 1)
  L_scaling = mean_i || max(exp(log_s_i) - eps_scaling, 0) ||  (face-local scale, eps_scaling = 0.6)
  L_offset  = mean(d_mu^2) + mean(d_r^2) + mean(d_s^2)         (the rectifier's outputs)
  L_mask    = mean over pixels |alpha - mask|                  (the render's opacity against the person mask)
The paper writes each regulariser as an L2 norm; per Gaussian we take that norm and average over the
Gaussians so the terms do not grow with the Gaussian count. The offset term is the mean of squares, as
the public release computes it (one mean per offset kind, summed).

LPIPS may be taken on a window around the person (``LossConfig.lpips_region: person``, docs/train.md):
outside the mask the target is the plain background, which the L1 term already covers. A window is two
index tensors (rows [h], cols [w]) of one size for the whole run, so a step's shapes never depend on the
frame.

L_mask is not in the paper. With one fixed background a semi-transparent avatar with darkened colours
renders the same as an opaque one (over white, 0.75 c + 0.25 looks like a darker c), and real masks'
soft edges invite it: the avatar becomes a ghost from other sides and over other backgrounds. Several
peers (GART, 3DGS-Avatar) add this term.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Callable

import torch

from rmavatar.avatar.model import AvatarExtras
from rmavatar.utils import UserError
from rmavatar.utils.device import constant
from rmavatar.utils.config import check_fields


LPIPS_REGIONS = ("person", "frame")


@dataclass
class LossConfig:
    """Loss weights: L = rgb L1 + ssim (1-SSIM) + lpips LPIPS + pos L_pos + scaling L_scaling + offset L_offset."""

    rgb: float = 1.5  # weight of the L1 colour difference between render and target
    ssim: float = 0.2  # weight of 1 - SSIM(render, target)
    lpips: float = 0.05  # weight of LPIPS(render clamped to [0, 1], target)
    pos: float = 0.01  # weight of L_pos, which keeps Gaussians near their triangle
    scaling: float = 1.0  # weight of L_scaling, which keeps face-local scales small (0: the paper's ablation)
    offset: float = 1.0  # weight of L_offset, which keeps the rectifier's offsets small (0: the paper's ablation)
    mask: float = 0.0  # weight of L_mask: mean |alpha - mask| between the render's opacity and the person mask
    eps_pos: float = 1.0  # L_pos threshold on |mu| (triangle-local units)
    eps_scaling: float = 0.6  # L_scaling threshold on the local (pre-w) scale
    lpips_region: str = "frame"  # LPIPS on: "frame" (the whole image), "person" (a window around the mask: faster)

    def validate(self) -> "LossConfig":
        if self.lpips_region not in LPIPS_REGIONS:
            raise UserError(f"loss.lpips_region must be one of {', '.join(LPIPS_REGIONS)}, not {self.lpips_region!r}")
        weights = tuple(f.name for f in dataclasses.fields(self) if f.name != "lpips_region")
        check_fields(self, "loss", nonnegative=weights)
        return self


ImageFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _row_mean(values: torch.Tensor, row_weights: torch.Tensor | None) -> torch.Tensor:
    """Mean over rows of ``values`` [N]; with ``row_weights`` [N] (capacity buffers: 1/live for a live
    row, 0 for an unused one) the mean over the live rows."""
    return values.mean() if row_weights is None else (values * row_weights).sum()


def position_loss(local_means: torch.Tensor, eps: float = 1.0, row_weights: torch.Tensor | None = None) -> torch.Tensor:
    """mean over Gaussians of max(|mu| - eps, 0); local_means [N,3] in units of the triangle scale."""
    return _row_mean(torch.relu(torch.linalg.vector_norm(local_means, dim=-1) - eps), row_weights)


def scaling_loss(local_log_scales: torch.Tensor, eps: float = 0.6, row_weights: torch.Tensor | None = None) -> torch.Tensor:
    """mean over Gaussians of || max(exp(log_s) - eps, 0) ||; local_log_scales [N,3]."""
    return _row_mean(torch.linalg.vector_norm(torch.relu(torch.exp(local_log_scales) - eps), dim=-1), row_weights)


def mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """mean |alpha - mask| over pixels: the render's accumulated opacity [H,W,1] against the frame's
    person mask [H,W,1] (or [H,W]) in 0..1."""
    return (alpha.reshape(mask.shape) - mask).abs().mean()


def offset_loss(d_mu: torch.Tensor, d_s: torch.Tensor, d_r: torch.Tensor,
                row_weights: torch.Tensor | None = None) -> torch.Tensor:
    """mean(d_mu^2) + mean(d_r^2) + mean(d_s^2) of the rectifier's outputs [N,3], [N,3], [N,4]."""
    if row_weights is None:
        return d_mu.square().mean() + d_r.square().mean() + d_s.square().mean()
    return sum((d.square().mean(-1) * row_weights).sum() for d in (d_mu, d_r, d_s))


class _Regularisers(torch.autograd.Function):
    """(L_pos, L_scaling, L_offset) [3] in one go, with the backward written out (about half the
    operations autograd records for the three functions above, which define them).

    (local_means [N,3], local_log_scales [N,3], d_mu [N,3], d_s [N,3], d_r [N,4], eps_pos, eps_scaling,
    row_weights [N] or None: each row's weight in the means, as :func:`position_loss`'s)."""

    @staticmethod
    def forward(ctx, means, log_scales, d_mu, d_s, d_r, eps_pos, eps_scaling, row_weights=None):
        n = torch.linalg.vector_norm(means, dim=-1)
        excess = torch.relu(n - eps_pos)
        e = torch.exp(log_scales)
        over = torch.relu(e - eps_scaling)
        over_norm = torch.linalg.vector_norm(over, dim=-1)
        offsets = torch.cat((d_mu, d_s, d_r), dim=-1)  # [N,10]
        # per-Gaussian sums (weighted by row_weights, which hold the 1/N), then one product with the
        # weights that make each term's mean
        if row_weights is None:
            parts = torch.cat((excess.sum().view(1), over_norm.sum().view(1),
                               torch.einsum("ni,ni->i", offsets, offsets)))  # [12]
        else:
            # products, then sums (cascaded: a matrix-vector product adds 10^5 rows in one long run)
            parts = torch.cat(((torch.stack((excess, over_norm)) * row_weights).sum(-1),
                               (offsets.square() * row_weights.unsqueeze(-1)).sum(0)))
        count = means.shape[0] if row_weights is None else 1
        weights, _ = _regulariser_weights(count, (d_mu.shape[1], d_s.shape[1], d_r.shape[1]), means.dtype,
                                          means.device)
        ctx.count = count
        ctx.save_for_backward(means, n, excess, e, over, over_norm, offsets, row_weights)
        ctx.widths = (d_mu.shape[1], d_s.shape[1], d_r.shape[1])
        return weights @ parts

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        means, n, excess, e, over, over_norm, offsets, row_weights = ctx.saved_tensors
        _, backward_weights = _regulariser_weights(ctx.count, ctx.widths, means.dtype, means.device)
        c = torch.mv(backward_weights, grad)  # [12]: d loss / d each per-Gaussian sum, times 2 for the squares
        tiny = torch.finfo(n.dtype).tiny  # |mu| = 0 or |over| = 0: that Gaussian's term has no gradient
        rows = c[:2] if row_weights is None else row_weights.unsqueeze(-1) * c[:2]  # [N,2] or [2]
        # d|mu|/dmu = mu / |mu| where |mu| > eps_pos (sign(excess) is that mask)
        g_means = means * (torch.sign(excess) / n.clamp_min(tiny) * rows[..., 0]).unsqueeze(-1)
        # d|over|/dlog_s = over / |over| * e (over = 0 where the relu is off)
        g_scales = over * e / over_norm.clamp_min(tiny).unsqueeze(-1) * rows[..., 1:]
        g_off = offsets * c[2:]
        if row_weights is not None:
            g_off = g_off * row_weights.unsqueeze(-1)
        return g_means, g_scales, *g_off.split(ctx.widths, dim=-1), None, None, None

    @staticmethod
    def reference(means, log_scales, d_mu, d_s, d_r, eps_pos, eps_scaling, row_weights=None) -> torch.Tensor:
        """The same [3] under plain autograd: the three functions that define the terms (for tests)."""
        return torch.stack((position_loss(means, eps_pos, row_weights), scaling_loss(log_scales, eps_scaling, row_weights),
                            offset_loss(d_mu, d_s, d_r, row_weights)))


@functools.lru_cache(maxsize=32)
def _regulariser_weights(n: int, widths: tuple, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """[3,12] weights from _Regularisers' per-Gaussian sums to (L_pos, L_scaling, L_offset): 1/N for the
    first two, 1/(N * width) for each offset column; and their transpose [12,3] for the backward, with
    the offset rows doubled. Made once per Gaussian count (density control changes it)."""
    rows = [[0.0] * (2 + sum(widths)) for _ in range(3)]
    rows[0][0] = rows[1][1] = 1.0 / n
    col = 2
    for width in widths:
        for _ in range(width):
            rows[2][col] = 1.0 / (n * width)
            col += 1
    doubled = [[v if i < 2 else 2 * v for v in column] for i, column in enumerate(zip(*rows))]
    return (torch.tensor(rows, dtype=dtype, device=device), torch.tensor(doubled, dtype=dtype, device=device))


def _default_ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    from rmavatar.evaluate import ssim

    return ssim(a, b, check_range=False)


class _Clamp01(torch.autograd.Function):
    """``x.clamp(0, 1)`` with clamp's gradient (passed where 0 <= x <= 1) as one select against a mask
    made in the forward, where autograd's clamp backward takes five operations."""

    @staticmethod
    def forward(ctx, x):
        out = x.clamp(0.0, 1.0)
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(out == x)  # False outside [0, 1] and for NaN, as clamp's backward
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        (inside,) = ctx.saved_tensors
        return torch.where(inside, grad, constant(0.0, grad.dtype, grad.device))

    @staticmethod
    def reference(x: torch.Tensor) -> torch.Tensor:
        """The same under plain autograd (for tests)."""
        return x.clamp(0.0, 1.0)


def _default_lpips(a: torch.Tensor, b: torch.Tensor, frame: tuple[int, int] | None = None) -> torch.Tensor:
    """LPIPS of a render to a target [h,w,3]; ``frame``: the size of the image they are a window of
    (``LPIPSAlex.forward``)."""
    from rmavatar.evaluate import lpips
    from rmavatar.evaluate.lpips_net import load_lpips

    # Renders may overshoot [0, 1] (SH colours are unbounded above); LPIPS sees what the image shows.
    if frame is None:
        return lpips(_Clamp01.apply(a), b, check_range=False)
    x, y = _Clamp01.apply(a).permute(2, 0, 1).unsqueeze(0), b.permute(2, 0, 1).unsqueeze(0)
    return load_lpips(a.device, a.dtype)(x, y, frame=frame).squeeze(0)


Window = tuple[torch.Tensor, torch.Tensor]  # (rows [h], cols [w]): torch.long indices into an image's rows, columns


def crop(image: torch.Tensor, window: Window) -> torch.Tensor:
    """``image`` [H,W,C] at the window's rows and columns: [h,w,C]. Index tensors on the image's device,
    never Python numbers read from it, so the shape is the window's whatever the frame (a step keeps
    static shapes) and no step waits on the device; the gradient is the incoming one scattered back,
    zero outside the window."""
    rows, cols = window
    return image.index_select(0, rows).index_select(1, cols)


def lpips_units(target: torch.Tensor, window: Window | None = None) -> list[torch.Tensor]:
    """What LPIPS needs of a target image [H,W,3] (its unit features, no gradient), for
    ``total_loss(..., lpips_units=)``: a target used at many steps goes through the network once.
    ``window``: of the target's crop (the same window must then go to ``total_loss``)."""
    from rmavatar.evaluate.lpips_net import load_lpips

    if window is not None:
        target = crop(target, window)
    return load_lpips(target.device, target.dtype).units(target.permute(2, 0, 1).unsqueeze(0))


def _lpips_to_units(a: torch.Tensor, units: list[torch.Tensor],
                    frame: tuple[int, int] | None = None) -> torch.Tensor:
    from rmavatar.evaluate.lpips_net import load_lpips

    x = _Clamp01.apply(a).permute(2, 0, 1).unsqueeze(0)
    return load_lpips(a.device, a.dtype)(x, y_units=units, frame=frame).squeeze(0)


def _lpips_term(render: torch.Tensor, target: torch.Tensor, lpips_fn: ImageFn | None,
                units: list[torch.Tensor] | None, window: Window | None) -> torch.Tensor:
    """LPIPS of render to target [H,W,3] (scalar); from the target's ``units`` when given and the
    default LPIPS is used. With a ``window``, of both cropped to it, as a share of the whole frame's:
    each layer's distances averaged over the frame's feature pixels (the frame's LPIPS with nothing
    counted outside the window, so a pixel in it gets about the gradient the whole frame's LPIPS gives
    it; averaged over the window's own pixels the term would weigh about H W / (h w) times as much), and a
    custom ``lpips_fn``'s value of the crops times h w / (H W)."""
    if window is None:
        if units is not None and lpips_fn is None:
            return _lpips_to_units(render, units)
        return (lpips_fn or _default_lpips)(render, target)
    frame = (render.shape[0], render.shape[1])
    render = crop(render, window)
    if units is not None and lpips_fn is None:
        return _lpips_to_units(render, units, frame)
    target = crop(target, window)
    if lpips_fn is None:
        return _default_lpips(render, target, frame)
    return lpips_fn(render, target) * (render.shape[0] * render.shape[1] / (frame[0] * frame[1]))


def total_loss(
    render: torch.Tensor,
    target: torch.Tensor,
    extras: AvatarExtras | None,
    weights: LossConfig | None = None,
    lpips_fn: ImageFn | None = None,
    ssim_fn: ImageFn | None = None,
    lpips_units: list[torch.Tensor] | None = None,
    lpips_window: Window | None = None,
    alpha: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The weighted sum of all terms, and each unweighted term (detached) by name.

    render, target [H,W,3]; extras: the posed avatar's ``AvatarExtras`` (its local_means,
    local_log_scales and offsets feed the regularisers; None: image terms only); weights: a
    ``LossConfig`` (None = the paper's weights; the ablations set ``offset`` or ``scaling`` to 0).
    ssim_fn / lpips_fn (a, b) -> scalar similarity / distance; None = ``rmavatar.evaluate``'s.
    lpips_units: :func:`lpips_units` of ``target``, when the caller keeps them (training, per frame):
    the default LPIPS then does not run the target through its network again.
    lpips_window: (rows [h], cols [w]) long index tensors on the images' device: LPIPS (and lpips_fn)
    sees render and target cropped to them (:func:`crop`; training: ``FrameCache.lpips_window``, the
    person's window), as a share of the whole frame's LPIPS (``_lpips_term``), and ``lpips_units`` must
    be of that crop; None: the whole images.
    alpha [H,W,1], mask [H,W,1]: the render's opacity and the frame's person mask, for L_mask (its weight
    needs both).
    Terms with weight 0 are not computed.
    """
    if render.shape != target.shape:
        raise ValueError(f"render {tuple(render.shape)} and target {tuple(target.shape)} differ in shape")
    weights = weights or LossConfig()
    w = {f: float(getattr(weights, f)) for f in ("rgb", "ssim", "lpips", "pos", "scaling", "offset", "mask")}
    if w["mask"] and (alpha is None or mask is None):
        raise ValueError("loss.mask needs the render's alpha and the frame's mask")

    # The loss is one product of the weights with all terms' values side by side, plus a constant (the
    # SSIM term enters as w (1 - SSIM) = w - w SSIM): one kernel launch on a GPU, where a multiply and an
    # add per term (and 1 - SSIM forward and backward) take a dozen.
    values: list[tuple[str, torch.Tensor]] = []  # (name, [k] values), each of k terms weighted by w[name]
    if w["rgb"]:
        values.append(("l1", (render - target).abs().mean().view(1)))
    if w["ssim"]:
        values.append(("ssim", (ssim_fn or _default_ssim)(render, target).view(1)))
    if w["lpips"]:
        values.append(("lpips", _lpips_term(render, target, lpips_fn, lpips_units, lpips_window).view(1)))
    if w["mask"]:
        values.append(("mask", mask_loss(alpha, mask).view(1)))
    means, log_scales, offsets, rw = (None, None, None, None) if extras is None else (
        extras.local_means, extras.local_log_scales, extras.offsets, extras.row_weights)
    if w["pos"] and w["scaling"] and w["offset"] and None not in (means, log_scales, offsets):
        # the full model: all three in one autograd Function
        values.append(("regularisers", _Regularisers.apply(means, log_scales, *offsets, weights.eps_pos,
                                                           weights.eps_scaling, rw)))
    else:  # ablations and avatars without a rectifier: only the terms asked for
        if w["pos"] and means is not None:
            values.append(("pos", position_loss(means, weights.eps_pos, rw).view(1)))
        if w["scaling"] and log_scales is not None:
            values.append(("scaling", scaling_loss(log_scales, weights.eps_scaling, rw).view(1)))
        if w["offset"] and offsets is not None:
            values.append(("offset", offset_loss(*offsets, row_weights=rw).view(1)))
    if not values:
        return render.new_zeros(()), {}
    key_weight = {"l1": "rgb", "ssim": "ssim", "lpips": "lpips", "pos": "pos", "scaling": "scaling", "offset": "offset",
                  "mask": "mask"}
    names = [n for name, _ in values for n in (("pos", "scaling", "offset") if name == "regularisers" else (name,))]
    row = tuple(-w["ssim"] if n == "ssim" else w[key_weight[n]] for n in names)
    weight = constant((row,), render.dtype, render.device)  # [1,T]
    const = constant((w["ssim"] if "ssim" in names else 0.0,), render.dtype, render.device)
    flat = torch.cat([v for _, v in values]) if len(values) > 1 else values[0][1]
    loss = torch.addmv(const, weight, flat).squeeze(0)
    parts = dict(zip(names, flat.detach().unbind()))
    if "ssim" in parts:
        parts["ssim"] = 1.0 - parts["ssim"]  # the term, as it is weighted and reported
    return loss, parts
