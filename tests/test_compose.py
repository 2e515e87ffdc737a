"""compose_gaussians (avatar/compose.py): the world Gaussians from the face rows and the rectifier's offsets,
with a written-out backward, against compose_reference, the plain formulas under autograd (float64)."""

import pytest
import torch

from rmavatar.avatar.compose import compose_gaussians, compose_reference
from rmavatar.avatar.geometry import FaceTable
from rmavatar.avatar.rectifier import LocalRectifier, PaperRectifier

from devices import DEVICES

F64 = torch.float64
MIN_SCALE = 1e-3  # large enough that some of the random scales below are clamped
# The designs by their config names (their offsets: in the triangle's frame, in world units); None: no rectifier.
DESIGNS = {"local": LocalRectifier(), "paper": PaperRectifier(), None: None}


def _plain(g, means, quats, log_scales, offsets, design):
    """compose_reference's outputs, flat as _call's (the formulas of compose.py's docstring, one autograd
    operation at a time; the columns of g read as independent inputs)."""
    mu, r, s, frames, world = compose_reference(g, means, quats, log_scales, offsets, DESIGNS[design], MIN_SCALE)
    return (mu, r, s, frames) if world is None else (mu, r, s, frames, *world)


def _inputs(n, device, gen, design):
    g = torch.randn(n, FaceTable.WIDTH, generator=gen, dtype=F64)
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
    mu, r, s, frames, world = compose_gaussians(g, means, quats, log_scales, offsets, DESIGNS[design], MIN_SCALE)
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
    g = torch.zeros(2, FaceTable.WIDTH)
    z = torch.zeros(2, 3)
    for design in (None, "local"):  # no design, or a config name instead of the design object
        with pytest.raises(ValueError, match="design"):
            compose_gaussians(g, z, torch.zeros(2, 4), z, (z, z, torch.zeros(2, 4)), design)
        with pytest.raises(ValueError, match="design"):
            compose_reference(g, z, torch.zeros(2, 4), z, (z, z, torch.zeros(2, 4)), design)


def test_reference_is_the_formulas_written_out():
    """compose_reference itself against the formulas written here with the face rows' named columns
    (R, w R, M, w, L), so the fast path is compared with something checked independently."""
    gen = torch.Generator().manual_seed(6)
    g, means, quats, log_scales, d_mu, d_s, d_r = _inputs(12, "cpu", gen, "local")
    wR, M, w = g[:, FaceTable.wR].reshape(-1, 3, 3), g[:, FaceTable.M], g[:, FaceTable.w]
    L = g[:, FaceTable.L].reshape(-1, 4, 4)
    unit = lambda v: v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # noqa: E731
    r_star = (L @ unit(quats).unsqueeze(-1)).squeeze(-1)
    q = unit(d_r + torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64))
    pw, px, py, pz = r_star.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    r = torch.stack((pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw), -1)
    for design in ("local", "paper"):
        world = (((wR @ d_mu.unsqueeze(-1)).squeeze(-1), w * d_s) if design == "local" else (d_mu, d_s))
        mu = (wR @ means.unsqueeze(-1)).squeeze(-1) + M + world[0]
        s = (w * torch.exp(log_scales) + world[1]).clamp_min(MIN_SCALE)
        want = (mu, r, s, g[:, FaceTable.R].reshape(-1, 3, 3), *world, d_r)
        got = _plain(g, means, quats, log_scales, (d_mu, d_s, d_r), design)
        for a, b in zip(got, want, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13)
