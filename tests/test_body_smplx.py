"""SMPL-H and SMPL-X files (.npz, python-2-style .pkl with chumpy stand-ins) against body-models' own
SMPL-H / SMPL-X, the hand conventions (flat-hand zero, None = the file's mean hands) and the checks."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch
from helpers import random_smpl, random_smplx, save_chumpy_pkl, save_npz

from rmavatar.body import load_body_model
from rmavatar.body.base import HAND_JOINT_NAMES, HAND_POINT_NAMES
from rmavatar.utils import UserError

COMPONENTS = {"smplh": 16, "smplx": 400}  # AMASS's SMPL-H has 16 shape components; SMPL-X 1.1 300 + 100
FIRST_FINGER = {"smplh": 22, "smplx": 25}  # where the left hand's 15 joints start in the file


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("smplx")
    models = {}
    for seed, (kind, components) in enumerate(COMPONENTS.items()):
        models[kind] = random_smplx(kind, components, seed=seed)
        save_chumpy_pkl(models[kind], root / f"{kind}.pkl")
        save_npz(models[kind], root / f"{kind}.npz")
    return root, models


def reference(kind, path, betas, go, bp, hand_pose, transl, flat_hand_mean=True):
    """body-models' vertices [B,V,3] and joint positions [B,J,3] for SMPL-format body_pose (its first 21 joints)."""
    from body_models.smplh.torch import SMPLH
    from body_models.smplx.torch import SMPLX

    B = go.shape[0]
    body, hands = bp[:, :63].reshape(B, 21, 3), hand_pose.reshape(B, 30, 3)
    common = dict(pelvis_rotation=go, shape=betas, global_translation=transl)
    with torch.no_grad():
        if kind == "smplh":
            ref = SMPLH(model_path=path, flat_hand_mean=flat_hand_mean)
            args = (body, hands)
        else:
            ref = SMPLX(model_path=path, flat_hand_mean=flat_hand_mean)
            args = (body, torch.zeros(B, 3, 3), hands)
            common["expression"] = torch.zeros(B, 10)
        return ref.forward_vertices(*args, **common), ref.forward_skeleton(*args, **common)[..., :3, 3]


def random_pose(seed, B, num_betas):
    gen = torch.Generator().manual_seed(seed)
    return (torch.randn(B, num_betas, generator=gen), torch.randn(B, 3, generator=gen),
            0.5 * torch.randn(B, 69, generator=gen), 0.5 * torch.randn(B, 90, generator=gen),
            torch.randn(B, 3, generator=gen))  # fmt: skip


@pytest.mark.parametrize("kind", ["smplh", "smplx"])
@pytest.mark.parametrize("suffix", ["pkl", "npz"])
def test_forward_equals_body_models(files, kind, suffix):
    root, models = files
    path = root / f"{kind}.{suffix}"
    body = load_body_model(f"smpl:{path}")
    V = models[kind]["v_template"].shape[0]
    assert body.kind.name == {"smplh": "SMPL-H", "smplx": "SMPL-X"}[kind]
    assert body.num_betas == min(COMPONENTS[kind], 300) and body.spec == f"smpl:{path.resolve()}"
    B = 3
    betas, go, bp, hand_pose, transl = random_pose(len(kind) + len(suffix), B, body.num_betas)
    with torch.no_grad():
        out = body(betas, go, bp, transl, hand_pose=hand_pose)
    ref_vertices, ref_joints = reference(kind, path, betas, go, bp, hand_pose, transl)
    assert out.vertices.shape == (B, V, 3) and out.joints.shape == (B, 24, 3) and out.hand_points.shape == (B, 42, 3)
    err = (out.vertices - ref_vertices).norm(dim=-1).max().item()
    assert err < 1e-5, err
    # joints: the 22 body joints, then each hand's middle finger's first joint
    middle1 = [FIRST_FINGER[kind] + 15 * side + HAND_JOINT_NAMES.index("middle1") for side in (0, 1)]
    torch.testing.assert_close(out.joints, ref_joints[:, list(range(22)) + middle1], atol=1e-5, rtol=0)
    # hand points: wrist and finger joints are the model's joints, the tips vertices of the last finger bone
    points = out.hand_points.reshape(B, 2, 21, 3)
    for side in (0, 1):
        torch.testing.assert_close(points[:, side, 0], out.joints[:, 20 + side], atol=0, rtol=0)
        for k, name in enumerate(HAND_POINT_NAMES[1:], start=1):
            if name.endswith("_tip"):
                tip = int(body.fingertip_vertices[side * 5 + (k - 1) // 4])
                last = FIRST_FINGER[kind] + 15 * side + HAND_JOINT_NAMES.index(name[:-4] + "3")
                assert models[kind]["weights"][tip, last] > 0.5
                torch.testing.assert_close(points[:, side, k], out.vertices[:, tip], atol=0, rtol=0)
            else:
                joint = FIRST_FINGER[kind] + 15 * side + HAND_JOINT_NAMES.index(name)
                torch.testing.assert_close(points[:, side, k], ref_joints[:, joint], atol=1e-5, rtol=0)


@pytest.mark.parametrize("kind", ["smplh", "smplx"])
def test_relaxed_hands_are_the_files_mean(files, kind):
    root, models = files
    path = root / f"{kind}.npz"
    body = load_body_model(f"smpl:{path}")
    mean = np.concatenate([models[kind]["hands_meanl"], models[kind]["hands_meanr"]])
    np.testing.assert_allclose(body.relaxed_hand_pose.numpy(), mean, atol=1e-7)
    B = 2
    betas, go, bp, _, transl = random_pose(7, B, body.num_betas)
    with torch.no_grad():
        relaxed = body(betas, go, bp, transl).vertices
        given = body(betas, go, bp, transl, hand_pose=torch.tensor(mean, dtype=torch.float32).expand(B, -1)).vertices
        canonical = body(None, torch.zeros(1, 3), torch.zeros(1, 69)).vertices[0]
    torch.testing.assert_close(relaxed, given, atol=0, rtol=0)
    # body-models adds the file's mean to its hand pose unless flat_hand_mean: zero there is our None
    ref, _ = reference(kind, path, betas, go, bp, torch.zeros(B, 90), transl, flat_hand_mean=False)
    assert (relaxed - ref).norm(dim=-1).max().item() < 1e-5
    torch.testing.assert_close(body.v_template, canonical, atol=0, rtol=0)


def test_without_hands_mean_relaxed_is_flat(tmp_path):
    path = tmp_path / "SMPLH_MALE.npz"
    save_npz(random_smplx("smplh", 10, seed=5, hands_mean=False), path)
    body = load_body_model(f"smpl:{path}")
    assert not body.relaxed_hand_pose.any()
    z = torch.zeros(1, 3)
    with torch.no_grad():
        flat = body(None, z, torch.zeros(1, 69), hand_pose=torch.zeros(1, 90)).vertices
        torch.testing.assert_close(body(None, z, torch.zeros(1, 69)).vertices, flat)
        torch.testing.assert_close(body.v_template, body.template)


def test_smpl_hand_joints_are_ignored(files):
    root, _ = files
    body = load_body_model(f"smpl:{root / 'smplx.npz'}")
    _, go, bp, hand_pose, _ = random_pose(3, 2, 0)
    moved = bp.clone()
    moved[:, 63:] += 1.0
    with torch.no_grad():
        torch.testing.assert_close(body(None, go, bp, hand_pose=hand_pose).vertices,
                                   body(None, go, moved, hand_pose=hand_pose).vertices, atol=0, rtol=0)  # fmt: skip


@pytest.mark.parametrize("kind", ["smplh", "smplx"])
def test_joint_weights(files, kind):
    root, models = files
    body = load_body_model(f"smpl:{root / f'{kind}.npz'}")
    w = torch.tensor(models[kind]["weights"], dtype=torch.float32)
    first = FIRST_FINGER[kind]
    folded, apart = body.joint_weights(), body.joint_weights(hands=True)
    assert folded.shape == (w.shape[0], 24) and apart.shape == (w.shape[0], 54)
    torch.testing.assert_close(folded.sum(1), torch.ones(w.shape[0]))
    torch.testing.assert_close(apart.sum(1), torch.ones(w.shape[0]))
    torch.testing.assert_close(folded[:, :15], w[:, :15], atol=0, rtol=0)
    torch.testing.assert_close(folded[:, 15], w[:, 15:16].sum(1) + w[:, 22:first].sum(1))  # jaw and eyes: the head
    for side in (0, 1):
        hand = w[:, first + 15 * side : first + 15 * side + 15]
        thumb = [HAND_JOINT_NAMES.index(f"thumb{k}") for k in (1, 2, 3)]
        fingers = [k for k in range(15) if k not in thumb]
        torch.testing.assert_close(folded[:, 20 + side], w[:, 20 + side] + hand[:, thumb].sum(1))
        torch.testing.assert_close(folded[:, 22 + side], hand[:, fingers].sum(1))
        torch.testing.assert_close(apart[:, 24 + 15 * side : 39 + 15 * side], hand, atol=0, rtol=0)
        assert not apart[:, 22 + side].any()  # SMPL's hand joint: nothing in SMPL-H / SMPL-X


def test_shape_components(tmp_path):
    path = tmp_path / "smplx_v1_0.npz"  # SMPL-X 1.0: 10 shape + 10 expression components
    save_npz(random_smplx("smplx", 20, seed=6), path)
    body = load_body_model(f"smpl:{path}")
    assert body.num_betas == 10 and body.shapedirs.shape[2] == 10
    with pytest.raises(UserError, match="betas must have shape"):
        body(torch.zeros(1, 11), torch.zeros(1, 3), torch.zeros(1, 69))


def test_folder_lookup(tmp_path):
    save_npz(random_smplx("smplx", 20, seed=7), tmp_path / "SMPLX_NEUTRAL.npz")
    save_chumpy_pkl(random_smplx("smplh", 10, seed=8), tmp_path / "SMPLH_female.pkl")  # the MANO site's name
    assert load_body_model(f"smpl:{tmp_path}").file.name == "SMPLX_NEUTRAL.npz"
    female = load_body_model(f"smpl:{tmp_path}", gender="female")
    assert female.file.name == "SMPLH_female.pkl" and female.kind.name == "SMPL-H"
    with pytest.raises(UserError, match="no male SMPL model .*SMPLX_MALE"):
        load_body_model(f"smpl:{tmp_path}", gender="male")


def test_bad_files_and_inputs(tmp_path, files):
    root, _ = files
    model = random_smplx("smplh", 10, seed=9)
    model["posedirs"] = model["posedirs"][..., :207]
    save_npz(model, tmp_path / "few_posedirs.npz")
    with pytest.raises(UserError, match=r"few_posedirs.npz is not an SMPL-H model \(52 joints, 459 pose blend "
                                        r"shapes\) .*posedirs"):  # fmt: skip
        load_body_model(f"smpl:{tmp_path / 'few_posedirs.npz'}")
    model = random_smplx("smplx", 20, seed=10)
    model["hands_meanl"] = model["hands_meanl"][:44]
    save_chumpy_pkl(model, tmp_path / "short_mean.pkl")
    with pytest.raises(UserError, match=r"short_mean.pkl is not an SMPL-X model .*hands_meanl \(44,\)"):
        load_body_model(f"smpl:{tmp_path / 'short_mean.pkl'}")
    model = random_smplx("smplx", 20, seed=11)
    model["kintree_table"][0, 25] = 21  # the left index finger on the right wrist
    save_npz(model, tmp_path / "tree.npz")
    with pytest.raises(UserError, match="tree.npz: its kinematic tree is not SMPL-X's"):
        load_body_model(f"smpl:{tmp_path / 'tree.npz'}")
    model = random_smplx("smplh", 10, seed=12)
    model["J_regressor"] = scipy.sparse.csc_matrix(model["J_regressor"].toarray()[:50])
    model["kintree_table"] = model["kintree_table"][:, :50]
    save_npz(model, tmp_path / "fifty.npz")
    with pytest.raises(UserError, match=r"fifty.npz is not an SMPL model file of a known kind .*SMPL-H: 52"):
        load_body_model(f"smpl:{tmp_path / 'fifty.npz'}")
    model = random_smplx("smplh", 10, seed=13)
    model["weights"] = np.full_like(model["weights"], 1.0 / model["weights"].shape[1])
    save_npz(model, tmp_path / "smeared.npz")
    with pytest.raises(UserError, match="smeared.npz is not an SMPL-H model .*last joint of every finger"):
        load_body_model(f"smpl:{tmp_path / 'smeared.npz'}")
    body = load_body_model(f"smpl:{root / 'smplh.npz'}")
    z3 = torch.zeros(1, 3)
    with pytest.raises(UserError, match=r"hand_pose must have shape \[1, 90\]"):
        body(None, z3, torch.zeros(1, 69), hand_pose=torch.zeros(1, 45))
    bad = torch.zeros(1, 90)
    bad[0, 7] = float("nan")
    with pytest.raises(UserError, match="hand_pose contains NaN"):
        body(None, z3, torch.zeros(1, 69), hand_pose=bad)


def test_smpl_has_no_fingers(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.npz"
    model = random_smpl(10, seed=1)
    save_npz(model, path)
    body = load_body_model(f"smpl:{path}")
    assert body.kind.name == "SMPL" and body.relaxed_hand_pose is None
    out = body(None, torch.zeros(1, 3), torch.zeros(1, 69), hand_pose=torch.ones(1, 90))
    assert out.hand_points is None
    apart = body.joint_weights(hands=True)
    torch.testing.assert_close(apart[:, :24], body.weights, atol=0, rtol=0)
    assert apart.shape == (body.weights.shape[0], 54) and not apart[:, 24:].any()
