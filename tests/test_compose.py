"""compose_gaussians (avatar/compose.py): the world Gaussians from the face rows and the rectifier's offsets,
with a written-out backward, against the plain formulas under autograd (float64)."""

import pytest
import torch

from rmavatar.avatar.compose import compose_gaussians

from devices import DEVICES

F64 = torch.float64
MIN_SCALE = 1e-3  # large enough that some of the random scales below are clamped


def _unit(v):
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)


def _hamilton(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw), dim=-1)


def _plain(g, means, quats, log_scales, offsets, design):
    """The formulas of the module docstring, one autograd operation at a time; the columns of g read as
    independent inputs (R 0:9, w R 9:18, M 18:21, w 21, L 22:38)."""
    frames, wR = g[:, 0:9].reshape(-1, 3, 3), g[:, 9:18].reshape(-1, 3, 3)
    M, w, L = g[:, 18:21], g[:, 21:22], g[:, 22:38].reshape(-1, 4, 4)
    mu = (wR @ means.unsqueeze(-1)).squeeze(-1) + M
    r = (L @ _unit(quats).unsqueeze(-1)).squeeze(-1)
    s = w * torch.exp(log_scales)
    if offsets is None:
        return mu, r, s, frames
    d_mu, d_s, d_r = offsets
    if design == "local":
        d_mu = (wR @ d_mu.unsqueeze(-1)).squeeze(-1)
        d_s = w * d_s
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=d_r.dtype, device=d_r.device)
    return (mu + d_mu, _hamilton(r, _unit(d_r + identity)), (s + d_s).clamp_min(MIN_SCALE), frames,
            d_mu, d_s, d_r)


def _inputs(n, device, gen, design):
    g = torch.randn(n, 38, generator=gen, dtype=F64)
    means, quats, log_scales = (torch.randn(n, k, generator=gen, dtype=F64) for k in (3, 4, 3))
    log_scales = log_scales - 4.0  # s ~ 0.02 |w|: the clamp at MIN_SCALE bites for some
    quats[0] = 0.0  # shorter than eps: divided by eps, only the first term of the Jacobian
    quats[1] = 1e-13
    raw = tuple(0.3 * torch.randn(n, k, generator=gen, dtype=F64) for k in (3, 3, 4))
    if design is not None:
        raw[2][2] = torch.tensor([-1.0, 0.0, 0.0, 0.0], dtype=F64)  # 1 + d_r = 0
    return [t.to(device).requires_grad_(True) for t in (g, means, quats, log_scales, *raw)]


def _call(design, g, means, quats, log_scales, d_mu, d_s, d_r):
    offsets = None if design is None else (d_mu, d_s, d_r)
    mu, r, s, frames, world = compose_gaussians(g, means, quats, log_scales, offsets, design, MIN_SCALE)
    return (mu, r, s, frames) if world is None else (mu, r, s, frames, *world)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("design", [None, "local", "paper"])
def test_compose_matches_the_plain_formulas(device, design):
    gen = torch.Generator().manual_seed(3)
    inputs = _inputs(60, device, gen, design)
    used = inputs[:4] if design is None else inputs
    ours = _call(design, *inputs)
    plain = _plain(*inputs[:4], None if design is None else tuple(inputs[4:]), design)
    assert len(ours) == len(plain)
    clamped = (plain[2] == MIN_SCALE).sum()
    assert design is None or 0 < clamped < plain[2].numel()  # both sides of the clamp are exercised
    for a, b in zip(ours, plain):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    upstream = [torch.randn(t.shape, generator=gen, dtype=F64).to(device) for t in plain]
    for subset in (used, used[1:]):  # with and without the face rows' gradient (training has none)
        ga = torch.autograd.grad(ours, subset, upstream, retain_graph=True)
        gb = torch.autograd.grad(plain, subset, upstream, retain_graph=True)
        for a, b in zip(ga, gb):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("design", [None, "local", "paper"])
def test_compose_passes_gradcheck(design):
    gen = torch.Generator().manual_seed(4)
    inputs = _inputs(6, "cpu", gen, design)
    with torch.no_grad():  # away from the kinks (|v| = eps, s = min_scale) finite differences are exact
        inputs[2][:2] = torch.randn(2, 4, generator=gen, dtype=F64)
        inputs[3].add_(4.0)
        inputs[6][2] = 0.1
    used = inputs[:4] if design is None else inputs
    assert torch.autograd.gradcheck(lambda *x: _call(design, *x, *inputs[len(used):]), used)


def test_missing_output_gradients_count_as_zero():
    # Only the means are used: the other outputs send no gradient (None in the backward).
    gen = torch.Generator().manual_seed(5)
    inputs = _inputs(10, "cpu", gen, "local")
    ours = _call("local", *inputs)[0]
    plain = _plain(*inputs[:4], tuple(inputs[4:]), "local")[0]
    for a, b in zip(torch.autograd.grad(ours.sum(), inputs, allow_unused=True),
                    torch.autograd.grad(plain.sum(), inputs, allow_unused=True)):
        if b is None:
            assert a is None or not a.any()
        else:
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_offsets_need_a_design():
    g = torch.zeros(2, 38)
    z = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="design"):
        compose_gaussians(g, z, torch.zeros(2, 4), z, (z, z, torch.zeros(2, 4)), None)
