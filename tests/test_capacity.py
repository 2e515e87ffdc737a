"""Capacity buffers (issue 42): the Gaussians in fixed-size tensors, live rows first, so a captured CUDA
graph stays valid across density events. On the CPU: the same surgery, the same training and the same
checkpoints as without them."""

import pytest
import torch
import trimesh
from test_density import adam_with_state, make

from rmavatar.avatar import GAUSSIAN_PARAMS, Avatar, AvatarConfig
from rmavatar.avatar.rows import RowGathers
from rmavatar.avatar.run import RunFolder
from rmavatar.train.density import densify, grown_capacity, prune, use_capacity
from rmavatar.train.losses import _Regularisers
from rmavatar.train.trainer import Trainer

from helpers import tiny_train_config


def _pair(cap: int):
    """Two equal avatars with equal Adam state, the second in capacity buffers of ``cap`` rows."""
    (a, _), (b, _) = make(rectifier="paper"), make(rectifier="paper")
    for av in (a, b):
        with torch.no_grad():
            av.log_scales[::2] -= 4.0  # small ones are cloned, the others split
    oa, ob = adam_with_state(a), adam_with_state(b)
    use_capacity(b, ob, cap)
    return (a, oa), (b, ob)


def _assert_live_rows_equal(a, oa, b, ob):
    n = a.num_gaussians
    assert b.num_gaussians == n and b.capacity >= n
    assert torch.equal(a.face_ids, b.face_ids[:n])
    for name in GAUSSIAN_PARAMS:
        pa, pb = getattr(a, name), getattr(b, name)
        assert torch.equal(pa, pb[:n]), name
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(oa.state[pa][key], ob.state[pb][key][:n]), (name, key)
            assert not ob.state[pb][key][n:].any(), (name, key)  # unused rows: no moments
    assert torch.equal(b.live, (torch.arange(b.capacity) < n).float())
    assert torch.allclose(b.row_weights.sum(), torch.tensor(1.0))
    assert not b.means[n:].any() and torch.equal(b.quats[n:, 0], torch.ones(b.capacity - n))


def test_densify_and_prune_rewrite_the_rows_in_place_as_the_plain_surgery_would():
    (a, oa), (b, ob) = _pair(cap=400)
    n0, capacity, where = a.num_gaussians, b.capacity, b.means.data_ptr()
    assert capacity == 400 and b.num_gaussians == n0 < capacity
    grad = torch.linspace(0, 1e-3, n0)
    for av, opt in ((a, oa), (b, ob)):
        gen = torch.Generator().manual_seed(3)
        clones, splits = densify(av, opt, grad, 2e-4, percent_dense=0.02, generator=gen)
        assert clones > 0 and splits > 0
        with torch.no_grad():
            n = av.num_gaussians  # the last ten are clones: their faces keep their other Gaussian
            av.opacity_logits[n - 10:n] = -20.0
        assert prune(av, opt) > 0
    _assert_live_rows_equal(a, oa, b, ob)
    # In place: the parameters are the same tensors in the same memory, and so are the optimiser's.
    assert b.capacity == capacity and b.means.data_ptr() == where
    assert ob.param_groups[0]["params"][0] is b.means


def test_the_rows_gathers_are_rewritten_in_place_with_the_values_of_fresh_ones():
    """A captured posing graph reads each row's face slot and the local rectifier's per-row constants
    where they are: density control rewrites them in place, with what a fresh gather gives."""
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    v, f = torch.tensor(mesh.vertices, dtype=torch.float32), torch.tensor(mesh.faces)
    weights = torch.softmax(4 * torch.randn(len(v), 24, generator=torch.Generator().manual_seed(1)), -1)
    av = Avatar(f, None, v, AvatarConfig(rectifier="local", sh_degree=1), joint_weights=weights)
    with torch.no_grad():
        av.log_scales[::2] -= 4.0
    opt = adam_with_state(av)
    use_capacity(av, opt, 400)
    held = (av.rows.slot(av), *av.rows.local(av))  # what a captured graph holds
    densify(av, opt, torch.linspace(0, 1e-3, av.num_gaussians), 2e-4, percent_dense=0.02,
            generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        av.opacity_logits[av.num_gaussians - 10 : av.num_gaussians] = -20.0
    assert prune(av, opt) > 0 and av.num_gaussians > len(f)
    fresh = RowGathers()  # the held tensors hold the new rows' values already, without being asked again
    for got, want in zip(held, (fresh.slot(av), *fresh.local(av))):
        assert torch.equal(got, want)
    assert all(a is b for a, b in zip(held, (av.rows.slot(av), *av.rows.local(av))))


def test_outgrowing_the_buffers_reallocates_half_as_many_again():
    (a, oa), (b, ob) = _pair(cap=0)
    n0 = a.num_gaussians
    assert b.capacity == grown_capacity(n0) == 1024
    for av, opt in ((a, oa), (b, ob)):  # every Gaussian split: twice as many, then again
        for _ in range(4):
            gen = torch.Generator().manual_seed(av.num_gaussians)
            densify(av, opt, torch.ones(av.num_gaussians), 2e-4, generator=gen)
    assert a.num_gaussians == 16 * n0 > 1024
    _assert_live_rows_equal(a, oa, b, ob)
    assert b.capacity == grown_capacity(16 * n0) and ob.param_groups[0]["params"][0] is b.means


def test_the_regularisers_of_capacity_buffers_are_those_of_the_live_rows():
    gen = torch.Generator().manual_seed(0)
    n, capacity = 70, 128
    live = (torch.arange(capacity) < n).float()
    inputs = [torch.randn(capacity, k, generator=gen, dtype=torch.float64) for k in (3, 3, 3, 3, 4)]
    inputs[1] = inputs[1] - 1.0  # some scales under the threshold, some over
    full = [t.clone().requires_grad_() for t in inputs]
    rows = [t[:n].clone().requires_grad_() for t in inputs]
    got = _Regularisers.apply(*full, 1.0, 0.6, live / n)
    want = _Regularisers.apply(*rows, 1.0, 0.6)
    torch.testing.assert_close(got, want)
    torch.testing.assert_close(_Regularisers.reference(*full, 1.0, 0.6, live / n), want)
    weights = torch.tensor([0.3, -1.1, 2.0], dtype=torch.float64)
    (got @ weights).backward()
    (want @ weights).backward()
    for f, r in zip(full, rows):
        torch.testing.assert_close(f.grad[:n], r.grad)
        assert not f.grad[n:].any()  # an unused row gets no gradient


SIZE, ITERS = 48, 12


@pytest.fixture(scope="module")
def data(tmp_path_factory, make_synth_subject):
    out = tmp_path_factory.mktemp("synth") / "subject"
    return str(make_synth_subject(out, size=SIZE, seed=0, train=8, test=1, novel_pose=1, ss=1))


def _cfg(data, capacity, max_gaussians=0):
    """The full model's defaults; the run-length-scaled schedule densifies and prunes at every iteration
    from 2 to 7 and resets opacities at each."""
    cfg = tiny_train_config(data, ITERS, size=SIZE, density=True, device="cpu", threads=1, preview_every=10**6)
    cfg.density.capacity, cfg.density.max_gaussians = capacity, max_gaussians
    # The two runs sum over different rows, so their gradients differ by rounding. With the default
    # epsilon (1e-15) Adam turns a gradient of rounding size into a whole step of lr whose sign is the
    # rounding's: on a machine with AVX-512 four quaternion entries of 130k then differed by 1e-4 after 12
    # steps. With 1e-10 a rounding-size gradient moves its parameter by a rounding-size step, and the
    # largest difference was 1.3e-6: the comparison below then tells the buffers' arithmetic apart from
    # Adam's amplification of rounding.
    cfg.optim.adam_eps = 1e-10
    # float32, not "auto": where the CPU has bf16 dot products "auto" rounds the rectifier's products to
    # bf16's 3 digits, and the buffers' extra rows would then move those roundings, not the buffers' own
    # arithmetic under test.
    cfg.model.rectifier_precision = "float32"
    return cfg


def _steps(t, upto):
    losses = []
    while t.iteration < upto:
        out = t.step()
        t.iteration += 1
        assert bool(out["ok"])
        losses.append(out["loss"])
    return losses


def _live(t):
    """The live Gaussians' parameters and faces."""
    n = t.avatar.num_gaussians
    return {name: getattr(t.avatar, name).detach()[:n] for name in (*GAUSSIAN_PARAMS, "face_ids")}


def _assert_same_training(a, b, losses_a, losses_b):
    # Float rounding only: the regularisers' means and the rectifier's gradients sum over more rows.
    torch.testing.assert_close(torch.stack(losses_a), torch.stack(losses_b), rtol=1e-5, atol=1e-7)
    la, lb = _live(a), _live(b)
    assert torch.equal(la["face_ids"], lb["face_ids"])
    for name in GAUSSIAN_PARAMS:
        torch.testing.assert_close(la[name], lb[name], rtol=1e-4, atol=1e-5, msg=name)


def test_a_run_in_capacity_buffers_trains_the_same_avatar(data, tmp_path):
    plain = Trainer(_cfg(data, False), tmp_path / "plain", progress=False)
    plain.setup()
    losses_plain = _steps(plain, ITERS)
    sizes = set()
    buffered = Trainer(_cfg(data, True, max_gaussians=3 * plain.avatar.num_gaussians), tmp_path / "buffered",
                       progress=False)
    buffered.setup()
    where, capacity = buffered.avatar.means.data_ptr(), buffered.avatar.capacity
    losses = []
    while buffered.iteration < ITERS:
        losses += _steps(buffered, buffered.iteration + 1)
        sizes.add(buffered.avatar.num_gaussians)
    assert len(sizes) > 2, "the schedule changed the count too seldom to test anything"
    assert buffered.avatar.capacity == capacity > max(sizes) and buffered.avatar.means.data_ptr() == where
    _assert_same_training(plain, buffered, losses_plain, losses)
    # the unused rows never moved: no gradient reached them, Adam left them alone
    n = buffered.avatar.num_gaussians
    assert not buffered.avatar.means[n:].any() and not buffered.avatar.sh_dc[n:].any()
    assert not buffered.avatar.opacity_logits[n:].any()


@pytest.mark.parametrize("first, second", [(True, False), (False, True)])
def test_checkpoints_hold_the_live_rows_and_resume_either_way(data, tmp_path, first, second):
    straight = Trainer(_cfg(data, second), tmp_path / "straight", progress=False)
    straight.setup()
    losses_straight = _steps(straight, ITERS)

    half = Trainer(_cfg(data, first), tmp_path / "split", progress=False)
    half.setup()
    losses = _steps(half, 5)
    half.save()
    ckpt = RunFolder(tmp_path / "split").read_checkpoint()
    n = half.avatar.num_gaussians
    assert ckpt.avatar["state_dict"]["means"].shape[0] == n
    assert ckpt.density["grad_accum"].shape == (n,)
    for index, name in enumerate(GAUSSIAN_PARAMS):  # the optimiser's first groups, one parameter each
        assert ckpt.optimizer["state"][index]["exp_avg"].shape == getattr(half.avatar, name)[:n].shape, name
    rest = Trainer(_cfg(data, second), tmp_path / "split", checkpoint=ckpt, progress=False)
    rest.setup()
    assert (rest.avatar.live_rows is not None) == second and rest.avatar.num_gaussians == n
    losses += _steps(rest, ITERS)
    _assert_same_training(straight, rest, losses_straight, losses)
