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
