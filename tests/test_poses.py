"""Pose corrections and pose errors (body.corrections), the pose-refinement config, the per-frame Adam,
and checkpoint migration to the pose-carrying format."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from rmavatar.body import CORRECTION_DIM, PoseSequence, apply_pose_corrections, joint_angle_errors, pose_error
from rmavatar.avatar.run import CHECKPOINT_VERSION
from rmavatar.body.corrections import pose_corrections
from rmavatar.train.config import TrainConfig, from_dict, load_config, save_config, to_dict
from rmavatar.train.pose_refine import PoseConfig
from rmavatar.utils import UserError


def _random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return PoseSequence.from_arrays(rng.normal(0, 1.0, (n, 3)), rng.normal(0, 0.5, (n, 69)), rng.normal(0, 0.3, (n, 3)))


def test_angle_error_of_a_known_turn_is_its_angle():
    # Every joint of frame k turned by a known angle about a random axis: the error is that angle.
    n = 3
    base = _random_poses(n)
    angles = np.array([1.0, 7.5, 170.0])  # degrees, near pi too
    rng = np.random.default_rng(1)
    turned = []
    for key, k in (("global_orient", 1), ("body_pose", 23)):
        r = getattr(base, key).numpy().reshape(n, k, 3)
        axes = rng.normal(size=(n, k, 3))
        axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
        delta = axes * np.deg2rad(angles)[:, None, None]
        rot = Rotation.from_rotvec(delta.reshape(-1, 3)) * Rotation.from_rotvec(r.reshape(-1, 3))
        turned.append(rot.as_rotvec().reshape(n, 3 * k))
    other = PoseSequence.from_arrays(turned[0], turned[1], base.transl + torch.tensor([0.0, 0.003, 0.004]))
    err = joint_angle_errors(base, other)
    assert err.shape == (n, 24)
    np.testing.assert_allclose(err.numpy(), np.repeat(angles[:, None], 24, 1), atol=2e-3)
    summary = pose_error(base, other)
    assert summary["joint_angle_deg"] == pytest.approx(angles.mean(), abs=2e-3)
    assert summary["transl_mm"] == pytest.approx(5.0, abs=1e-3)
    assert pose_error(base, base)["joint_angle_deg"] == pytest.approx(0.0, abs=1e-6)


def test_corrections_compose_on_the_left_and_undo_noise():
    base = _random_poses(4)
    delta = torch.tensor(np.random.default_rng(2).normal(0, 0.1, (4, CORRECTION_DIM)), dtype=torch.float32)
    fixed = apply_pose_corrections(base, delta)
    for j in range(24):
        rv = torch.cat((base.global_orient, base.body_pose), 1).reshape(4, 24, 3)[:, j]
        out = torch.cat((fixed.global_orient, fixed.body_pose), 1).reshape(4, 24, 3)[:, j]
        want = Rotation.from_rotvec(delta[:, 3 * j: 3 * j + 3].numpy()) * Rotation.from_rotvec(rv.numpy())
        np.testing.assert_allclose(Rotation.from_rotvec(out.numpy()).as_matrix(), want.as_matrix(), atol=1e-5)
    torch.testing.assert_close(fixed.transl, base.transl + delta[:, -3:])
    # Zero corrections give the poses back; the angle error of a correction is its length.
    zero = apply_pose_corrections(base, torch.zeros(4, CORRECTION_DIM))
    assert pose_error(zero, base)["joint_angle_deg"] < 1e-3
    lengths = torch.linalg.vector_norm(delta[:, :72].reshape(4, 24, 3), dim=-1).double() * 180 / math.pi
    np.testing.assert_allclose(joint_angle_errors(base, fixed).numpy(), lengths.numpy(), atol=2e-3)


def test_pose_corrections_undo_apply_also_near_a_half_turn():
    """pose_corrections(base, target) is the correction apply_pose_corrections needs to reach target,
    checked in float64 with scipy's rotations, also for targets turned by nearly pi from the base."""
    base = PoseSequence(*(getattr(_random_poses(5), k).double() for k in ("global_orient", "body_pose", "transl")))
    rng = np.random.default_rng(7)
    turn = Rotation.from_rotvec(rng.normal(size=(5 * 24, 3)))
    turn = Rotation.from_rotvec(turn.as_rotvec() / np.linalg.norm(turn.as_rotvec(), axis=1, keepdims=True)
                                * rng.uniform(0.0, math.pi - 1e-3, (5 * 24, 1)))
    rv = torch.cat((base.global_orient, base.body_pose), 1).reshape(-1, 3).double().numpy()
    target_rv = (turn * Rotation.from_rotvec(rv)).as_rotvec().reshape(5, 72)
    target = PoseSequence(torch.tensor(target_rv[:, :3]), torch.tensor(target_rv[:, 3:]),
                          torch.tensor(rng.normal(size=(5, 3))))
    delta = pose_corrections(base, target)
    assert delta.shape == (5, CORRECTION_DIM)
    np.testing.assert_allclose(Rotation.from_rotvec(delta[:, :72].reshape(-1, 3).numpy()).as_matrix(),
                               turn.as_matrix(), atol=1e-9)
    back = apply_pose_corrections(base, delta)
    assert pose_error(back, target)["joint_angle_deg"] < 1e-6
    torch.testing.assert_close(back.transl, target.transl.to(back.transl))
    with pytest.raises(ValueError, match="lengths"):
        pose_corrections(base, target.select(slice(0, 2)))


def test_corrections_have_finite_gradients_at_zero():
    base = _random_poses(2)
    delta = torch.zeros(2, CORRECTION_DIM, requires_grad=True)
    out = apply_pose_corrections(base, delta)
    (out.body_pose.sum() + out.global_orient.sum() + out.transl.sum()).backward()
    assert torch.isfinite(delta.grad).all() and delta.grad.abs().sum() > 0


def test_refine_poses_config_round_trips_and_resolves(tmp_path):
    for value in (None, True, False):
        cfg = TrainConfig()
        cfg.poses.refine = value
        cfg.poses.lr_rotation = 0.02
        save_config(cfg, tmp_path / "c.yaml")
        back = load_config(tmp_path / "c.yaml")
        assert back.poses.refine is value and back.poses.lr_rotation == 0.02
        assert to_dict(from_dict(TrainConfig, to_dict(cfg))) == to_dict(cfg)
    assert PoseConfig().refines(True) and not PoseConfig().refines(False)
    assert not PoseConfig(refine=False).refines(True)
    assert PoseConfig(refine=True).refines(False)
    (tmp_path / "bad.yaml").write_text("poses:\n  refine: maybe\n")
    with pytest.raises(UserError, match="poses.refine"):
        load_config(tmp_path / "bad.yaml")
    with pytest.raises(UserError, match="poses.warmup"):
        PoseConfig(warmup=1.0).validate()
    for bad in (-1, 1.5, True):
        with pytest.raises(UserError, match="poses.smooth"):
            PoseConfig(smooth=bad).validate()
    for bad in (0.75, [0.0], [1.0], ["x"], [True]):
        with pytest.raises(UserError, match="poses.fits"):
            PoseConfig(fits=bad).validate()
    for bad in (0.75, [0.0], [1.0], ["x"], [True]):
        with pytest.raises(UserError, match="poses.held_fits"):
            PoseConfig(held_fits=bad).validate()
    for bad in ((), (0,), (1.5,), (True,), 2, "4,2,1"):
        with pytest.raises(UserError, match="poses.held_fit_scales"):
            PoseConfig(held_fit_scales=bad).validate()
    assert PoseConfig(held_fit_scales=[2.0, 1]).validate().held_fit_scales == (2, 1)  # as YAML may spell it
    assert PoseConfig(held_fit_scales=[2, 1]).validate().fit_config(held=True).scales == (2, 1)
    assert PoseConfig(held_fit_scales=(1,)).validate().fit_config(held=False).scales == (4, 2, 1)
    for bad in (0.0, -1e-3, float("nan"), True):
        with pytest.raises(UserError, match="held_fit_lr_rotation"):
            PoseConfig(held_fit_lr_rotation=bad).validate()
    with pytest.raises(UserError, match="poses.fit_steps"):
        PoseConfig(fit_steps=0).validate()
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(UserError, match="poses.fit_mask"):
            PoseConfig(fit_mask=bad).validate()
    PoseConfig(fit_mask=0.0).validate()
    for bad in (-0.1, 1.5, True, "half"):
        with pytest.raises(UserError, match="poses.first_pass"):
            PoseConfig(first_pass=bad).validate()
    # The pose pass runs only with refinement, round(fraction * iters) long, at least one iteration.
    assert PoseConfig().first_pass_iters(1000, True) == 100
    assert PoseConfig(first_pass=0.5).first_pass_iters(1000, True) == 500
    assert PoseConfig().first_pass_iters(1000, False) == 0
    assert PoseConfig(first_pass=0.0).first_pass_iters(1000, True) == 0
    assert PoseConfig(first_pass=0.1).first_pass_iters(3, True) == 1
    for bad in (0.0, -0.5, 1.5, float("nan"), True, "half"):
        with pytest.raises(UserError, match="poses.first_pass_scale"):
            PoseConfig(first_pass_scale=bad).validate()
    # the first pass's size: its longer side scaled, never below LPIPS's 32 px nor above the run's own
    assert PoseConfig().first_pass_size((512, 384)) is None
    assert PoseConfig(first_pass_scale=0.5).first_pass_size((512, 384)) == 256
    assert PoseConfig(first_pass_scale=0.5).first_pass_size((48, 48)) == 32
    assert PoseConfig(first_pass_scale=0.5).first_pass_size((20, 20)) == 20
    (tmp_path / "fits.yaml").write_text("poses:\n  fits: [0.5, 0.8]\n")
    cfg = load_config(tmp_path / "fits.yaml").validate()
    assert cfg.poses.fits == (0.5, 0.8)
    assert cfg.poses.fit_iterations(1000, 40) == {500, 800}


def test_a_config_file_of_the_old_layout_is_read_in_the_new_one(tmp_path):
    """Before checkpoint version 5 pose refinement's settings were in "optim" (pose_sweeps, pose_refits,
    pose_refit_lr with an unwritten 1/40 for translations, ...): a hand-written config of that layout
    reads as today's, missing settings at their defaults; a run's own unstamped RUN/config.yaml
    (``as_trained``) gets the values its run was trained with for settings it predates."""
    (tmp_path / "old.yaml").write_text("optim:\n  iters: 7\n  refine_poses: true\n  pose_sweeps: [0.5, 0.8]\n"
                                       "  pose_refit_lr: 0.004\n")
    cfg = load_config(tmp_path / "old.yaml")
    assert cfg.optim.iters == 7 and cfg.poses.refine is True and cfg.poses.fits == (0.5, 0.8)
    assert cfg.poses.held_fit_lr_rotation == 0.004 and cfg.poses.held_fit_lr_translation == 0.004 / 40
    assert cfg.poses.held_fits == PoseConfig().held_fits and cfg.poses.smooth == PoseConfig().smooth
    trained = load_config(tmp_path / "old.yaml", as_trained=True)
    assert trained.poses.held_fits == () and trained.poses.smooth == 0 and trained.poses.first_pass == 0
    assert trained.poses.fit_mask == 1.0 and trained.poses.fits == (0.5, 0.8)
    (tmp_path / "bad.yaml").write_text("optim:\n  refine_poses: maybe\n")
    with pytest.raises(UserError, match="poses.refine"):
        load_config(tmp_path / "bad.yaml")
    save_config(cfg, tmp_path / "new.yaml")  # written stamped: read back as it is, also as a run's own
    assert (tmp_path / "new.yaml").read_text().startswith(f"version: {CHECKPOINT_VERSION}\n")
    assert to_dict(load_config(tmp_path / "new.yaml", as_trained=True)) == to_dict(cfg)


def test_a_sweep_on_an_opacity_reset_runs_before_it():
    """1,000 steps with the paper's schedule reset opacities at 200, 300, ..., 600: a pose fit that falls
    on one of them fits the avatar one step earlier, before it turns nearly transparent; others stay."""
    from rmavatar.train.density import DensityConfig

    poses = PoseConfig(fits=(0.3, 0.45, 0.6, 0.75), held_fits=(0.5, 0.8)).validate()
    schedule = DensityConfig().schedule(1000)
    assert [s for s in range(1, 1001) if schedule.reset_at(s)] == [200, 300, 400, 500, 600]
    assert poses.fit_iterations(1000, 40, schedule) == {299, 450, 599, 750}
    assert poses.fit_iterations(1000, 40) == {300, 450, 600, 750}
    assert poses.fit_iterations(1000, 40, schedule, held=True) == {499, 800}  # the second pass's, the same rule


def test_the_held_fits_by_default_are_three_and_five_in_a_long_run():
    """poses.held_fits None (the default): five held fits from 3 x held_fit_steps x frames iterations of the
    second pass (6,000 for 100 frames at 20 steps: five fits of 20 steps cost at most 5/3 frame-steps per
    iteration), three before; a longer fit or more frames move the threshold; an explicit list is kept."""
    from rmavatar.train.pose_refine import LONG_HELD_FITS, SHORT_HELD_FITS

    cfg = PoseConfig().validate()
    assert cfg.held_fits is None and cfg.held_fit_steps == 20
    assert SHORT_HELD_FITS == (0.25, 0.6, 0.85) and LONG_HELD_FITS == (0.2, 0.4, 0.6, 0.8, 0.95)
    assert cfg.held_fit_fractions(5999, 100) == SHORT_HELD_FITS
    assert cfg.held_fit_fractions(6000, 100) == LONG_HELD_FITS
    assert cfg.held_fit_fractions(6000, 101) == SHORT_HELD_FITS
    assert cfg.held_fit_fractions(50_000, 40) == LONG_HELD_FITS
    assert PoseConfig(held_fit_steps=40).held_fit_fractions(8000, 100) == SHORT_HELD_FITS
    assert PoseConfig(held_fits=(0.5,)).validate().held_fit_fractions(50_000, 10) == (0.5,)
    assert PoseConfig(held_fits=()).validate().held_fit_fractions(50_000, 10) == ()
    assert cfg.fit_iterations(8000, 100, held=True) == {1600, 3200, 4800, 6400, 7600}
    assert cfg.fit_iterations(4000, 100, held=True) == {1000, 2400, 3400}
    assert cfg.fit_iterations(8000, 100) == {7200}  # the first pass's fits are not by length
    # the strategy counts its training frames: 3 frames at 2 steps make 18 iterations a long second pass
    short = PoseConfig(held_fit_steps=2).validate().build(_random_poses(3), None, range(3), 17, "cpu", held=True)
    long = PoseConfig(held_fit_steps=2).validate().build(_random_poses(3), None, range(3), 18, "cpu", held=True)
    assert short.fit_at == {4, 10, 14} and long.fit_at == {4, 7, 11, 14, 17}
    # a fit that rounds to a short pass's last iteration runs before that step (after it none would)
    assert cfg.fit_iterations(4, 3) == {3} and cfg.fit_iterations(2, 3) == {1} and cfg.fit_iterations(1, 3) == {1}
    assert cfg.fit_iterations(5, 3, held=True) == {1, 3, 4}


def test_pose_lr_schedule_is_frozen_then_decays():
    cfg = PoseConfig(warmup=0.2, lr_final_scale=0.1)
    assert cfg.warmup_steps(100) == 20
    assert cfg.lr_scale(0, 100) == 0.0 and cfg.lr_scale(19, 100) == 0.0
    assert cfg.lr_scale(20, 100) == pytest.approx(1.0)
    assert cfg.lr_scale(100, 100) == pytest.approx(0.1)
    assert cfg.lr_scale(60, 100) == pytest.approx(math.sqrt(0.1))  # log-linear: halfway is the geometric mean


def test_per_frame_adam_moves_only_the_trained_frame_along_its_gradient():
    from rmavatar.train.poses import PoseRefiner

    cfg = PoseConfig(warmup=0.0, lr_rotation=0.01, lr_translation=0.002, lr_final_scale=1.0)
    ref = PoseRefiner(_random_poses(3), None, cfg, 10, torch.device("cpu"))
    grad = torch.zeros(3, CORRECTION_DIM)
    grad[1] = torch.linspace(-1, 1, CORRECTION_DIM) + 0.01
    ref.delta.grad = grad.clone()
    ref.step(1, 1, torch.tensor(True))
    # One second moment per frame (the gradient's squared norm): the first step is lr * g / |g|, along
    # the gradient (a coordinate with a small gradient moves little); other frames do not move.
    lr = torch.cat((torch.full((72,), 0.01), torch.full((3,), 0.002)))
    expected = -lr * grad[1] / grad[1].norm()
    torch.testing.assert_close(ref.delta[1].detach(), expected, atol=1e-7, rtol=1e-4)
    # With a constant gradient the bias-corrected moments are g and |g|^2: the same step again.
    ref.delta.grad = grad.clone()
    ref.step(1, 2, torch.tensor(True))
    torch.testing.assert_close(ref.delta[1].detach(), 2 * expected, atol=1e-7, rtol=1e-4)
    assert ref.delta[0].abs().sum() == 0 and ref.delta[2].abs().sum() == 0
    assert ref.steps.tolist() == [0, 2, 0] and ref.delta.grad is None
    # A state dict restores exactly; a changed dataset pose is refused.
    other = PoseRefiner(_random_poses(3), None, cfg, 10, torch.device("cpu"))
    other.load_state_dict(ref.state_dict(), "ckpt")
    assert torch.equal(other.delta, ref.delta) and torch.equal(other.steps, ref.steps)
    with pytest.raises(UserError, match="changed"):
        PoseRefiner(_random_poses(3, seed=5), None, cfg, 10, torch.device("cpu")).load_state_dict(ref.state_dict(), "ckpt")
    # A pose sweep's fitted poses become the corrected poses, and every frame's Adam starts afresh.
    target = _random_poses(3, seed=9)
    ref.set_poses(target)
    assert pose_error(ref.poses(), target)["joint_angle_deg"] < 1e-3
    assert ref.steps.sum() == 0 and ref.exp_avg.abs().sum() == 0 and ref.exp_avg_sq.abs().sum() == 0
    ref.set_poses(PoseSequence(*(getattr(ref.base, k).cpu() for k in ("global_orient", "body_pose", "transl"))))
    assert ref.delta.abs().max() < 1e-5
    ref.delta.grad = grad.clone()
    ref.step(1, 1, torch.tensor(True))
    # A step the trainer's device-side check rejects (a non-finite gradient) changes nothing.
    state = [t.detach().clone() for t in (ref.delta, ref.exp_avg, ref.exp_avg_sq, ref.steps)]
    bad = grad.clone()
    bad[1, 5] = float("nan")
    ref.delta.grad = bad
    ref.step(1, 3, torch.tensor(False))
    for before, after in zip(state, (ref.delta, ref.exp_avg, ref.exp_avg_sq, ref.steps)):
        assert torch.equal(before, after.detach())


def test_per_joint_adam_moves_each_joint_along_its_own_gradient():
    """A second moment per joint ([n,25], as test-time fitting keeps it): the first step is lr * g / |g_j|
    for joint j's three values (and the translation's), so every joint with a gradient moves by lr."""
    from rmavatar.body.corrections import correction_adam_step

    grad = torch.zeros(2, CORRECTION_DIM, dtype=torch.float64)
    grad[1] = torch.linspace(-1, 1, CORRECTION_DIM, dtype=torch.float64) + 0.01
    grad[1, 30:33] = 0.0  # a joint the image does not see stays put
    delta = torch.zeros_like(grad)
    exp_avg, exp_avg_sq = torch.zeros_like(grad), torch.zeros(2, 25, dtype=torch.float64)
    steps = torch.zeros(2, dtype=torch.long)
    lr = torch.cat((torch.full((72,), 0.01), torch.full((3,), 0.002))).double()
    correction_adam_step(delta, grad[1:], exp_avg, exp_avg_sq, steps, slice(1, 2), lr)
    g = grad[1]
    norms = torch.cat((g[:72].reshape(24, 3).norm(dim=-1).repeat_interleave(3), g[72:].norm().expand(3)))
    expected = -lr * g / norms.clamp_min(1e-300)
    expected[30:33] = 0.0
    torch.testing.assert_close(delta[1], expected, atol=1e-9, rtol=1e-6)
    step_lengths = delta[1, :72].reshape(24, 3).norm(dim=-1)
    assert torch.allclose(step_lengths[torch.arange(24) != 10], torch.tensor(0.01, dtype=torch.float64))
    assert delta[0].abs().sum() == 0 and steps.tolist() == [0, 1]


def test_fit_config_refuses_bad_settings():
    from rmavatar.evaluate.fit import PoseFitConfig

    for bad, match in (({"steps": 0}, "at least 1 step"), ({"refresh": 0}, "refresh"), ({"scales": (4, 0)}, "scales"),
                       ({"scales": ()}, "scales"), ({"scales": (1.5,)}, "scales"), ({"scales": (True,)}, "fit.scales"),
                       ({"scales": "4,2,1"}, "fit.scales"), ({"smooth": -1}, "smoothing"),
                       ({"smooth": 1.5}, "smoothing"), ({"prior": -0.1}, "fit.prior"),
                       ({"lr_rotation": -0.01}, "fit.lr_rotation"), ({"lr_translation": float("nan")}, "finite"),
                       ({"final_scale": 0.0}, "fit.final_scale"), ({"silhouette": float("inf")}, "finite")):
        with pytest.raises(UserError, match=match):
            PoseFitConfig(**bad).validate()
    assert "4x4 then 2x2 then 1x1" in PoseFitConfig().protocol()["loss"]
    assert "0.01 x sum of the squared joint corrections" in PoseFitConfig().protocol()["loss"]


def test_a_version_6_run_keeps_the_pose_refinement_defaults_it_was_trained_with(tmp_path):
    """Version 7 changed the pose-refinement defaults: a run's own config of version 6 (as_trained; a
    checkpoint's always) that lacks one of those settings reads with version 6's default; one it has
    stays; a hand-written version 6 file, and any file of today's version, take today's defaults."""
    from rmavatar.avatar.run import MIGRATIONS, POSE_DEFAULTS_V6, POSE_DEFAULTS_V8, migrate_config

    before = {"first_pass": 0.5, "fits": (0.2, 0.45), "fit_steps": 30, "held_fits": (0.4, 0.7), "held_fit_steps": 30,
              "held_fit_scales": (4, 2, 1), "smooth_held": False}
    assert POSE_DEFAULTS_V6 == before and all(getattr(PoseConfig(), k) != v for k, v in before.items())
    v6 = {"poses": {"refine": True, "first_pass": 0.2}, "optim": {"iters": 10}}
    trained = migrate_config(v6, 6, as_trained=True)["poses"]
    assert trained == {**before, "refine": True, "first_pass": 0.2, **POSE_DEFAULTS_V8}  # and version 8's
    assert migrate_config(v6, 6, as_trained=False) == v6
    assert migrate_config({"optim": {"iters": 10}}, 6, as_trained=True)["poses"] == {**before, **POSE_DEFAULTS_V8}
    assert migrate_config(v6, CHECKPOINT_VERSION, as_trained=True) == v6
    payload = {"version": 6, "config": v6, "iteration": 4}
    assert MIGRATIONS[6](payload)["config"]["poses"]["held_fits"] == (0.4, 0.7)
    assert payload["config"]["poses"] == {"refine": True, "first_pass": 0.2}  # the payload read is not changed
    (tmp_path / "run_v6.yaml").write_text("version: 6\nposes:\n  refine: true\n")
    cfg = load_config(tmp_path / "run_v6.yaml", as_trained=True)
    assert cfg.poses.first_pass == 0.5 and cfg.poses.held_fit_scales == (4, 2, 1) and not cfg.poses.smooth_held
    assert load_config(tmp_path / "run_v6.yaml").poses.held_fits == PoseConfig().held_fits
    (tmp_path / "bad.yaml").write_text("version: 6\nposes: 3\n")  # not a section: refused, not replaced
    with pytest.raises(UserError, match="poses"):
        load_config(tmp_path / "bad.yaml", as_trained=True)


def test_a_version_7_run_keeps_its_three_held_fits(tmp_path):
    """Version 8 made the held fits' default depend on the run's length (None): a run's own config of
    version 7 that lacks poses.held_fits, and its checkpoint, read version 7's three; one it has stays; a
    hand-written version 7 file, and a file of today's version, take today's default."""
    from rmavatar.avatar.run import MIGRATIONS, POSE_DEFAULTS_V7, migrate_config

    assert POSE_DEFAULTS_V7 == {"held_fits": (0.25, 0.6, 0.85)} and PoseConfig().held_fits is None
    v7 = {"poses": {"refine": True}, "optim": {"iters": 8000}}
    assert migrate_config(v7, 7, as_trained=True)["poses"] == {"refine": True, "held_fits": (0.25, 0.6, 0.85),
                                                               "held_fit_prior": 0.01, "held_fit_anchor": "start"}
    assert migrate_config({"poses": {"held_fits": (0.5,)}}, 7, as_trained=True)["poses"]["held_fits"] == (0.5,)
    assert migrate_config(v7, 7, as_trained=False) == v7 and migrate_config(v7, 9, as_trained=True) == v7
    payload = {"version": 7, "config": v7, "iteration": 4}
    assert MIGRATIONS[7](payload)["config"]["poses"]["held_fits"] == (0.25, 0.6, 0.85)
    assert payload["config"] == v7  # the payload read is not changed
    (tmp_path / "run_v7.yaml").write_text("version: 7\nposes:\n  refine: true\n")
    assert load_config(tmp_path / "run_v7.yaml", as_trained=True).poses.held_fits == (0.25, 0.6, 0.85)
    assert load_config(tmp_path / "run_v7.yaml").poses.held_fits is None
    (tmp_path / "run_v8.yaml").write_text("version: 8\nposes:\n  held_fits: null\n")
    assert load_config(tmp_path / "run_v8.yaml", as_trained=True).poses.held_fits is None


def test_a_v3_checkpoint_reads_as_one_without_pose_corrections():
    from rmavatar.avatar.run import MIGRATIONS

    migrated = MIGRATIONS[3]({"format": "rmavatar-checkpoint", "version": 3, "iteration": 5})
    assert migrated["poses"] is None and migrated["iteration"] == 5


def test_smoothing_removes_jitter_but_keeps_fast_motion():
    """smooth_poses: on a still pose with 3 degrees of frame-to-frame noise the average of +-2 frames is
    much closer to the truth; a joint turning 60 degrees per frame (fast motion) is left as it is; frames
    whose numbers are far apart are not neighbours; the frames' order does not matter; radius 0 is
    the identity."""
    from rmavatar.body import smooth_poses

    gen = torch.Generator().manual_seed(0)
    n = 20
    truth = PoseSequence(torch.full((n, 3), 0.3), torch.full((n, 69), -0.2), torch.zeros(n, 3))
    noisy = apply_pose_corrections(truth, torch.cat((torch.randn(n, 72, generator=gen) * math.radians(3),
                                                     torch.zeros(n, 3)), 1))
    before = pose_error(noisy, truth)["joint_angle_deg"]
    after = pose_error(smooth_poses(noisy, range(n), 2), truth)["joint_angle_deg"]
    assert after < 0.6 * before, (before, after)
    same = smooth_poses(noisy, range(n), 0)
    assert torch.equal(same.body_pose, noisy.body_pose)
    # gaps: frame numbers 10 apart are not within radius 2, so nothing is averaged
    apart = smooth_poses(noisy, range(0, 10 * n, 10), 2)
    assert pose_error(apart, noisy)["joint_angle_deg"] < 1e-3
    # order: shuffled frames give each frame the same result
    perm = torch.randperm(n, generator=gen)
    shuffled = smooth_poses(noisy.select(perm), perm.tolist(), 2)
    assert pose_error(shuffled, smooth_poses(noisy, range(n), 2).select(perm))["joint_angle_deg"] < 1e-3
    # fast motion: the global orientation turns 60 degrees per frame about y, no noise
    angles = torch.arange(n, dtype=torch.float32) * math.radians(60)
    turning = PoseSequence(torch.stack((torch.zeros(n), angles, torch.zeros(n)), 1), torch.zeros(n, 69),
                           torch.zeros(n, 3))
    kept = smooth_poses(turning, range(n), 2)
    assert pose_error(kept, turning)["joint_angle_deg"] < 0.05
    with pytest.raises(ValueError, match="frame_ids"):
        smooth_poses(noisy, range(n - 1), 2)


def test_a_version_8_run_keeps_its_held_fits_prior(tmp_path):
    """Version 9 pulls the held fits' joints toward their neighbours' average at prior 0.1: a run's own
    config of version 8 and its checkpoint read version 8's pull toward the fit's start at 0.01; a
    hand-written version 8 file takes today's; an unknown anchor is refused, naming the setting."""
    from rmavatar.avatar.run import MIGRATIONS, POSE_DEFAULTS_V8, migrate_config

    assert POSE_DEFAULTS_V8 == {"held_fit_prior": 0.01, "held_fit_anchor": "start"}
    today = PoseConfig()
    assert (today.held_fit_prior, today.held_fit_anchor) == (0.1, "neighbours")
    assert (today.fit_config(held=True).prior, today.fit_config(held=False).prior) == (0.1, 0.01)
    v8 = {"poses": {"refine": True}}
    assert migrate_config(v8, 8, as_trained=True)["poses"] == {"refine": True, **POSE_DEFAULTS_V8}
    assert MIGRATIONS[8]({"version": 8, "config": v8})["config"]["poses"]["held_fit_anchor"] == "start"
    (tmp_path / "run_v8.yaml").write_text("version: 8\nposes:\n  refine: true\n")
    old = load_config(tmp_path / "run_v8.yaml", as_trained=True).poses
    assert (old.held_fit_prior, old.held_fit_anchor, old.fit_config(held=True).prior) == (0.01, "start", 0.01)
    assert load_config(tmp_path / "run_v8.yaml").poses.held_fit_anchor == "neighbours"
    with pytest.raises(UserError, match="poses.held_fit_anchor"):
        PoseConfig(held_fit_anchor="mean").validate()
    with pytest.raises(UserError, match="held_fit_prior"):
        PoseConfig(held_fit_prior=-1.0).validate()
