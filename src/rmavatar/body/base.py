"""The body-model interface every body (SMPL, Anny) implements, and input checks they share."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from rmavatar.utils import UserError

# SMPL's kinematic tree (parent of each of the 24 joints); it is the same in every SMPL file.
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)

SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
)  # fmt: skip

# A typical SMPL neutral rest skeleton (joint positions in metres, rounded). Only its bone directions
# (which define SMPL's T-pose) and its pelvis / hip centre (where SMPL's body sits) are used.
SMPL_REST_JOINTS = np.array([
    [0.000, -0.223, 0.028], [0.070, -0.314, 0.024], [-0.068, -0.314, 0.021], [-0.003, -0.104, 0.012],
    [0.104, -0.704, 0.018], [-0.106, -0.701, 0.013], [0.005, 0.025, 0.026], [0.088, -1.115, -0.035],
    [-0.088, -1.115, -0.036], [0.005, 0.078, 0.028], [0.120, -1.172, 0.085], [-0.120, -1.172, 0.085],
    [-0.002, 0.289, -0.015], [0.077, 0.194, -0.006], [-0.080, 0.193, -0.010], [0.005, 0.355, 0.038],
    [0.172, 0.226, -0.017], [-0.173, 0.225, -0.019], [0.433, 0.213, -0.040], [-0.429, 0.212, -0.041],
    [0.682, 0.222, -0.043], [-0.688, 0.219, -0.045], [0.767, 0.215, -0.057], [-0.769, 0.216, -0.058],
])  # fmt: skip


# Hand poses, as in MANO, SMPL-H and SMPL-X: per hand 15 joints, each an axis-angle rotation relative to
# its parent joint (world-aligned axes at the rest pose, like SMPL's), in this order; zero is a flat hand
# (fingers straight). ``hand_pose [B,90]`` is the left hand's 45 values, then the right hand's.
HAND_JOINT_NAMES = (
    "index1", "index2", "index3", "middle1", "middle2", "middle3", "pinky1", "pinky2", "pinky3",
    "ring1", "ring2", "ring3", "thumb1", "thumb2", "thumb3",
)  # fmt: skip
FINGERS = ("thumb", "index", "middle", "ring", "pinky")
HAND_POSE_DIM = 90

# The 54-joint tree of a body with fingers: SMPL's 24 joints, then the left hand's 15 (MANO order), then
# the right hand's. A finger's first joint hangs from SMPL's hand joint (22 / 23), the thumb's from the
# wrist (20 / 21): SMPL's hand joint keeps turning the four fingers as it always did, and in SMPL-H /
# SMPL-X data (which have no joints 22 / 23) it is zero, so the fingers hang from the wrist.
HAND_PARENTS = SMPL_PARENTS + tuple(
    (hand if name[-1] == "1" and name != "thumb1" else wrist if name == "thumb1" else 24 + 15 * side + k - 1)
    for side, (wrist, hand) in enumerate(((20, 22), (21, 23)))
    for k, name in enumerate(HAND_JOINT_NAMES)
)

# Each of the 54 joints' SMPL joint (0..23): its own for SMPL's, for a finger joint the one its finger
# hangs from (the wrist for the thumb, SMPL's hand joint for the other four): where a body without the
# finger joints apart counts their skinning weights.
HAND_ANCESTORS = tuple(
    j if j < 24 else (20 if HAND_JOINT_NAMES[(j - 24) % 15].startswith("thumb") else 22) + (j - 24) // 15
    for j in range(len(HAND_PARENTS))
)

# MediaPipe's 21 hand landmarks per hand: the wrist, then per finger (thumb, index, middle, ring, pinky)
# its three joints from the palm out and its tip. ``BodyOutput.hand_points`` follows this order.
HAND_POINT_NAMES = ("wrist",) + tuple(f"{f}{k}" for f in FINGERS for k in ("1", "2", "3", "_tip"))


@dataclass
class BodyOutput:
    """A posed body: ``vertices [B,V,3]``, the 24 SMPL(-equivalent) ``joints [B,24,3]`` (float32) and,
    for bodies with fingers, ``hand_points [B,42,3]``: each hand's 21 points in MediaPipe's order
    (:data:`HAND_POINT_NAMES`), the left hand's then the right's (None for bodies without fingers)."""

    vertices: torch.Tensor
    joints: torch.Tensor
    hand_points: torch.Tensor | None = None


class BodyModel(torch.nn.Module):
    """A posable body mesh driven by SMPL-format parameters.

    Attributes every body has: ``faces`` LongTensor [F,3], ``binding_faces`` LongTensor [Fb] (faces that
    may carry Gaussians), ``v_template`` [V,3] (canonical rest vertices: what ``forward`` gives for zero
    pose and translation with default shape), ``num_betas``, ``spec`` (identifies the body for checkpoint
    compatibility).

    Output convention: SMPL's (y up, facing +z, metres) with SMPL's translation semantics:
    ``vertices = R(global_orient) (v - J0) + J0 + transl`` for the rigid root part, J0 the rest pelvis.
    """

    spec: str
    num_betas: int
    faces: torch.Tensor
    binding_faces: torch.Tensor
    v_template: torch.Tensor

    def forward(
        self,
        betas: torch.Tensor | None,
        global_orient: torch.Tensor,
        body_pose: torch.Tensor,
        transl: torch.Tensor | None = None,
        check_values: bool = True,
        hand_pose: torch.Tensor | None = None,
    ) -> BodyOutput:  # pragma: no cover - implemented by subclasses
        """``hand_pose [B,90]`` (see :data:`HAND_JOINT_NAMES`): None gives the body's relaxed hands
        (what it always did); bodies without fingers ignore it."""
        raise NotImplementedError

    def joint_weights(self, hands: bool = False) -> torch.Tensor:  # pragma: no cover - implemented by subclasses
        """Skinning weights per vertex and SMPL joint ``[V,24]`` (rows sum to 1): how much each of the
        24 joints' world transforms moves each vertex of ``v_template``; a body with fingers counts them
        for their hand, or with ``hands`` gives ``[V,54]``: the 30 finger joints (``HAND_PARENTS``) apart."""
        raise NotImplementedError


def check_pose_inputs(
    betas: torch.Tensor | None,
    global_orient: torch.Tensor,
    body_pose: torch.Tensor,
    transl: torch.Tensor | None,
    num_betas: int,
    dtype: torch.dtype,
    device: torch.device,
    check_values: bool = True,
) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Check shapes and values of SMPL-format parameters; return them as ``dtype`` tensors.

    Raises UserError naming the argument and the problem (wrong shape, NaN/inf). ``check_values=False``
    skips the NaN/inf test, a host synchronisation per argument: for callers that check the result on
    the device themselves (the training step with pose refinement).
    """
    global_orient = _as_tensor(global_orient, "global_orient", dtype, device)
    body_pose = _as_tensor(body_pose, "body_pose", dtype, device)
    if global_orient.ndim != 2 or global_orient.shape[1] != 3:
        raise UserError(f"global_orient must have shape [B, 3] (axis-angle), got {list(global_orient.shape)}")
    B = global_orient.shape[0]
    if body_pose.ndim != 2 or body_pose.shape[1] != 69:
        hint = ""
        if body_pose.ndim == 2 and body_pose.shape[1] == 72:
            hint = " (that is 24 joints: split off the first 3 values as global_orient)"
        raise UserError(
            f"body_pose must have shape [B, 69] (23 joints x 3 axis-angle values), got "
            f"{list(body_pose.shape)}{hint}"
        )
    if body_pose.shape[0] != B:
        raise UserError(f"body_pose has batch {body_pose.shape[0]} but global_orient has batch {B}")
    if transl is None:
        transl = torch.zeros(B, 3, dtype=dtype, device=device)
    transl = _as_tensor(transl, "transl", dtype, device)
    if transl.shape != (B, 3):
        raise UserError(f"transl must have shape [{B}, 3], got {list(transl.shape)}")
    if betas is not None:
        betas = _as_tensor(betas, "betas", dtype, device)
        if betas.ndim == 1:
            betas = betas[None]
        if betas.ndim != 2 or betas.shape[0] not in (1, B) or betas.shape[1] > num_betas:
            raise UserError(f"betas must have shape [{B}, <= {num_betas}], got {list(betas.shape)}")
    for name, value in (("global_orient", global_orient), ("body_pose", body_pose), ("transl", transl),
                        ("betas", betas)):  # fmt: skip
        if check_values and value is not None and not bool(torch.isfinite(value).all()):
            raise UserError(f"{name} contains NaN or infinite values")
    return betas, global_orient, body_pose, transl


def hand_points(points: torch.Tensor, tips: torch.Tensor) -> torch.Tensor:
    """``BodyOutput.hand_points [B,42,3]`` from each hand's wrist and 15 finger joints ``points [B,2,16,3]``
    (the wrist, then per finger of :data:`FINGERS` its joints 1-3) and fingertips ``tips [B,2,5,3]``."""
    fingers = torch.cat([points[:, :, 1:].reshape(-1, 2, 5, 3, 3), tips[:, :, :, None]], 3).reshape(-1, 2, 20, 3)
    return torch.cat([points[:, :, :1], fingers], 2).reshape(-1, 42, 3)


def fingertip_vertex(rest_vertices: np.ndarray, last_weights: np.ndarray, head: np.ndarray,
                     direction: np.ndarray) -> int | None:
    """The fingertip vertex of a rest mesh: of the vertices that mostly follow the finger's last bone
    (``last_weights [V]`` > 0.5), the one reaching furthest along ``direction`` from its ``head``; None
    when no vertex follows it."""
    own = np.nonzero(last_weights > 0.5)[0]
    if len(own) == 0:
        return None
    return int(own[np.argmax((rest_vertices[own] - head) @ direction)])


def check_hand_pose(hand_pose, batch: int, dtype: torch.dtype, device: torch.device,
                    check_values: bool = True) -> torch.Tensor | None:
    """``hand_pose`` as a ``[batch, 90]`` tensor (None stays None); UserError naming what is wrong."""
    if hand_pose is None:
        return None
    hand_pose = _as_tensor(hand_pose, "hand_pose", dtype, device)
    if hand_pose.shape != (batch, HAND_POSE_DIM):
        raise UserError(
            f"hand_pose must have shape [{batch}, {HAND_POSE_DIM}] (left then right hand, 15 joints x 3 "
            f"axis-angle values each, MANO order), got {list(hand_pose.shape)}"
        )
    if check_values and not bool(torch.isfinite(hand_pose).all()):
        raise UserError("hand_pose contains NaN or infinite values")
    return hand_pose


def _as_tensor(value, name: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    try:
        return torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise UserError(f"{name} is not a numeric array: {exc}") from exc
