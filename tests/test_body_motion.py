"""Motion files (AIST++/InstantAvatar .npz, AMASS .npz, GART .npy), bad inputs, and `rmavatar body show`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import dance

from rmavatar.body import PoseSequence, load_body_model, load_motion, motion_to_sequence, posed_vertices
from rmavatar.body.base import HAND_POINT_NAMES
from rmavatar.body.hands import hand_axes
from rmavatar.commands import main
from rmavatar.utils import UserError

MOTIONS = Path(__file__).resolve().parents[2] / "shared" / "data" / "motions"
# A fist as a hand pose in the MANO / SMPL-X convention (radians per joint, left hand then right): at the
# T-pose the left hand's fingers point along +x with the palm down (-y), so bending them towards the palm
# turns them about -z; the right hand (fingers along -x) about +z. The thumbs point forward-out along
# (+-1, 0, 1) and bend across the palm about (1, 0, -+1) / sqrt(2).
_BEND = np.array([[0.0, 0.0, -1.0]] * 12 + [[2**-0.5, 0.0, -(2**-0.5)]] * 3)
FIST = np.concatenate([_BEND, _BEND * [1.0, -1.0, -1.0]]).reshape(90)  # mirrored in x for the right hand


def test_aist_npz(tmp_path):
    rng = np.random.default_rng(0)
    poses, trans = rng.normal(size=(5, 72)), rng.normal(size=(5, 3))
    np.savez(tmp_path / "a.npz", poses=poses, trans=trans)
    m = load_motion(tmp_path / "a.npz")
    assert len(m) == 5 and m.fps is None and m.betas is None
    assert m.global_orient.dtype == np.float32
    np.testing.assert_allclose(m.global_orient, poses[:, :3], rtol=1e-6)
    np.testing.assert_allclose(m.body_pose, poses[:, 3:], rtol=1e-6)
    np.testing.assert_allclose(m.transl, trans, rtol=1e-6)


def test_amass_npz(tmp_path):
    rng = np.random.default_rng(1)
    poses, trans = rng.normal(size=(4, 156)), rng.normal(size=(4, 3))
    np.savez(tmp_path / "amass.npz", poses=poses, trans=trans, betas=np.arange(16.0),
             mocap_framerate=np.array(120.0), gender="female")  # fmt: skip
    m = load_motion(tmp_path / "amass.npz", keep_up=True)
    assert m.fps == 120.0 and m.betas.shape == (10,) and m.body_pose.shape == (4, 69)
    np.testing.assert_allclose(m.body_pose[:, :63], poses[:, 3:66], rtol=1e-6)
    assert (m.body_pose[:, 63:] == 0).all()  # SMPL's hand joints stay at rest
    np.testing.assert_allclose(m.global_orient, poses[:, :3], rtol=1e-6)
    # Z-up -> y-up: the whole posed body turns -90 degrees about x, about the world origin
    y_up = load_motion(tmp_path / "amass.npz")
    np.testing.assert_allclose(y_up.body_pose, m.body_pose)
    body = load_body_model("anny")
    with torch.no_grad():
        z = body(None, torch.from_numpy(m.global_orient), torch.from_numpy(m.body_pose), torch.from_numpy(m.transl))
        y = body(None, torch.from_numpy(y_up.global_orient), torch.from_numpy(y_up.body_pose),
                 torch.from_numpy(y_up.transl))  # fmt: skip
    turn = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # -90 degrees about x: z -> y
    assert (y.vertices - z.vertices @ turn.T).abs().max() < 1e-4
    # the fingers are posed relative to their parents, so turning the world leaves them as they are
    np.testing.assert_allclose(m.hand_pose, poses[:, 66:], rtol=1e-6)
    np.testing.assert_array_equal(y_up.hand_pose, m.hand_pose)
    hands_z, hands_y = (body(None, *(torch.from_numpy(a) for a in (n.global_orient, n.body_pose, n.transl)),
                             hand_pose=torch.from_numpy(n.hand_pose)) for n in (m, y_up))
    assert (hands_y.vertices - hands_z.vertices @ turn.T).abs().max() < 1e-4


def write_amass(path, poses, rate_key="mocap_framerate"):
    """An AMASS-style file as AMASS ships it: poses, trans, betas (16), the frame rate, a gender string."""
    np.savez(path, poses=poses, trans=np.zeros((len(poses), 3)), betas=np.zeros(16), gender="neutral",
             **{rate_key: np.array(60.0)})
    return path


@pytest.mark.parametrize("width, hands_at", [(156, 66), (165, 75)], ids=["SMPL-H", "SMPL-X"])
def test_amass_hand_poses(tmp_path, width, hands_at):
    poses = np.random.default_rng(2).normal(size=(3, width))
    m = load_motion(write_amass(tmp_path / "hands.npz", poses, "mocap_frame_rate"), keep_up=True)
    assert m.fps == 60.0 and m.hand_pose.dtype == np.float32 and m.hand_pose.shape == (3, 90)
    np.testing.assert_allclose(m.body_pose[:, :63], poses[:, 3:66], rtol=1e-6)
    assert (m.body_pose[:, 63:] == 0).all()  # SMPL's own hand joints: SMPL-H and SMPL-X have none
    np.testing.assert_allclose(m.hand_pose, poses[:, hands_at:hands_at + 90], rtol=1e-6)  # SMPL-X: no jaw, eyes
    seq = motion_to_sequence(m)
    torch.testing.assert_close(seq.hand_pose, torch.from_numpy(m.hand_pose), atol=0, rtol=0)


def test_motion_without_hands_keeps_the_relaxed_hands(tmp_path):
    poses, trans = dance(n=3, drift=1.0)
    np.savez(tmp_path / "aist.npz", poses=poses, trans=trans)
    m = load_motion(tmp_path / "aist.npz")
    seq = motion_to_sequence(m)
    assert m.hand_pose is None and seq.hand_pose is None
    body = load_body_model("anny")
    with torch.no_grad():
        before = body(None, torch.from_numpy(poses[:, :3]), torch.from_numpy(poses[:, 3:]), torch.from_numpy(trans))
    assert torch.equal(posed_vertices(body, seq), before.vertices)  # bit for bit what it always gave


def test_hand_motion_moves_the_fingers_only(tmp_path):
    body = load_body_model("anny")
    poses = np.zeros((1, 156))
    poses[:, 66:] = 0.5 * FIST  # every finger joint bent 29 degrees towards the palm
    # kept z-up: the zero pose then stands in the rest frame that hand poses and hand_axes are given in
    bent = motion_to_sequence(load_motion(write_amass(tmp_path / "bent.npz", poses), keep_up=True))
    flat = PoseSequence(bent.global_orient, bent.body_pose, bent.transl, torch.zeros(1, 90))
    relaxed = PoseSequence(bent.global_orient, bent.body_pose, bent.transl)  # what a motion without hands gives
    with torch.no_grad():
        out = {name: body(None, s.global_orient, s.body_pose, s.transl, hand_pose=s.hand_pose)
               for name, s in (("bent", bent), ("flat", flat), ("relaxed", relaxed))}
    tips = [k for k, name in enumerate(HAND_POINT_NAMES) if name.endswith("_tip")]
    tip_points = {name: o.hand_points[0].reshape(2, 21, 3)[:, tips] for name, o in out.items()}
    assert float((tip_points["bent"] - tip_points["relaxed"]).norm(dim=-1).min()) > 0.02  # all ten fingertips move
    # towards the palm: MANO's signs give Anny's flexion (a finger bent backwards would move out of the back)
    palm = hand_axes(body).palm  # [2,3], out of each palm
    assert float(((tip_points["bent"] - tip_points["flat"]) * palm[:, None]).sum(-1).min()) > 0.02
    rest = out["relaxed"].vertices[0]
    torso = rest[:, 0].abs() < 0.3  # at rest the hands are far out on the sides
    assert int(torso.sum()) > 1000
    assert float((out["bent"].vertices[0] - rest)[torso].abs().max()) < 1e-6


def test_gart_npy(tmp_path):
    np.save(tmp_path / "g.npy", np.zeros((7, 72), np.float32))
    m = load_motion(tmp_path / "g.npy")
    assert len(m) == 7 and (m.transl == 0).all() and m.fps is None


def test_shared_motions_load():
    for name, n in [("aist_demo.npz", 320), ("walking.npy", 200)]:
        if (MOTIONS / name).is_file():
            assert len(load_motion(MOTIONS / name)) == n


def test_bad_motion_files(tmp_path):
    with pytest.raises(UserError, match="missing.npz does not exist"):
        load_motion(tmp_path / "missing.npz")
    np.save(tmp_path / "short.npy", np.zeros((3, 69)))
    with pytest.raises(UserError, match=r"short.npy: poses must have shape \(N, 72\)"):
        load_motion(tmp_path / "short.npy")
    np.savez(tmp_path / "nopose.npz", trans=np.zeros((3, 3)))
    with pytest.raises(UserError, match="nopose.npz has no 'poses'"):
        load_motion(tmp_path / "nopose.npz")
    bad = np.zeros((3, 72))
    bad[2, 10] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(UserError, match="nan.npy: poses contain NaN/inf .*frame 2"):
        load_motion(tmp_path / "nan.npy")
    np.savez(tmp_path / "trans.npz", poses=np.zeros((3, 72)), trans=np.zeros((2, 3)))
    with pytest.raises(UserError, match=r"trans.npz: trans must have shape \(3, 3\)"):
        load_motion(tmp_path / "trans.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(UserError, match="cannot read motion file .*text.npz"):
        load_motion(tmp_path / "text.npz")


def test_bad_specs_and_poses():
    with pytest.raises(UserError, match="unknown body 'smplx'"):
        load_body_model("smplx")
    with pytest.raises(UserError, match="unknown Anny preset 'giant'"):
        load_body_model("anny:giant")
    with pytest.raises(UserError, match="gender must be one of"):
        load_body_model("anny", gender="x")
    body = load_body_model("anny")
    with pytest.raises(UserError, match=r"body_pose must have shape \[B, 69\]"):
        body(None, torch.zeros(2, 3), torch.zeros(2, 23, 3))
    with pytest.raises(UserError, match="global_orient contains NaN"):
        body(None, torch.full((1, 3), float("nan")), torch.zeros(1, 69))
    with pytest.raises(UserError, match="transl must have shape"):
        body(None, torch.zeros(1, 3), torch.zeros(1, 69), torch.zeros(2, 3))


def test_body_show_cli(tmp_path, capsys):
    from PIL import Image

    np.save(tmp_path / "m.npy", np.zeros((2, 72), np.float32))
    out = tmp_path / "x.png"
    assert main(["body", "show", "--body", "anny", "--motion", str(tmp_path / "m.npy"), "--frame", "1",
                 "--size", "96", "--out", str(out)]) == 0  # fmt: skip
    image = np.asarray(Image.open(out))
    assert image.shape == (96, 192, 3)
    assert (image < 250).any(axis=-1).mean() > 0.05  # the body covers part of the picture
    assert main(["body", "show", "--motion", str(tmp_path / "m.npy"), "--frame", "5", "--out", str(out)]) == 2
    assert "outside" in capsys.readouterr().err
