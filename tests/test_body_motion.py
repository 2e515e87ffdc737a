"""Motion files (AIST++/InstantAvatar .npz, AMASS .npz, GART .npy), bad inputs, and `rmavatar body show`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from rmavatar.body import load_body_model, load_motion
from rmavatar.commands import main
from rmavatar.utils import UserError

MOTIONS = Path(__file__).resolve().parents[2] / "shared" / "data" / "motions"


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
