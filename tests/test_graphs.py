"""The captured (CUDA graph) code paths: a training step through StepGraphs and a trained avatar posed
through Replay give what the plain composition gives. On the CPU the same code runs without replay; the
cuda variants compare replayed graphs with eager runs where a GPU is present."""

from __future__ import annotations

import gc

import pytest
import torch
from devices import DEVICES

from rmavatar.avatar import load_trained, pose_frame, render_frame
from rmavatar.body import PoseSequence
from rmavatar.train.losses import total_loss
from rmavatar.train.trainer import Trainer
from rmavatar.utils.graphs import Replay

CUDA = pytest.mark.skipif(not torch.cuda.is_available(),
                          reason="no CUDA device here: the cuda variant runs where one is")


@pytest.mark.parametrize("device", DEVICES)
def test_replay_equals_the_function_and_follows_new_inputs(device):
    calls = []

    def fn(a, b):
        calls.append(1)
        return (a @ b).relu(), a.sum(0) * 2

    replay = Replay(fn)
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):  # each call's own inputs, not the first call's
        a, b = (torch.randn(5, 5, generator=gen).to(device) for _ in range(2))
        for got, want in zip(replay(a, b), fn(a, b)):
            torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
    assert replay.captures == (1 if device == "cuda" else 0) and replay.enabled
    c = torch.randn(3, 5, generator=gen).to(device)  # a new shape: captured again on CUDA
    torch.testing.assert_close(replay(c, b)[0], fn(c, b)[0], rtol=0, atol=1e-6)
    assert replay.captures == (2 if device == "cuda" else 0)


@CUDA
def test_cuda_a_function_that_cannot_be_captured_runs_eagerly_and_says_why():
    def reads_the_host(a):
        return (a * float(a.sum()),)  # a host read: not capturable

    replay = Replay(reads_the_host)
    a = torch.ones(3, device="cuda")
    torch.testing.assert_close(replay(a)[0], a * 3)
    assert not replay.enabled and replay.off_reason and replay.captures == 0
    torch.testing.assert_close(replay(a * 2)[0], a * 12)


def _trainer(subject, make_train_config, run, device, graphs: bool):
    cfg = make_train_config(subject, 30, size=32, sh_degree=1, device=device)
    cfg.cuda_graphs = graphs
    cfg.loss.lpips_region = "person"  # the graphs take the window's index tensors as inputs too
    t = Trainer(cfg, run, progress=False)
    t.setup()
    t.iteration = 5  # inside the encoding window's opening: the window is read from the device buffer
    return t


@pytest.mark.parametrize("device", DEVICES)
def test_a_step_through_step_graphs_equals_render_frame_and_total_loss(tiny_subject, make_train_config,
                                                                       tmp_path, device):
    # The step's pieces (posing, eager rasterizer, losses) against the one forward path written plainly:
    # the same loss, terms and parameter gradients. On CUDA the pieces are replayed graphs.
    t = _trainer(tiny_subject, make_train_config, tmp_path / "run", device, graphs=True)
    av, cfg = t.avatar, t.cfg
    for it in range(3):  # the third step replays graphs captured at the first
        i = t.sampler.next()
        av.set_progress(t.iteration + 1, cfg.optim.iters)
        bg = torch.ones(3, device=t.device)
        target = t.frames.target(i, bg)
        vertices, body_pose, table = t.frame_body(i, t.iteration + 1)
        cam = t.frames.cameras[i]
        from rmavatar.render import rasterize

        posed = t.graphs.pose(vertices, body_pose, table, cam.viewmat)
        image, _, _ = rasterize(posed.means, posed.quats, posed.scales, posed.opacities, posed.colors,
                                cam.viewmat, cam.K, cam.width, cam.height, background=bg, check=False)
        window = t.frames.lpips_window(i)
        assert window is not None
        loss, parts = t.graphs.losses(image, target, posed, t.frames.lpips_units(i, bg), window)
        loss.backward()
        got = {n: p.grad.clone() for n, p in av.named_parameters() if p.grad is not None}
        av.zero_grad(set_to_none=True)

        out = render_frame(av, vertices, body_pose, cam, bg, table=table, check=False)
        want_loss, want_parts = total_loss(out.image, target, out.extras, cfg.loss,
                                           lpips_units=t.frames.lpips_units(i, bg), lpips_window=window)
        want_loss.backward()
        want = {n: p.grad.clone() for n, p in av.named_parameters() if p.grad is not None}
        av.zero_grad(set_to_none=True)
        exact = device == "cpu"  # the same operations in the same order; replay may differ in rounding
        tol = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-4, "atol": 1e-6}
        torch.testing.assert_close(image, out.image, **tol)
        torch.testing.assert_close(loss, want_loss, **tol)
        assert parts.keys() == want_parts.keys()
        for k in parts:
            torch.testing.assert_close(parts[k], want_parts[k], **tol)
        assert got.keys() == want.keys() and "rectifier.l1.weight" in got
        for k in got:
            grad_tol = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-3, "atol": 1e-6}
            torch.testing.assert_close(got[k], want[k], **grad_tol)
        t.iteration += 1
    assert t.graphs.captures == (2 if device == "cuda" else 0), t.graphs.off_reason


def test_a_failed_capture_runs_those_steps_eagerly_and_is_tried_again_at_the_next_shapes(
        tiny_subject, make_train_config, tmp_path, monkeypatch):
    # On any device: capturing is made to fail, as it did on an H100 at a run's first re-capture.
    t = _trainer(tiny_subject, make_train_config, tmp_path / "run", "cpu", graphs=True)
    g = t.graphs
    g.enabled, g.off_reason = True, None  # as on a GPU
    monkeypatch.setattr(g, "_pin_accumulators", lambda: None)  # (needs a CUDA stream)
    tries = []

    def fail(fn, sample, **kw):
        tries.append(type(fn).__name__)
        raise RuntimeError("CUDA error: operation failed due to a previous error during capture\nmore")

    monkeypatch.setattr(torch.cuda, "make_graphed_callables", fail)
    monkeypatch.setattr(torch.cuda, "synchronize", lambda *a: None)
    eager = _trainer(tiny_subject, make_train_config, tmp_path / "eager", "cpu", graphs=False)
    for _ in range(3):  # the same shapes: one try per piece, then those steps run eagerly
        got, want = t.step(), eager.step()
        t.iteration += 1
        eager.iteration += 1
        torch.testing.assert_close(got["loss"], want["loss"], rtol=0, atol=0)
    assert tries == ["_Posing", "_Losses"] and g.enabled and g.captures == 0
    assert g.failures == [("posing", "RuntimeError: CUDA error: operation failed due to a previous error "
                                     "during capture")] + [("losses", g.failures[0][1])]
    t.avatar.set_progress = lambda *a: None  # (the schedule would move the switches back)
    t.avatar.rectifier.set_frequency_alpha(t.avatar.rectifier.num_freqs)  # new switches: tried again
    t.step()
    assert tries[-1] == "_Posing" and len(g.failures) == 3
    assert not g.enabled and "3 captures failed" in g.off_reason
    t.step()  # from now on eager, no more tries
    assert len(tries) == 3


@CUDA
def test_cuda_training_steps_with_graphs_follow_the_losses_of_steps_without(tiny_subject, make_train_config,
                                                                           tmp_path):
    # Ten whole steps (Adam included), captured and replayed against eager: the same loss at every step
    # (a graph that read a stale frame, window or parameter would not). Parameters are not compared:
    # Adam's first steps move a parameter by about lr * sign(gradient), so a gradient at rounding level
    # can move it either way in the two runs.
    # The collector runs at almost every allocation, so an old graph left in a reference cycle would be
    # destroyed in the middle of the re-capture.
    losses, thresholds = {}, gc.get_threshold()
    for graphs in (True, False):
        t = _trainer(tiny_subject, make_train_config, tmp_path / f"run{graphs}", "cuda", graphs)
        gc.set_threshold(1, 1, 1)
        try:
            losses[graphs] = []
            for _ in range(10):
                out = t.step()
                t.iteration += 1
                assert bool(out["ok"])
                losses[graphs].append(out["loss"])
        finally:
            gc.set_threshold(*thresholds)
        # posing and losses at iteration 6, posing again at 15 of 30 when the encoding window is open
        assert t.graphs.captures == (3 if graphs else 0) and not t.graphs.failures, t.graphs.failures
    torch.testing.assert_close(torch.stack(losses[True]), torch.stack(losses[False]), rtol=1e-3, atol=1e-6)


@CUDA
def test_cuda_graphs_are_captured_again_as_sh_bands_switch_on(tiny_subject, make_train_config, tmp_path):
    # As in a real run: the first capture at SH degree 0, then one more for each band (at iterations 2, 4
    # and 6 of 30); a 512 px run's first re-capture (degree 0 -> 1) failed on an H100 (docs/gpu.md).
    cfg = make_train_config(tiny_subject, 30, size=64, sh_degree=3, device="cuda")
    cfg.model.sh_every_frac = 2 / 30
    t = Trainer(cfg, tmp_path / "run", progress=False)
    t.setup()
    for _ in range(8):
        assert bool(t.step()["ok"])
        t.iteration += 1
    assert not t.graphs.failures, t.graphs.failures
    assert t.graphs.captures == 5 and t.graphs.enabled


@CUDA
@pytest.mark.parametrize("capacity", [False, True])
def test_cuda_graphs_after_density_control(tiny_subject, make_train_config, tmp_path, capacity):
    # Without capacity buffers densification and pruning replace the parameters: each event is a new
    # signature, captured again. With them (the default with graphs) the rows are rewritten in place and
    # the graphs stay valid: no capture after the first ones, and the steps' losses follow eager steps.
    losses = {}
    for graphs in (True, False):
        cfg = make_train_config(tiny_subject, 30, size=64, sh_degree=0, device="cuda", density=True)
        cfg.density.start, cfg.density.every, cfg.density.reset_start = 2000, 2000, 50_000  # every 1.2 of 30
        cfg.density.capacity, cfg.cuda_graphs = capacity, graphs
        cfg.density.max_gaussians = 100_000  # buffers of that many rows, never outgrown here
        t = Trainer(cfg, tmp_path / f"run{graphs}", progress=False)
        t.setup()
        sizes, losses[graphs] = set(), []
        for _ in range(10):
            out = t.step()
            assert bool(out["ok"])
            t.iteration += 1
            sizes.add(t.avatar.num_gaussians)
            losses[graphs].append(out["loss"])
        assert len(sizes) > 1, "no density event happened: the test does not test re-capturing"
        if graphs:
            assert not t.graphs.failures and t.graphs.enabled, t.graphs.failures
            if capacity:  # posing and losses, once (SH degree 0, the encoding window opens at 15 of 30)
                assert t.graphs.captures == 2 and t.avatar.capacity > max(sizes)
            else:
                assert t.graphs.captures >= 2 + len(sizes) - 1
    if capacity:
        torch.testing.assert_close(torch.stack(losses[True]), torch.stack(losses[False]), rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_posing_a_trained_avatar_equals_the_plain_formula(trained_run, device):
    trained = load_trained(trained_run, device=device)
    gen = torch.Generator().manual_seed(2)
    poses = PoseSequence(0.3 * torch.randn(3, 3, generator=gen), 0.3 * torch.randn(3, 69, generator=gen),
                         0.1 * torch.randn(3, 3, generator=gen))
    for i in range(3):
        got = trained.pose(poses, i)
        one = poses.select(slice(i, i + 1))
        want = trained.gaussians(trained.vertices(one)[0], one.body_pose[0])
        for name in ("means", "quats", "scales", "opacities", "sh", "frames"):
            a, b = getattr(got, name), getattr(want, name)
            assert (a is None) == (b is None), name
            if a is not None:
                torch.testing.assert_close(a, b, rtol=0, atol=0 if device == "cpu" else 1e-5)
        assert got.sh_degree == want.sh_degree
    assert trained.posing_graph.captures == (1 if device == "cuda" else 0), trained.posing_graph.off_reason


@pytest.mark.parametrize("device", DEVICES)
def test_a_refining_step_poses_the_corrected_body_in_the_posing_piece(tiny_subject, make_train_config, tmp_path,
                                                                      device):
    # Pose refinement: the corrected body is posed inside the posing piece (one graph on CUDA); the
    # Gaussians and the corrections' gradient equal the eager corrected body's.
    cfg = make_train_config(tiny_subject, 30, size=32, sh_degree=1, device=device)
    cfg.poses.refine, cfg.poses.warmup, cfg.poses.first_pass, cfg.poses.fits = True, 0.0, 0.0, ()
    t = Trainer(cfg, tmp_path / "run", progress=False)
    t.setup()
    refiner = t.poses.refiner
    with torch.no_grad():
        refiner.delta.normal_(0, 0.02, generator=torch.Generator(device=refiner.delta.device).manual_seed(0))
    for i in (0, 3, 0):
        cam = t.frames.cameras[i]
        inputs = t.poses.frame_inputs(i, 1)
        posed = t.graphs.pose_body(t._pose_corrected, inputs, cam.viewmat)
        (posed.means.sum() + posed.colors.square().sum()).backward()
        got_means, got_grad = posed.means.detach().clone(), refiner.delta.grad.clone()
        refiner.delta.grad = None
        t.avatar.zero_grad(set_to_none=True)
        vertices, body_pose = t._pose_corrected(*refiner.frame_inputs(i))
        gs, _, colors = pose_frame(t.avatar, vertices, body_pose, cam.viewmat)
        (gs.means.sum() + colors.square().sum()).backward()
        tol = {"rtol": 0, "atol": 0} if device == "cpu" else {"rtol": 1e-4, "atol": 1e-5}
        torch.testing.assert_close(got_means, gs.means, **tol)
        torch.testing.assert_close(got_grad, refiner.delta.grad, **tol)
        assert got_grad[i].abs().sum() > 0 and got_grad[1].abs().sum() == 0  # only the frame's own row
        refiner.delta.grad = None
        t.avatar.zero_grad(set_to_none=True)
    assert t.graphs.captures == (1 if device == "cuda" else 0), t.graphs.off_reason
