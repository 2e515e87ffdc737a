"""Density control on the mesh: schedule, clone/split/prune/reset invariants, Adam-state surgery."""

import math

import pytest
import torch
import trimesh

from rmavatar.avatar import GAUSSIAN_PARAMS, Avatar, AvatarConfig, quat_to_rotmat
from rmavatar.train.density import (
    DensityConfig,
    DensityController,
    densify,
    prune,
    prune_mask,
    reset_opacity,
)


def make(n=None, rectifier=False):
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    v = torch.tensor(m.vertices, dtype=torch.float32)
    f = torch.tensor(m.faces)
    cfg = AvatarConfig(rectifier=rectifier, sh_degree=1, placement="area" if n else "face", num_gaussians=n)
    return Avatar(f, None, v, cfg), v


def gaussian_parameters(av):
    return {name: getattr(av, name) for name in GAUSSIAN_PARAMS}


def controller(av, opt, start, every, stop, reset_start, reset_every, seed=0, **thresholds):
    """A controller whose schedule is exactly the given iterations (a run as long as the reference)."""
    cfg = DensityConfig(reference_iters=1000, start=start, every=every, stop=stop, reset_start=reset_start,
                        reset_every=reset_every, **thresholds)
    return DensityController(av, opt, cfg, iters=1000, seed=seed)


def adam_with_state(av, seed=0):
    """Adam over the avatar with one real step taken, so every parameter has moments."""
    groups = [{"params": [p], "lr": 1e-3, "name": name} for name, p in gaussian_parameters(av).items()]
    if av.rectifier is not None:
        groups.append({"params": list(av.rectifier.parameters()), "lr": 1e-4})
    opt = torch.optim.Adam(groups, eps=1e-15)
    gen = torch.Generator().manual_seed(seed)
    for p in av.parameters():
        p.grad = torch.randn(p.shape, generator=gen)
    opt.step()
    opt.zero_grad(set_to_none=True)
    return opt


def check_optimizer_matches(av, opt):
    params = gaussian_parameters(av)
    in_opt = {id(p) for g in opt.param_groups for p in g["params"]}
    for name, p in params.items():
        assert id(p) in in_opt, f"{name} is not the optimizer's parameter"
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape, name
    assert av.face_ids.shape[0] == av.num_gaussians


def test_paper_schedule_and_scaling():
    s = DensityConfig().schedule(50_000)
    assert [s.densify_at(i) for i in (9_500, 10_000, 10_250, 10_500, 34_500, 35_000)] == [False, True, False, True, True, False]
    assert [i for i in range(1, 50_001) if s.reset_at(i)] == [10_000, 15_000, 20_000, 25_000, 30_000]
    assert s.gather_at(34_999) and not s.gather_at(35_000)
    t = DensityConfig().schedule(5_000)
    assert (t.start, t.every, t.stop, t.reset_start, t.reset_every) == (1_000, 50, 3_500, 1_000, 500)
    z = DensityConfig(reference_iters=50_000, start=15_000, every=100).schedule(50_000)
    assert (z.start, z.every) == (15_000, 100)
    tiny = DensityConfig().schedule(20)
    assert tiny.every >= 1 and tiny.reset_every >= 1


def test_prune_mask_by_hand():
    faces = torch.tensor([0, 0, 1, 1, 2, 3, 3])
    opac = torch.tensor([0.001, 0.002, 0.5, 0.001, 0.003, 0.004, 0.004])
    remove = prune_mask(opac, faces, 0.005, 5)
    # face 0: both low -> keep the more opaque (index 1); face 1: drop 3; face 2: its only one stays;
    # face 3: a tie -> keep the lower index.
    assert remove.tolist() == [True, False, False, True, False, False, True]


def test_pruning_everything_keeps_one_per_face_and_adam_rows():
    av, v = make(n=300)
    opt = adam_with_state(av)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        av.opacity_logits.copy_(torch.rand(av.num_gaussians, generator=gen) * 3 - 12)  # all < 0.005
    before = {name: (p.detach().clone(), opt.state[p]["exp_avg"].clone()) for name, p in gaussian_parameters(av).items()}
    old_faces = av.face_ids.clone()
    best = {}
    logits = av.opacity_logits.tolist()
    for i, fid in enumerate(old_faces.tolist()):
        if fid not in best or logits[i] > logits[best[fid]]:
            best[fid] = i
    removed = prune(av, opt, 0.005)
    assert removed == 300 - av.faces.shape[0]
    assert torch.equal(torch.bincount(av.face_ids, minlength=av.faces.shape[0]), torch.ones(av.faces.shape[0], dtype=torch.long))
    kept = torch.tensor(sorted(best.values()))
    assert torch.equal(av.face_ids, old_faces[kept])
    check_optimizer_matches(av, opt)
    for name, p in gaussian_parameters(av).items():
        assert torch.equal(p.detach(), before[name][0][kept])
        assert torch.equal(opt.state[p]["exp_avg"], before[name][1][kept])
    av(v)  # still renders


def test_clone_and_split_in_the_parent_frame():
    av, v = make(n=200)
    opt = adam_with_state(av)
    n = av.num_gaussians
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        av.quats.copy_(torch.randn(n, 4, generator=gen))
        av.means.copy_(torch.randn(n, 3, generator=gen) * 0.3)
        # Half tiny (clone), half large (split) relative to percent_dense * extent.
        av.log_scales.copy_(torch.where(torch.arange(n)[:, None] % 2 == 0, torch.tensor(-6.0), torch.tensor(0.5)).expand(n, 3))
    extent = float(av.rest_extent)
    small = (av.rest_face_scale[av.face_ids] * av.log_scales.exp().amax(-1)) <= 0.01 * extent
    assert small.any() and (~small).any()
    grad = torch.zeros(n)
    sel = torch.arange(n) % 3 == 0
    grad[sel] = 1e-3
    old = {name: p.detach().clone() for name, p in gaussian_parameters(av).items()}
    old_m = {name: opt.state[p]["exp_avg_sq"].clone() for name, p in gaussian_parameters(av).items()}
    old_faces = av.face_ids.clone()
    n_clone, n_split = densify(av, opt, grad, 2e-4, 0.01, generator=torch.Generator().manual_seed(3))
    ci = (sel & small).nonzero().squeeze(-1)
    si = (sel & ~small).nonzero().squeeze(-1)
    assert (n_clone, n_split) == (len(ci), len(si))
    assert av.num_gaussians == n + n_clone + n_split
    check_optimizer_matches(av, opt)
    keep = (~(sel & ~small)).nonzero().squeeze(-1)
    k = len(keep)
    # Kept rows unchanged with their moments; new rows' moments are zero.
    for name, p in gaussian_parameters(av).items():
        assert torch.equal(p.detach()[:k], old[name][keep])
        assert torch.equal(opt.state[p]["exp_avg_sq"][:k], old_m[name][keep])
        assert (opt.state[p]["exp_avg_sq"][k:] == 0).all()
    # Clones: exact copies, same face.
    for name, p in gaussian_parameters(av).items():
        assert torch.equal(p.detach()[k : k + n_clone], old[name][ci])
    assert torch.equal(av.face_ids[k : k + n_clone], old_faces[ci])
    # Split children: parent's face, scale / 1.6, same rotation, displaced.
    ch = slice(k + n_clone, None)
    assert torch.equal(av.face_ids[ch], old_faces[si].repeat(2))
    assert torch.allclose(av.log_scales.detach()[ch], old["log_scales"][si].repeat(2, 1) - math.log(1.6))
    assert torch.equal(av.quats.detach()[ch], old["quats"][si].repeat(2, 1))
    assert torch.equal(av.opacity_logits.detach()[ch], old["opacity_logits"][si].repeat(2))
    assert (av.means.detach()[ch] - old["means"][si].repeat(2, 1)).norm(dim=-1).min() > 0
    # The optimiser keeps working on the new tensors.
    g = av(v)
    (g.means.sum() + g.scales.sum() + g.opacities.sum() + g.sh.sum() + g.quats.sum()).backward()
    opt.step()


def test_split_children_follow_the_parent_distribution():
    av, v = make()
    n = av.num_gaussians
    q = torch.tensor([0.8, 0.2, -0.5, 0.3])
    q = q / q.norm()
    scales = torch.tensor([0.3, 0.05, 0.1])
    with torch.no_grad():
        av.quats.copy_(q.expand(n, 4))
        av.log_scales.copy_(scales.log().expand(n, 3))
        av.means.zero_()
    # Run many rounds on a fresh copy of the same parents to collect children offsets.
    offsets = []
    gen = torch.Generator().manual_seed(4)
    for _ in range(40):
        a2, _ = make()
        a2.load_state_dict(av.state_dict())
        densify(a2, None, torch.ones(n), 2e-4, percent_dense=0.0, generator=gen)
        offsets.append(a2.means.detach())
    x = torch.cat(offsets).double()
    assert x.shape[0] == 40 * 2 * n
    R = quat_to_rotmat(q).double()
    cov = R @ torch.diag(scales.double() ** 2) @ R.T
    emp = x.T @ x / x.shape[0]
    assert torch.allclose(emp, cov, atol=0.08 * float(cov.abs().max()))
    assert x.mean(0).abs().max() < 0.02


def test_reset_opacity_caps_and_clears_moments():
    av, _ = make()
    opt = adam_with_state(av)
    with torch.no_grad():
        av.opacity_logits[:10] = -7.0  # below the cap: unchanged
    reset_opacity(av, opt, 0.01)
    op = torch.sigmoid(av.opacity_logits.detach())
    assert op.max() <= 0.01 + 1e-7
    assert torch.allclose(av.opacity_logits.detach()[:10], torch.full((10,), -7.0))
    assert (opt.state[av.opacity_logits]["exp_avg"] == 0).all()
    assert (opt.state[av.means]["exp_avg"] != 0).any()


def test_controller_statistics_and_cycle():
    av, v = make(rectifier="paper")
    opt = adam_with_state(av)
    n = av.num_gaussians
    ctl = controller(av, opt, start=2, every=2, stop=5, reset_start=4, reset_every=10, grad_threshold=2e-4,
                     percent_dense=0.01)
    m2d = torch.zeros(n, 2, requires_grad=True)
    m2d.grad = torch.zeros(n, 2)
    m2d.grad[:, 0] = 1e-4
    m2d.grad[:, 1] = torch.linspace(0, 4e-4, n)
    visible = torch.arange(n) % 4 != 0
    info = {"means2d": m2d, "visible": visible}
    W, H = 64, 48
    assert ctl.after_step(1, info, W, H) == {}
    norm = torch.sqrt((1e-4 * W / 2) ** 2 + (m2d.grad[:, 1] * H / 2) ** 2)
    assert torch.allclose(ctl.grad_average(), torch.where(visible, norm, torch.zeros(n)))
    state = ctl.state_dict()
    out = ctl.after_step(2, info, W, H)
    expected = int((visible & (norm >= 2e-4)).sum())
    assert out["cloned"] + out["split"] == expected > 0
    assert av.num_gaussians == n + expected - out["pruned"]
    assert ctl.grad_accum.shape == (av.num_gaussians,) and float(ctl.grad_accum.sum()) == 0
    check_optimizer_matches(av, opt)
    # Rectifier state untouched by the surgery.
    assert all(p in opt.state for p in av.rectifier.parameters())
    out = ctl.after_step(4, {"means2d": torch.zeros(av.num_gaussians, 2, requires_grad=True), "visible": torch.ones(av.num_gaussians, dtype=torch.bool)}, W, H)
    assert out.get("reset") is True
    assert ctl.after_step(6, info, W, H) == {}  # past stop: nothing, not even gathering
    with pytest.raises(ValueError):
        ctl.load_state_dict(state)  # for the old count


def test_max_gaussians_cap():
    av, _ = make()
    n = av.num_gaussians
    grad = torch.linspace(0, 1e-3, n)
    c, s = densify(av, None, grad, 2e-4, max_gaussians=n + 7)
    assert c + s == 7 and av.num_gaussians == n + 7


def test_with_the_real_rasterizer():
    from rmavatar.render import rasterize

    av, v = make(rectifier="paper")
    av.active_sh_degree.fill_(1)
    opt = adam_with_state(av)
    ctl = controller(av, opt, start=1, every=1, stop=10, reset_start=100, reset_every=100, grad_threshold=0.0)
    viewmat = torch.eye(4)
    viewmat[2, 3] = 2.0
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    g = av(v, torch.zeros(69))
    img, _, info = rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, viewmat, K, 32, 32, sh_degree=g.sh_degree)
    img.square().mean().backward()
    opt.step()
    n = av.num_gaussians
    out = ctl.after_step(1, info, 32, 32)
    assert out["cloned"] + out["split"] == int(info["visible"].sum()) > 0
    assert av.num_gaussians > n
    check_optimizer_matches(av, opt)
    opt.zero_grad(set_to_none=True)
    g = av(v, torch.zeros(69))
    img, _, info = rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, viewmat, K, 32, 32, sh_degree=g.sh_degree)
    img.square().mean().backward()
    opt.step()
    assert all(p.grad is not None for p in gaussian_parameters(av).values())


def test_controller_state_round_trip_gives_identical_splits():
    def setup():
        av, _ = make(n=150)
        ctl = controller(av, None, start=1, every=1, stop=10, reset_start=99, reset_every=99, percent_dense=0.0,
                         seed=5)
        return av, ctl

    a, ca = setup()
    ca.densify_and_prune()  # advances the split sampler
    b, cb = setup()
    b.load_state_dict(a.state_dict())
    cb.load_state_dict(ca.state_dict())
    for av, ctl in ((a, ca), (b, cb)):
        m = torch.zeros(av.num_gaussians, 2, requires_grad=True)
        m.grad = torch.full((av.num_gaussians, 2), 1e-3)
        ctl.after_step(1, {"means2d": m, "visible": torch.ones(av.num_gaussians, dtype=torch.bool)}, 32, 32)
    assert a.num_gaussians == b.num_gaussians > 150
    assert torch.equal(a.means, b.means) and torch.equal(a.face_ids, b.face_ids)
