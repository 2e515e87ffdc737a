"""Finger poses through the data and training layers: hand axes and angles, the native format's
hand_pose / hand_found, the synthetic subject's finger motion, training with and without hand poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rmavatar.body import PoseSequence, load_body_model
from rmavatar.body.base import HAND_POINT_NAMES
from rmavatar.body.hands import hand_axes, hand_pose_from_angles
from rmavatar.utils import UserError


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny:neutral")


def _points(body, hand_pose):
    z3, z69 = torch.zeros(1, 3), torch.zeros(1, 69)
    with torch.no_grad():
        return body(None, z3, z69, z3, hand_pose=hand_pose).hand_points[0].reshape(2, 21, 3)


def test_bending_moves_fingertips_towards_the_palm_and_spreading_apart(body):
    """A positive bend brings every fingertip to the palm side of the flat hand (along the palm normal)
    and nearer the wrist; a positive spread moves the index and the little finger apart."""
    axes = hand_axes(body)
    flat = _points(body, torch.zeros(1, 90))
    bend = torch.full((1, 2, 5, 3), np.deg2rad(40.0))
    bent = _points(body, hand_pose_from_angles(bend, torch.zeros(1, 2, 5), axes))
    tips = [HAND_POINT_NAMES.index(f"{f}_tip") for f in ("thumb", "index", "middle", "ring", "pinky")]
    for hand in range(2):
        wrist = flat[hand, 0]
        towards_palm = ((bent[hand, tips] - flat[hand, tips]) @ axes.palm[hand])
        assert (towards_palm > 0.01).all(), towards_palm
        assert ((bent[hand, tips] - wrist).norm(dim=-1) < (flat[hand, tips] - wrist).norm(dim=-1)).all()
    spread = _points(body, hand_pose_from_angles(torch.zeros(1, 2, 5, 3), torch.full((1, 2, 5), 0.3), axes))
    index, pinky = HAND_POINT_NAMES.index("index_tip"), HAND_POINT_NAMES.index("pinky_tip")
    for hand in range(2):
        before = (flat[hand, index] - flat[hand, pinky]).norm()
        assert (spread[hand, index] - spread[hand, pinky]).norm() > before + 0.02


def test_native_round_trip_with_hand_poses(tmp_path):
    from rmavatar.data import load_dataset
    from rmavatar.data.native import NativeMeta, write_native

    n = 3
    rng = np.random.default_rng(0)
    params = {"betas": np.zeros(10), "global_orient": np.zeros((n, 3)), "body_pose": np.zeros((n, 69)),
              "transl": np.zeros((n, 3)), "hand_pose": rng.normal(size=(n, 90)).astype(np.float32),
              "hand_found": np.array([[1, 0], [1, 1], [0, 0]], bool)}  # fmt: skip
    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]])
    images = [np.full((16, 16, 3), 0.5, np.float32)] * n
    masks = [np.ones((16, 16), np.float32)] * n
    meta = NativeMeta(name="hands", splits={"train": [0, 1], "test": [2]})
    write_native(tmp_path / "d", meta, {"K": K, "viewmat": np.eye(4)}, params, images, masks, progress=False)
    ds = load_dataset(str(tmp_path / "d"))
    p = ds.params("train")
    np.testing.assert_array_equal(p["hand_pose"], params["hand_pose"][:2])
    np.testing.assert_array_equal(p["hand_found"], params["hand_found"][:2])
    assert PoseSequence.from_params(p).hand_pose.shape == (2, 90)
    np.testing.assert_array_equal(ds.frame("test", 0).hand_pose, params["hand_pose"][2])
    bad = dict(params, hand_pose=np.zeros((n, 45)))
    with pytest.raises(UserError, match=r"'hand_pose' must be \[N,90\]"):
        write_native(tmp_path / "e", meta, {"K": K, "viewmat": np.eye(4)}, bad, images, masks, progress=False)
    bad = {k: v for k, v in params.items() if k != "hand_pose"}
    with pytest.raises(UserError, match="'hand_found' is given without 'hand_pose'"):
        write_native(tmp_path / "e", meta, {"K": K, "viewmat": np.eye(4)}, bad, images, masks, progress=False)


@pytest.fixture(scope="module")
def hand_data(tmp_path_factory):
    from rmavatar.data.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("hands") / "data"
    synthesize(root, SynthConfig(size=64, train=6, test=2, novel_pose=0, ss=1, hand_motion=True), progress=False)
    return root


def test_synthetic_finger_motion_is_stored_and_drawn(hand_data, body):
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import SynthConfig, plan, true_poses

    ds = load_dataset(str(hand_data))
    hands = ds.params("train")["hand_pose"]
    assert hands.shape == (6, 90) and np.abs(hands).max() > np.deg2rad(30)
    assert np.abs(np.diff(hands, axis=0)).max() > 0.1  # the fingers move from frame to frame
    np.testing.assert_allclose(true_poses(ds, "train").hand_pose.numpy(), hands)
    # the body's motion is the same with and without finger motion
    cfg = SynthConfig(size=64, train=6, test=2, novel_pose=0, ss=1)
    a = plan(cfg)
    b = plan(SynthConfig(**{**cfg.__dict__, "hand_motion": True}), hand_axes=hand_axes(body))
    assert all(np.array_equal(x.body_pose, y.body_pose) and x.hand_pose is None for x, y in zip(a, b))


def test_training_poses_the_fingers_unless_told_not_to(hand_data, tmp_path):
    from rmavatar.train import TrainConfig
    from rmavatar.train.trainer import Trainer

    held = {}
    for use in (True, False):
        cfg = TrainConfig()
        cfg.data.path, cfg.data.size, cfg.data.hand_pose = str(hand_data), 32, use
        cfg.optim.iters, cfg.density.enabled, cfg.log.tensorboard, cfg.threads = 1, False, False, 1
        trainer = Trainer(cfg, tmp_path / f"run{use}", progress=False)
        trainer.setup()
        held[use] = trainer.frames.vertices.clone()
    moved = (held[True] - held[False]).norm(dim=-1).amax(0)  # [V]: how far each vertex moves at most
    body = trainer.body
    hand_parts = [body.part_names.index(name) for name in ("hand.L", "hand.R")]
    on_hands = torch.zeros(len(moved), dtype=torch.bool)
    on_hands[body.faces[torch.isin(body.face_part, torch.tensor(hand_parts))].reshape(-1)] = True
    assert moved.max() > 0.03 and moved[~on_hands].max() < 1e-5  # the fingers, nothing else


def test_local_rectifier_of_a_hand_face_sees_its_finger_joints(body):
    """model.hand_pose: the pose input is body_pose then hand_pose (159); a finger pose changes the
    offsets of the Gaussians on the hands only, and only theirs."""
    from rmavatar.avatar import AvatarConfig

    avatar = AvatarConfig(sh_degree=0, hand_pose=True).build(body)
    assert avatar.pose_dim == 159 and avatar.pose_masks.shape[1] == 159
    with torch.no_grad():  # an MLP whose output depends on its input
        for p in avatar.rectifier.parameters():
            p.normal_(0, 0.3, generator=torch.Generator().manual_seed(1))
    v = body.v_template
    rest = avatar.pose_input(torch.zeros(69))
    assert torch.equal(rest[69:], body.relaxed_hand_pose)
    fist = avatar.pose_input(torch.zeros(69), torch.full((90,), 0.5))
    a = avatar.rectify(v, rest)[0]
    b = avatar.rectify(v, fist)[0]
    changed = (a - b).norm(dim=-1) > 1e-6
    hand_parts = torch.tensor([body.part_names.index(n) for n in ("hand.L", "hand.R")])
    on_hand = torch.isin(body.face_part[avatar.face_ids], hand_parts)
    assert changed[on_hand].float().mean() > 0.9
    near_wrist = torch.isin(body.faces[avatar.face_ids], torch.nonzero(body.joint_weights(hands=True)[:, 24:].sum(1) > 0.01)[:, 0]).any(1)
    assert not changed[~near_wrist].any()  # faces no finger joint skins ignore the fingers
    plain = AvatarConfig(sh_degree=0).build(body)
    assert plain.pose_dim == 69 and plain.pose_input(torch.zeros(69), torch.ones(90)).shape == (69,)


def test_training_with_a_rectifier_that_sees_the_hands_resumes_and_renders(hand_data, tmp_path):
    from rmavatar.avatar import load_trained
    from rmavatar.evaluate import evaluate_run
    from rmavatar.train import TrainConfig, train

    cfg = TrainConfig()
    cfg.data.path, cfg.data.size = str(hand_data), 32
    cfg.optim.iters, cfg.density.enabled, cfg.log.tensorboard, cfg.threads = 2, False, False, 1
    cfg.model.sh_degree, cfg.model.hand_pose = 0, True
    train(cfg, tmp_path / "run", progress=False)
    trained = load_trained(tmp_path / "run")
    assert trained.avatar.pose_dim == 159
    ds_hands = torch.full((1, 90), 0.4)
    seq = PoseSequence(torch.zeros(1, 3), torch.zeros(1, 69), torch.zeros(1, 3), ds_hands)
    assert torch.isfinite(trained.pose(seq, 0).means).all()
    result = evaluate_run(tmp_path / "run", split="test", progress=False)
    assert np.isfinite(result["mean"]["psnr"])
