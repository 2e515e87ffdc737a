"""`rmavatar synth`: determinism, an end-to-end round trip through load_dataset, the tunic's non-rigid
motion, and bad input."""

import hashlib

import numpy as np
import pytest
import torch

from rmavatar.data import load_dataset
from rmavatar.data.synth import SynthConfig, plan, synthesize
from rmavatar.utils import UserError

TINY = dict(size=40, train=3, test=2, novel_pose=2, ss=2)


def _digest(folder, names):
    return {n: hashlib.sha256((folder / n).read_bytes()).hexdigest() for n in names}


def test_same_seed_same_bytes(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    synthesize(a, SynthConfig(seed=3, **TINY), progress=False)
    synthesize(b, SynthConfig(seed=3, **TINY), progress=False)
    names = ["images/00000.png", "images/00004.png", "masks/00006.png", "smpl.npz", "cameras.npz"]
    assert _digest(a, names) == _digest(b, names)


def test_different_seed_differs():
    p0, p1 = plan(SynthConfig(seed=0, **TINY)), plan(SynthConfig(seed=1, **TINY))
    assert not np.allclose(p0[0].body_pose, p1[0].body_pose)


def test_end_to_end_loads_back_with_splits(tmp_path):
    out = tmp_path / "subject"
    cfg = SynthConfig(seed=0, novel_views=2, pose_noise=2.0, **TINY)
    summary = synthesize(out, cfg, progress=False)
    assert (out / "contact_sheet.png").is_file()
    ds = load_dataset(str(out))
    assert ds.num_frames("train") == 3
    assert ds.num_frames("test") == 2
    assert ds.num_frames("novel_pose") == 2
    assert ds.num_frames("novel_view") == 2  # every test pose once, spread over the 2 extra cameras
    assert ds.num_frames("val") == 1
    assert summary["frames"]["train"] == 3
    fr = ds.frame("train", 0)
    assert fr.image.shape == (40, 40, 3) and fr.mask.shape == (40, 40)
    # A person in the middle, white background where the mask is empty, soft edges.
    assert 0.05 < fr.mask.mean() < 0.6
    assert np.all(fr.image[fr.mask == 0] > 0.99)
    assert np.any((fr.mask > 0.05) & (fr.mask < 0.95))
    # The stored poses carry the requested noise; the true ones are kept beside them.
    true = np.load(out / "smpl_true.npz")
    stored = np.load(out / "smpl.npz")
    diff = np.degrees(np.abs(stored["body_pose"] - true["body_pose"]))
    assert 0.5 < diff.std() < 5.0
    # The camera sees the person where the body model puts it: the projected pelvis lies on the mask.
    from rmavatar.body import load_body_model

    body = load_body_model("anny")
    j = body(None, torch.tensor(true["global_orient"][:1]), torch.tensor(true["body_pose"][:1]),
             torch.tensor(true["transl"][:1])).joints[0, 0].numpy()  # fmt: skip
    u, v = fr.camera.project(j[None])[0]
    assert fr.mask[int(v), int(u)] > 0.5


def test_tunic_moves_non_rigidly_with_the_pose():
    from rmavatar.body import load_body_model
    from rmavatar.data.synth.motion import novel_motion, turn_motion
    from rmavatar.data.synth.subject import (
        build_subject,
        garment_state,
        pose_shell,
        vertex_normals,
    )

    body = load_body_model("anny")
    subject = build_subject(body, 0)
    rng = np.random.default_rng(0)
    turn = turn_motion(4, 0.5, rng)
    walk = novel_motion(8, rng)
    # the walking frame with the largest stride
    stride = max(range(8), key=lambda i: abs(garment_state(walk["body_pose"][i]).flex_l))
    offsets = []
    for m, i in ((turn, 0), (walk, stride)):
        go, bp, tr = (torch.tensor(m[k][i : i + 1], dtype=torch.float32) for k in ("global_orient", "body_pose", "transl"))
        v = body(None, go, bp, tr).vertices[0].numpy().astype(np.float64)
        from scipy.spatial.transform import Rotation

        R = Rotation.from_rotvec(m["global_orient"][i]).as_matrix()
        shell = pose_shell(subject.tunic, v, vertex_normals(v, subject.faces), R, garment_state(m["body_pose"][i]))
        base = subject.tunic.weights @ v  # where the tunic would be if it were painted on the LBS body
        offsets.append((shell - base) @ R)  # in the body's root frame, so global rotation cancels
    dist = np.linalg.norm(offsets[0] - offsets[1], axis=1)
    hem = subject.tunic.hem > 0.8
    assert dist[hem].max() > 0.02  # the hem moves by centimetres relative to the body between poses
    assert np.linalg.norm(offsets[1], axis=1).max() < 0.08  # yet stays within a few cm of the body
    assert np.linalg.norm(offsets[0], axis=1).min() > 0.005  # and never sinks into it


def test_bad_input(tmp_path):
    with pytest.raises(UserError, match="--size"):
        synthesize(tmp_path / "x", SynthConfig(size=8), progress=False)
    with pytest.raises(UserError, match="--preset"):
        synthesize(tmp_path / "x", SynthConfig(preset="giant"), progress=False)
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "thesis.tex").write_text("do not delete")
    with pytest.raises(UserError, match="holds files that rmavatar did not write there"):
        synthesize(precious, SynthConfig(**TINY), progress=False)
    assert (precious / "thesis.tex").read_text() == "do not delete"
    assert not (tmp_path / "x").exists()
