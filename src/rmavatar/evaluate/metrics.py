"""Image metrics: PSNR, SSIM (11x11 Gaussian window) and LPIPS (AlexNet v0.1).

All three take float RGB images ``[H,W,3]`` or batches ``[B,H,W,3]`` with values in [0, 1], as torch
tensors or numpy arrays. With torch inputs they return tensors (a 0-d tensor for one image, ``[B]`` for
a batch) and are differentiable, so training uses ``1 - ssim(render, gt)`` and ``lpips(render, gt)`` as
losses. With numpy inputs they return a Python float (one image) or a float64 array ``[B]``.

``check_range=True`` (the default) rejects values outside [0, 1]; a training loop whose renders may
overshoot 1 (SH colours are not clamped from above) passes ``check_range=False``.
"""

from __future__ import annotations

import functools

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from rmavatar.utils import UserError
from rmavatar.utils.device import constant

# Values this far outside [0, 1] are treated as rounding noise, anything beyond is an error.
_RANGE_TOL = 1e-4

# SSIM constants (Wang et al. 2004), data range 1: the setting every peer reports with.
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # 11x11 window; scikit-image's int(3.5 * sigma + 0.5) for truncate=3.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _prepare(name: str, a: Any, b: Any, check_range: bool, min_side: int = 1):
    """Validate two image arguments and return them as torch ``[B,H,W,3]`` plus output flags.

    Returns ``(a, b, batched, as_numpy)``; numpy inputs become float64 tensors so that numpy callers get
    full-precision numbers, torch inputs keep their dtype and device.
    """
    as_numpy = not (torch.is_tensor(a) or torch.is_tensor(b))
    tensors = []
    for arg, x in (("a", a), ("b", b)):
        if torch.is_tensor(x):
            t = x
        elif isinstance(x, np.ndarray):
            t = torch.from_numpy(np.ascontiguousarray(x))
        else:
            raise UserError(f"{name}: argument {arg} must be a torch tensor or numpy array, got {type(x).__name__}")
        if not t.is_floating_point():
            hint = " (divide uint8 images by 255)" if t.dtype == torch.uint8 else ""
            raise UserError(f"{name}: argument {arg} must hold float values in [0, 1], got dtype {t.dtype}{hint}")
        if t.ndim not in (3, 4) or t.shape[-1] != 3:
            raise UserError(
                f"{name}: argument {arg} must be an RGB image [H,W,3] or a batch [B,H,W,3], "
                f"got shape {tuple(t.shape)}"
            )
        tensors.append(t)
    ta, tb = tensors
    if ta.shape != tb.shape:
        raise UserError(f"{name}: a and b must have the same shape, got {tuple(ta.shape)} and {tuple(tb.shape)}")
    h, w = ta.shape[-3], ta.shape[-2]
    if h < min_side or w < min_side:
        raise UserError(f"{name}: images must be at least {min_side}x{min_side} pixels, got {h}x{w}")
    if as_numpy:
        ta, tb = ta.double(), tb.double()
    else:
        # Mixed inputs: follow whichever one is a tensor (its device and dtype).
        ref = ta if torch.is_tensor(a) else tb
        dtype = ref.dtype if ref.dtype in (torch.float32, torch.float64) else torch.float32
        ta, tb = ta.to(ref.device, dtype), tb.to(ref.device, dtype)
    if check_range:
        for arg, t in (("a", ta), ("b", tb)):
            lo, hi = torch.aminmax(t.detach())
            lo, hi = float(lo), float(hi)
            # Written so that NaN fails too.
            if not (lo >= -_RANGE_TOL and hi <= 1 + _RANGE_TOL):
                raise UserError(
                    f"{name}: argument {arg} must have values in [0, 1], found [{lo:.4g}, {hi:.4g}] "
                    "(pass check_range=False to score unclamped renders)"
                )
    batched = ta.ndim == 4
    if not batched:
        ta, tb = ta[None], tb[None]
    return ta, tb, batched, as_numpy


def _finish(values: torch.Tensor, batched: bool, as_numpy: bool):
    """``values [B]`` -> tensor/float/array as the module docstring promises."""
    if not batched:
        values = values.squeeze(0)  # a view whose backward is a view too (indexing's makes a zero tensor)
    if as_numpy:
        out = values.detach().cpu().numpy().astype(np.float64)
        return float(out) if not batched else out
    return values


def psnr(a: Any, b: Any, *, check_range: bool = True):
    """Peak signal-to-noise ratio in dB per image: ``20 log10(1 / RMSE)`` over all pixels and channels.

    Identical images give ``inf``. Batches return one value per image (average them yourself: the
    papers average per-image PSNRs, not the PSNR of the pooled error).
    """
    ta, tb, batched, as_numpy = _prepare("psnr", a, b, check_range)
    mse = (ta - tb).square().mean(dim=(1, 2, 3))
    return _finish(-10.0 * torch.log10(mse), batched, as_numpy)


def gaussian_window_1d(sigma: float = SSIM_SIGMA, radius: int = SSIM_RADIUS, dtype=torch.float32, device=None):
    """Normalised 1D Gaussian taps ``[2 radius + 1]`` (scipy's ``gaussian_filter1d`` weights)."""
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype=dtype, device=device)


@functools.lru_cache(maxsize=16)
def _ssim_windows(dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SSIM's separable window for the 12 filtered maps of :class:`_SSIM`, made once per dtype and device
    (a training loss asks every step); read-only: vertical [12,1,11,1], horizontal [12,1,1,11], and the
    horizontal one with the six linear maps' taps doubled (d(mu^2)/d mu = 2 mu, folded into the backward)."""
    win = 2 * SSIM_RADIUS + 1
    g = gaussian_window_1d(dtype=dtype, device=device)
    vertical = g.view(1, 1, win, 1).repeat(12, 1, 1, 1)
    horizontal = g.view(1, 1, 1, win).repeat(12, 1, 1, 1)
    doubled = horizontal.clone()
    doubled[:6] *= 2
    return vertical, horizontal, doubled


class _SSIM(torch.autograd.Function):
    """Mean SSIM map per image, x, y [B,3,H,W] -> [B], with the backward written out (a third of the
    tensor operations autograd records for it).

    With u = x + y and v = x - y, the SSIM factors are sums and differences of u's and v's moments:
    2 A1 = mu_u^2 - mu_v^2 + 2 c1, 2 B1 = mu_u^2 + mu_v^2 + 2 c1 (A1 = 2 mu_x mu_y + c1,
    B1 = mu_x^2 + mu_y^2 + c1), and 2 A2 = var_u - var_v + 2 c2, 2 B2 = var_u + var_v + 2 c2
    (A2 = 2 cov_xy + c2, B2 = var_x + var_y + c2). So four maps (u, v, u^2, v^2 per channel) are
    filtered instead of five, and every factor comes from one sum and one difference of z = (mu^2, var)
    over (u, v): SSIM = minus_W minus_V / (plus_W plus_V)."""

    @staticmethod
    def forward(ctx, x, y):
        b, c, h, w = x.shape
        vertical, horizontal, doubled = _ssim_windows(x.dtype, x.device)
        uv = torch.cat([x + y, x - y], 1)  # [B,6,H,W]
        # 'valid' convolution: only windows that lie fully inside the image, the region the mean is over.
        filt = F.conv2d(F.conv2d(torch.cat([uv, uv * uv], 1), vertical, groups=12), horizontal, groups=12)
        f = filt.view(b, 2, 2, c, *filt.shape[2:])  # [B, (mean, mean of square), (u, v), 3, h, w]
        mu = f[:, 0]
        sq = mu * mu
        z = torch.stack([sq, f[:, 1] - sq], 2) + constant(((2 * SSIM_K1**2, 2 * SSIM_K2**2), (0.0, 0.0)),
                                                          x.dtype, x.device).view(1, 2, 2, 1, 1, 1)
        plus, minus = z[:, 0] + z[:, 1], z[:, 0] - z[:, 1]  # [B, (W, V), 3, h, w]
        den = plus.prod(1)
        s = minus.prod(1) / den
        ctx.save_for_backward(uv, mu, plus, minus, s, den)
        ctx.windows = (vertical, doubled)
        return s.mean(dim=(1, 2, 3))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        uv, mu, plus, minus, s, den = ctx.saved_tensors
        vertical, doubled = ctx.windows
        b, _, h, w = uv.shape
        g = grad.view(-1, 1, 1, 1) * (1.0 / s[0].numel())  # d loss / d SSIM map
        # dS/d minus_W = minus_V / den (not S / minus_W: minus may be 0), dS/d plus = -S / plus;
        # plus = z_u + z_v and minus = z_u - z_v give dz_u = g_minus + g_plus, dz_v = g_plus - g_minus.
        g_minus = minus.flip(1) * (g / den).unsqueeze(1)
        sign = constant((1.0, -1.0), uv.dtype, uv.device).view(1, 2, 1, 1, 1, 1)
        dz = g_minus.unsqueeze(1) * sign - ((g * s).unsqueeze(1) / plus).unsqueeze(1)  # [B,(u,v),(W,V),3,h,w]
        # z = (mu^2, e - mu^2): d mu = 2 mu (dz_W - dz_V) (the 2 is in the doubled window), d e = dz_V.
        d_filt = torch.stack([mu * (dz[:, :, 0] - dz[:, :, 1]), dz[:, :, 1]], 1).view(b, 12, *s.shape[-2:])
        d_maps = F.conv_transpose2d(F.conv_transpose2d(d_filt, doubled, groups=12), vertical, groups=12)
        d_maps = d_maps.view(b, 2, 2, -1, h, w)
        d_uv = torch.addcmul(d_maps[:, 0], uv.view(b, 2, -1, h, w), d_maps[:, 1], value=2.0)  # [B,(u,v),3,H,W]
        dx = d_uv[:, 0] + d_uv[:, 1] if ctx.needs_input_grad[0] else None
        dy = d_uv[:, 0] - d_uv[:, 1] if ctx.needs_input_grad[1] else None
        return dx, dy


def ssim(a: Any, b: Any, *, check_range: bool = True):
    """Structural similarity with an 11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03, data range 1.

    The SSIM map is averaged over the pixels whose window lies inside the image and over the three
    channels, which is exactly what ``skimage.metrics.structural_similarity(a, b, gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)`` reports. Images must be at
    least 11x11. The Gaussian filter is applied separably (two 1D convolutions) and the backward is
    written out, so it is cheap enough to be a training loss (``1 - ssim``).
    """
    win = 2 * SSIM_RADIUS + 1
    ta, tb, batched, as_numpy = _prepare("ssim", a, b, check_range, min_side=win)
    return _finish(_SSIM.apply(ta.permute(0, 3, 1, 2), tb.permute(0, 3, 1, 2)), batched, as_numpy)


def lpips(a: Any, b: Any, *, check_range: bool = True, net: torch.nn.Module | None = None):
    """LPIPS v0.1 with the AlexNet backbone (which maps images from [0, 1] to [-1, 1] internally).

    ``net`` is an :class:`rmavatar.evaluate.lpips_net.LPIPSAlex`; by default the one for the input's
    device and dtype is loaded from the user cache (converted there on first use) and kept for reuse.
    Images must be at least 32x32 (AlexNet's fifth layer needs that much). Lower is more similar.
    Numpy inputs are scored in float32 (the weights' precision); float64 tensors run in float64.
    """
    from rmavatar.evaluate.lpips_net import MIN_SIDE, load_lpips

    ta, tb, batched, as_numpy = _prepare("lpips", a, b, check_range, min_side=MIN_SIDE)
    if as_numpy:
        # The weights are float32 and float64 convolutions are several times slower on CPU.
        ta, tb = ta.float(), tb.float()
    if net is None:
        net = load_lpips(ta.device, ta.dtype)
    return _finish(net(ta.permute(0, 3, 1, 2), tb.permute(0, 3, 1, 2)), batched, as_numpy)

