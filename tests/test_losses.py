"""The training loss and its regularisers, against hand-computed values."""

import math

import pytest
import torch
import trimesh

from rmavatar.avatar import Avatar, AvatarConfig, AvatarExtras
from rmavatar.train.config import LossConfig
from rmavatar.train.losses import mask_loss, offset_loss, position_loss, scaling_loss, total_loss

from devices import DEVICES


def test_position_loss_by_hand():
    mu = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0, 3, 4], [0.6, 0.0, -0.8]])
    # norms 0, 2, 5, 1 -> excess over 1: 0, 1, 4, 0
    assert math.isclose(float(position_loss(mu)), 5 / 4, rel_tol=1e-6)
    assert math.isclose(float(position_loss(mu, eps=2.0)), 3 / 4, rel_tol=1e-6)


def test_scaling_loss_by_hand():
    s = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.6, 0.2], [0.9, 1.0, 0.6]])
    # excess over 0.6: (0,0,0) -> 0; (0.4,0,0) -> 0.4; (0.3,0.4,0) -> 0.5
    assert math.isclose(float(scaling_loss(torch.log(s))), 0.9 / 3, rel_tol=1e-5)


def test_offset_loss_by_hand():
    d_mu = torch.full((5, 3), 2.0)
    d_s = torch.tensor([[3.0, 0, 0]]).expand(5, 3)
    d_r = torch.full((5, 4), 0.5)
    assert math.isclose(float(offset_loss(d_mu, d_s, d_r)), 4.0 + 3.0 + 0.25, rel_tol=1e-6)


def test_mask_loss_by_hand_and_in_the_total():
    alpha = torch.tensor([[1.0, 0.5], [0.0, 0.25]]).reshape(2, 2, 1).requires_grad_(True)
    mask = torch.tensor([[1.0, 1.0], [0.0, 1.0]]).reshape(2, 2, 1)
    assert math.isclose(float(mask_loss(alpha, mask)), (0.5 + 0.75) / 4, rel_tol=1e-6)
    render = target = torch.full((2, 2, 3), 0.5)
    cfg = LossConfig(rgb=1.0, ssim=0.0, lpips=0.0, pos=0.0, scaling=0.0, offset=0.0, mask=2.0)
    loss, terms = total_loss(render, target, None, cfg, alpha=alpha, mask=mask)
    assert set(terms) == {"l1", "mask"} and math.isclose(float(loss.detach()), 2 * 1.25 / 4, rel_tol=1e-6)
    loss.backward()  # pulls alpha up where the mask is 1, down where it is 0
    assert alpha.grad.reshape(-1).tolist() == [0.0, -0.5, 0.0, -0.5]
    with pytest.raises(ValueError, match="loss.mask needs the render's alpha"):
        total_loss(render, target, None, cfg)


def _fake_extras(n=4):
    means = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0, 3, 4], [0, 0, 0]], requires_grad=True)
    log_s = torch.log(torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.6, 0.2], [0.9, 1.0, 0.6], [0.6, 0.6, 0.6]]))
    log_s.requires_grad_(True)
    d_mu = torch.full((n, 3), 0.1, requires_grad=True)
    d_s = torch.zeros(n, 3, requires_grad=True)
    d_r = torch.full((n, 4), 0.2, requires_grad=True)
    return AvatarExtras(local_means=means, local_log_scales=log_s, offsets=(d_mu, d_s, d_r))


def test_total_loss_weights_and_switches():
    render = torch.full((16, 16, 3), 0.25)
    target = torch.full((16, 16, 3), 0.75)
    g = _fake_extras()
    ssim_fn = lambda a, b: torch.tensor(0.7)  # noqa: E731
    lpips_fn = lambda a, b: torch.tensor(0.1)  # noqa: E731
    pos = (0 + 1 + 4 + 0) / 4
    scal = 0.9 / 4
    off = 0.01 + 0.0 + 0.04
    loss, terms = total_loss(render, target, g, LossConfig(), lpips_fn, ssim_fn)
    expect = 1.5 * 0.5 + 0.2 * 0.3 + 0.05 * 0.1 + 0.01 * pos + 1.0 * scal + 1.0 * off
    assert math.isclose(float(loss.detach()), expect, rel_tol=1e-5)
    assert set(terms) == {"l1", "ssim", "lpips", "pos", "scaling", "offset"}
    assert math.isclose(float(terms["pos"]), pos, rel_tol=1e-6)
    loss.backward()
    assert all(t.grad is not None for t in (g.local_means, g.local_log_scales, *g.offsets[::2]))

    def never(a, b):
        raise AssertionError("a term with weight 0 must not be computed")

    loss, terms = total_loss(render, target, g, LossConfig(offset=0.0, scaling=0.0, lpips=0.0), never, ssim_fn)
    assert set(terms) == {"l1", "ssim", "pos"}
    assert math.isclose(float(loss.detach()), 1.5 * 0.5 + 0.2 * 0.3 + 0.01 * pos, rel_tol=1e-5)
    # Offsets None (no rectifier) is fine.
    g.offsets = None
    cfg = LossConfig(rgb=1.0, ssim=0.0, lpips=0.0, pos=0.0, scaling=2.0, offset=5.0)
    loss, terms = total_loss(render, target, g, cfg, never, never)
    assert set(terms) == {"l1", "scaling"}
    assert math.isclose(float(loss.detach()), 0.5 + 2 * scal, rel_tol=1e-5)
    with pytest.raises(ValueError):
        total_loss(render[:8], target, g, cfg)
    # No extras at all (None): the image terms only.
    loss, terms = total_loss(render, target, None, cfg, never, never)
    assert set(terms) == {"l1"} and math.isclose(float(loss.detach()), 0.5, rel_tol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_total_loss_default_ssim_matches_metric(device):
    from rmavatar.evaluate import ssim

    gen = torch.Generator().manual_seed(0)
    render = torch.rand(24, 24, 3, generator=gen).to(device)
    target = torch.rand(24, 24, 3, generator=gen).to(device)
    g = _fake_extras()
    w = LossConfig(rgb=0, lpips=0, pos=0, scaling=0, offset=0, ssim=1.0)
    loss, terms = total_loss(render, target, g, w)
    assert math.isclose(float(loss.detach()), 1 - float(ssim(render, target)), rel_tol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_loss_gradients_reach_every_avatar_parameter(device):
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    v = torch.tensor(m.vertices, dtype=torch.float32)
    f = torch.tensor(m.faces)
    av = Avatar(f, None, v, AvatarConfig(rectifier="paper")).to(device)
    v = v.to(device)
    av.active_sh_degree.fill_(3)
    with torch.no_grad():
        av.means.mul_(0).add_(1.5)  # beyond eps_pos
        av.log_scales.fill_(0.3)  # beyond eps_scaling
    g, extras = av.forward_with_extras(v, torch.randn(69).to(device))
    # A stand-in "render" that depends on every attribute, as the rasterizer does.
    render = (g.means.mean() + g.quats.mean() + g.scales.mean() + g.opacities.mean() + g.sh.mean()).expand(16, 16, 3)
    loss, _ = total_loss(render, torch.zeros(16, 16, 3, device=device), extras, LossConfig(ssim=0, lpips=0))
    loss.backward()
    for name, p in av.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, name


def test_total_loss_equals_the_plain_weighted_sum_in_float64():
    """Values and gradients of the loss equal those of the terms added one by one (float64)."""
    from rmavatar.evaluate import lpips, ssim

    gen = torch.Generator().manual_seed(3)
    render = torch.rand(40, 40, 3, generator=gen, dtype=torch.float64).requires_grad_(True)
    target = torch.rand(40, 40, 3, generator=gen, dtype=torch.float64)
    g = _fake_extras()
    for t in (g.local_means, g.local_log_scales, *g.offsets):
        t.data = t.data.double()
    cfg = LossConfig()
    plain = (cfg.rgb * (render - target).abs().mean() + cfg.ssim * (1.0 - ssim(render, target, check_range=False))
             + cfg.lpips * lpips(render.clamp(0.0, 1.0), target, check_range=False)
             + cfg.pos * position_loss(g.local_means, cfg.eps_pos)
             + cfg.scaling * scaling_loss(g.local_log_scales, cfg.eps_scaling) + cfg.offset * offset_loss(*g.offsets))
    loss, _ = total_loss(render, target, g, cfg)
    assert loss.dtype == torch.float64
    assert math.isclose(float(loss.detach()), float(plain.detach()), rel_tol=1e-12)
    inputs = (render, g.local_means, g.local_log_scales, *g.offsets)
    for a, b in zip(torch.autograd.grad(loss, inputs), torch.autograd.grad(plain, inputs)):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(b.abs().max()))


def test_fused_regularisers_match_the_three_definitions():
    """The one-Function regularisers against position_loss / scaling_loss / offset_loss (float64, rows
    with |mu| = 0, below and above eps, scales below and above eps), and finite differences."""
    from rmavatar.train.losses import _Regularisers

    gen = torch.Generator().manual_seed(5)
    mu = torch.randn(30, 3, generator=gen, dtype=torch.float64)
    mu[0] = 0.0
    log_s = torch.randn(30, 3, generator=gen, dtype=torch.float64) * 0.5 - 0.5
    off = [torch.randn(30, k, generator=gen, dtype=torch.float64) * 0.1 for k in (3, 3, 4)]
    inputs = [t.requires_grad_(True) for t in (mu, log_s, *off)]
    fused = _Regularisers.apply(*inputs, 0.8, 0.6)
    plain = torch.stack((position_loss(mu, 0.8), scaling_loss(log_s, 0.6), offset_loss(*off)))
    torch.testing.assert_close(fused, plain, rtol=1e-13, atol=0)
    grad = torch.tensor([0.3, -1.1, 2.0], dtype=torch.float64)
    for a, b in zip(torch.autograd.grad(fused, inputs, grad), torch.autograd.grad(plain, inputs, grad)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
    ref = _Regularisers.reference(*inputs, 0.8, 0.6)  # the reference beside the Function: the same three
    assert torch.equal(ref, plain)
    fused = _Regularisers.apply(*inputs, 0.8, 0.6)
    for a, b in zip(torch.autograd.grad(fused, inputs, grad), torch.autograd.grad(ref, inputs, grad)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
    mu_smooth = (mu.detach() + 0.05).requires_grad_(True)  # no |mu| = 0 row: the norm is differentiable
    assert torch.autograd.gradcheck(lambda *t: _Regularisers.apply(*t, 0.8, 0.6), (mu_smooth, *inputs[1:]))


def test_clamp_for_lpips_has_clamps_gradient():
    from rmavatar.train.losses import _Clamp01

    x = torch.tensor([-0.5, 0.0, 0.3, 1.0, 1.7, float("nan")], dtype=torch.float64, requires_grad=True)
    y = x.detach().clone().requires_grad_(True)
    grad = torch.arange(1.0, 7.0, dtype=torch.float64)
    ours, plain = _Clamp01.apply(x), y.clamp(0.0, 1.0)
    assert torch.equal(ours[:5], plain[:5]) and torch.isnan(ours[5])
    (ours * grad).sum().backward()
    (plain * grad).sum().backward()
    assert torch.equal(x.grad, y.grad)  # including the bounds 0 and 1 (passed) and NaN (blocked)
    z = x.detach().clone().requires_grad_(True)
    ref = _Clamp01.reference(z)  # the reference beside the Function is clamp itself
    assert torch.equal(ref[:5], plain[:5]) and torch.isnan(ref[5])
    (ref * grad).sum().backward()
    assert torch.equal(x.grad, z.grad)
