"""The Anny adapter: equal to anny's own skinning, retargeting SMPL poses, SMPL conventions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from rmavatar.body import load_body_model, load_motion
from rmavatar.body.anny import _AIM_CHILD, ANNY_TO_SMPL, PRESETS
from rmavatar.body.base import SMPL_PARENTS, SMPL_REST_JOINTS

MOTIONS = Path(__file__).resolve().parents[2] / "shared" / "data" / "motions"


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny:female")


def test_interface(body):
    V, F = body.v_template.shape[0], body.faces.shape[0]
    assert (V, F) == (13718, 27420)
    assert body.faces.dtype == torch.long and body.binding_faces.dtype == torch.long
    assert body.uv.shape[1] == 2 and body.face_uv_index.shape == (F, 3)
    assert int(body.face_uv_index.max()) < body.uv.shape[0]
    assert body.face_part.shape == (F,)
    bound = set(body.binding_faces.tolist())
    def faces_of(part):
        return torch.nonzero(body.face_part == body.part_names.index(part))[:, 0]

    for part in ("tongue", "mouth_cavity", "eye_cavity.L", "eye_back.R"):
        assert len(faces_of(part)) > 0 and not bound & set(faces_of(part).tolist())
    for part in ("head", "hand.L", "body", "eye_front.L"):
        assert set(faces_of(part).tolist()) <= bound
    assert body.spec == "anny:female" and body.num_betas == 0


@pytest.mark.slow
def test_lbs_equals_anny(body):
    """Our template + LBS reproduces anny's own forward for the same bone rotations (1e-5 m)."""
    anny = pytest.importorskip("anny")
    model = anny.Anny(skinning_method="lbs")
    gen = torch.Generator().manual_seed(0)
    B, J = 2, len(model.bone_labels)
    D = Rotation.from_rotvec(0.4 * torch.randn(B * J, 3, generator=gen).numpy()).as_matrix()
    D = torch.tensor(D).reshape(B, J, 3, 3)
    d0 = torch.tensor([[0.1, -0.2, 0.3], [-0.05, 0.0, 1.0]], dtype=torch.float64)
    H = torch.eye(4, dtype=torch.float64).repeat(B, J, 1, 1)
    H[..., :3, :3] = D
    H[:, 0, :3, 3] = d0
    with torch.no_grad():
        out = model(pose_parameters=H, phenotype_kwargs=PRESETS["female"])
    # anny's 'local-ref' deltas -> our local world-aligned rotations: L_c = A_p^T D_c A_c with
    # A = U R^T (reference orientation times rest orientation transposed).
    R = out["rest_bone_poses"][0, :, :3, :3]
    A = model.reference_bone_orientations @ R.transpose(-1, -2)
    parents = [0] + list(model.bone_parents[1:])
    L = A[parents].transpose(-1, -2) @ D @ A
    L[:, 0] = D[:, 0] @ A[0]
    C = torch.tensor(ANNY_TO_SMPL)
    L = C @ L @ C.T
    h0 = out["rest_bone_heads"][0, 0]
    t = (d0 - h0) @ C.T
    ours, _ = body.forward_bones(L.float(), t.float())
    expected = out["vertices"] @ C.T + body.anny_offset.double()
    err = (ours.double() - expected).norm(dim=-1).max().item()
    assert err < 1e-5, err


def _smpl_skeleton(poses: np.ndarray) -> np.ndarray:
    """Independent FK of the reference SMPL rest skeleton: poses [N,72] -> joints [N,24,3]."""
    N = len(poses)
    rot = Rotation.from_rotvec(poses.reshape(-1, 3)).as_matrix().reshape(N, 24, 3, 3)
    G = [rot[:, 0]]
    X = [np.repeat(SMPL_REST_JOINTS[None, 0], N, 0)]
    for j in range(1, 24):
        p = SMPL_PARENTS[j]
        G.append(G[p] @ rot[:, j])
        X.append(X[p] + np.einsum("nij,j->ni", G[p], SMPL_REST_JOINTS[j] - SMPL_REST_JOINTS[p]))
    return np.stack(X, 1)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


@pytest.mark.parametrize("name", ["aist_demo.npz", "walking.npy", "fencing.npy", "eating.npy"])
def test_retargeted_bones_follow_smpl(body, name):
    """Anny's bones point where SMPL's skeleton points, frame by frame, for real motion."""
    if not (MOTIONS / name).is_file():
        pytest.skip(f"{MOTIONS / name} not available")
    motion = load_motion(MOTIONS / name)
    frames = np.arange(0, len(motion), 7)
    go, bp = motion.global_orient[frames], motion.body_pose[frames]
    with torch.no_grad():
        joints = body(None, torch.from_numpy(go), torch.from_numpy(bp)).joints.numpy()
    ref = _smpl_skeleton(np.concatenate([go, bp], 1).astype(np.float64))
    segments = sorted(_AIM_CHILD.items())
    assert len(segments) == 18
    for j, k in segments:
        err = _angles(joints[:, k] - joints[:, j], ref[:, k] - ref[:, j])
        assert err.max() < 2.0, (name, j, k, err.max())


def test_canonical_is_smpl_tpose(body):
    """Zero SMPL pose: arms straight out along +-x, legs down, toes forward (+z), head up."""
    j = body(None, torch.zeros(1, 3), torch.zeros(1, 69)).joints[0].numpy()
    for a, b, direction in [(16, 20, [1, 0, 0]), (17, 21, [-1, 0, 0]), (1, 7, [0, -1, 0]),
                            (2, 8, [0, -1, 0]), (9, 15, [0, 1, 0])]:  # fmt: skip
        assert _angles(j[b] - j[a], np.array(direction, float)) < 12
    assert j[10, 2] > j[7, 2] + 0.05 and j[11, 2] > j[8, 2] + 0.05
    assert torch.allclose(body.v_template, body(None, torch.zeros(1, 3), torch.zeros(1, 69)).vertices[0])


def test_smpl_translation_semantics(body):
    """vertices(R, t) = R (vertices(0, 0) - J0) + J0 + t, J0 the rest pelvis; joints[0] = J0 + t."""
    gen = torch.Generator().manual_seed(1)
    pose = 0.3 * torch.randn(2, 69, generator=gen)
    orient = torch.tensor([[3.0, 0.2, -0.4], [0.0, 1.5, 0.0]])
    transl = torch.tensor([[0.1, 2.0, -0.8], [0.0, 0.0, 5.0]])
    out = body(None, orient, pose, transl)
    ref = body(None, torch.zeros(2, 3), pose, torch.zeros(2, 3))
    J0 = torch.tensor(SMPL_REST_JOINTS[0], dtype=torch.float32)
    R = torch.tensor(Rotation.from_rotvec(orient.numpy()).as_matrix(), dtype=torch.float32)
    expected = (ref.vertices - J0) @ R.transpose(1, 2) + J0 + transl[:, None]
    assert (out.vertices - expected).abs().max() < 1e-5
    assert torch.allclose(out.joints[:, 0], J0 + transl, atol=1e-6)


def test_differentiable_and_batched(body):
    pose = torch.zeros(3, 69, requires_grad=True)
    transl = torch.zeros(3, 3, requires_grad=True)
    out = body(None, torch.zeros(3, 3), pose, transl)
    assert out.vertices.shape == (3, 13718, 3) and out.vertices.dtype == torch.float32
    out.vertices[:, :100].sum().backward()
    assert torch.isfinite(pose.grad).all() and pose.grad.abs().sum() > 0
    assert torch.allclose(transl.grad, torch.full_like(transl, 100.0))


def test_presets_and_gender():
    assert load_body_model("anny", gender="male").spec == "anny:male"
    assert load_body_model("anny").spec == "anny:neutral"
    child = load_body_model("anny:child").v_template
    adult = load_body_model("anny:neutral").v_template
    assert (child[:, 1].max() - child[:, 1].min()) < (adult[:, 1].max() - adult[:, 1].min()) - 0.15


# ---------------------------------------------------------------------------------------------- fingers
def _flat_and_turned(body, joint: int, rotvec):
    """The body at zero pose with a flat hand, and with hand joint ``joint`` turned by ``rotvec``."""
    z3, z69 = torch.zeros(1, 3), torch.zeros(1, 69)
    flat = torch.zeros(1, 90)
    turned = flat.clone()
    turned[0, 3 * joint:3 * joint + 3] = torch.as_tensor(rotvec)
    with torch.no_grad():
        return (body(None, z3, z69, z3, hand_pose=flat), body(None, z3, z69, z3, hand_pose=turned),
                body.bone_rotations(z3, z69, flat), body.bone_rotations(z3, z69, turned))


def _subtree(labels: list[str], parents: list[int], root: str) -> set[str]:
    """``root`` and every bone below it, from anny's own skeleton."""
    out = {root}
    for name, p in zip(labels[1:], parents[1:]):
        if p >= 0 and labels[p] in out:
            out.add(name)
    return out


@pytest.fixture(scope="module")
def anny_skeleton():
    """Bone names, parents and skinning weights [V,104] as anny's own model has them."""
    anny = pytest.importorskip("anny")
    model = anny.Anny(skinning_method="lbs")
    labels = list(model.bone_labels)
    parents = [-1] + [int(p) for p in model.bone_parents[1:]]
    weights = torch.zeros(model.vertex_bone_indices.shape[0], len(labels), dtype=torch.float64)
    weights.scatter_add_(1, model.vertex_bone_indices.long(), model.vertex_bone_weights.double())
    return labels, parents, weights


@pytest.mark.slow
@pytest.mark.parametrize("joint, bone", [(1, "finger2-2.L"), (3, "finger3-1.L"), (8, "finger5-3.L"),
                                         (9, "finger4-1.L"), (12, "finger1-1.L"), (15 + 1, "finger2-2.R"),
                                         (15 + 13, "finger1-2.R"), (15 + 6, "finger5-1.R")])
def test_hand_joint_turns_its_anny_bones(body, anny_skeleton, joint, bone):
    """MANO joint -> Anny bone (names from anny's own skeleton): turning the joint turns exactly that
    bone and the bones below it, about the joint's head, in world axes; vertices that anny skins only to
    them turn rigidly with them, vertices it skins to none of them stay."""
    from rmavatar.body.anny import hand_bone
    from rmavatar.body.base import HAND_POINT_NAMES, HAND_JOINT_NAMES

    labels, parents, weights = anny_skeleton
    assert hand_bone(joint) == bone and labels == body.bone_names
    rotvec = np.array([0.3, -0.8, 0.5])
    R = torch.tensor(Rotation.from_rotvec(rotvec).as_matrix(), dtype=torch.float32)
    flat, turned, L0, L1 = _flat_and_turned(body, joint, rotvec)
    # world rotations of every Anny bone, composed independently of the retargeting code
    G0, G1 = L0[0].clone(), L1[0].clone()
    for b in range(1, len(labels)):
        G0[b] = G0[parents[b]] @ L0[0, b]
        G1[b] = G1[parents[b]] @ L1[0, b]
    moved = _subtree(labels, parents, bone)
    for b, name in enumerate(labels):
        expected = R @ G0[b] if name in moved else G0[b]
        assert torch.allclose(G1[b], expected, atol=1e-5), name
    # the joint's head, from the hand points: wrist, then 4 points per finger (joints 1-3, tip)
    side, k = divmod(joint, 15)
    name = HAND_JOINT_NAMES[k]
    at = side * 21 + HAND_POINT_NAMES.index(name[:-1] + name[-1])
    h = flat.hand_points[0, at]
    share = weights[:, [labels.index(n) for n in moved]].sum(1)
    rigid = share > 1 - 1e-6
    still = share < 1e-9
    assert rigid.sum() > 20 and still.sum() > 10000
    v0, v1 = flat.vertices[0], turned.vertices[0]
    assert (v1[rigid] - ((v0[rigid] - h) @ R.T + h)).norm(dim=-1).max() < 1e-5
    assert (v1[still] - v0[still]).norm(dim=-1).max() < 1e-6


def test_no_hand_pose_is_the_relaxed_hand(body):
    """hand_pose None = the relaxed hand pose given explicitly (Anny's rest fingers, as before hands)."""
    gen = torch.Generator().manual_seed(3)
    go, bp = torch.randn(2, 3, generator=gen), 0.3 * torch.randn(2, 69, generator=gen)
    none = body(None, go, bp)
    relaxed = body(None, go, bp, hand_pose=body.relaxed_hand_pose.expand(2, -1))
    assert (none.vertices - relaxed.vertices).abs().max() < 1e-5
    assert body.relaxed_hand_pose.abs().max() > 0.1  # the rest fingers are curled a little, not flat


def test_flat_hand_is_straight_and_smpl_hand_joint_still_turns_fingers(body):
    """Zero hand pose: every finger's joints and tip on one line. SMPL's hand joint (22 / 23) turns
    the four fingers but not the thumb, with or without a hand pose."""
    z3, z69 = torch.zeros(1, 3), torch.zeros(1, 69)
    points = body(None, z3, z69, z3, hand_pose=torch.zeros(1, 90)).hand_points[0].reshape(2, 21, 3).numpy()
    for hand in points:
        for f in range(5):
            bones = np.diff(hand[1 + 4 * f:5 + 4 * f], axis=0)
            assert _angles(bones[:-1], bones[1:]).max() < 0.5
    bp = z69.clone()
    bp[0, 3 * 21:3 * 22] = torch.tensor([0.0, 0.0, 0.7])  # joint 22, the left hand
    for hands in (None, torch.zeros(1, 90)):
        a = body(None, z3, z69, z3, hand_pose=hands).hand_points[0, :21]
        b = body(None, z3, bp, z3, hand_pose=hands).hand_points[0, :21]
        moved = (a - b).norm(dim=-1) > 1e-4
        assert not moved[:5].any() and moved[[8, 12, 16, 20]].all()


def test_hand_pose_checked(body):
    from rmavatar.utils import UserError

    with pytest.raises(UserError, match=r"hand_pose must have shape \[1, 90\]"):
        body(None, torch.zeros(1, 3), torch.zeros(1, 69), hand_pose=torch.zeros(1, 45))
    with pytest.raises(UserError, match="hand_pose contains NaN"):
        body(None, torch.zeros(1, 3), torch.zeros(1, 69), hand_pose=torch.full((1, 90), float("nan")))
