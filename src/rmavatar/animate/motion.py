"""Turning a motion file into poses an avatar can show in front of a camera.

Motion files come in whatever world their capture used: AIST++ is y-up, AMASS z-up, trackers' poses
live in the camera frame (y down). :func:`recenter_motion` rotates the whole motion so the body's up
axis is +y and its first frame faces +z (towards a front camera), and removes the root's horizontal
travel so the person dances in place and stays in view, keeping the vertical motion (jumps, squats).
"""

from __future__ import annotations

import roma
import torch

from rmavatar.body.poses import PoseSequence
from rmavatar.utils import UserError


def parse_frame_range(text: str | None, num_frames: int, step: int = 1) -> list[int]:
    """Frame indices from ``A:B`` (python slice rules: B exclusive, negatives count from the end,
    either side may be empty), taking every ``step``-th frame."""
    if text is None:
        return list(range(0, num_frames, step))
    parts = text.split(":")
    if len(parts) != 2:
        raise UserError(f"--frames must look like A:B (e.g. 0:120 or 30:), got {text!r}")
    try:
        a, b = (int(p) if p.strip() else None for p in parts)
    except ValueError:
        raise UserError(f"--frames must look like A:B with integers, got {text!r}") from None
    idx = list(range(num_frames))[slice(a, b, step)]
    if not idx:
        raise UserError(f"--frames {text} selects no frames of a {num_frames}-frame motion")
    return idx


def upright_rotation(global_orient: torch.Tensor) -> torch.Tensor:
    """Rotation Q [3,3] taking the motion's world to ours: body up -> +y, first frame facing -> +z.

    The up axis is the world axis (+-x, y or z) closest to the body's mean up direction (its local
    +y axis rotated by global_orient [N,3]), since capture worlds are axis-aligned.
    """
    R = roma.rotvec_to_rotmat(global_orient.double())  # [N,3,3]
    mean_up = R[:, :, 1].mean(0)
    axis = int(mean_up.abs().argmax())
    up = torch.zeros(3, dtype=torch.float64)
    up[axis] = 1.0 if mean_up[axis] >= 0 else -1.0
    facing = None
    for i in range(R.shape[0]):  # the first frame not lying along the up axis
        f = R[i, :, 2] - (R[i, :, 2] @ up) * up
        if f.norm() > 1e-3:
            facing = f / f.norm()
            break
    if facing is None:
        facing = torch.roll(up, 1)
    right = torch.linalg.cross(up, facing)
    return torch.stack([right, up, facing])


def recenter_motion(seq: PoseSequence, root_rest: torch.Tensor) -> PoseSequence:
    """Poses of ``seq`` made upright, facing +z, with the root kept above the origin (body and finger
    poses as they are).

    ``root_rest`` [3] is the body's root joint in the rest pose (SMPL's transl moves the root from
    there; global_orient rotates about it). The root's horizontal travel is removed frame by frame;
    its height keeps its variation about the clip's mean.
    """
    Q = upright_rotation(seq.global_orient)
    R = roma.rotvec_to_rotmat(seq.global_orient.double())
    orient = roma.rotmat_to_rotvec(Q @ R)
    j0 = root_rest.double().reshape(3)
    root = (seq.transl.double() + j0) @ Q.T  # the root in our world, frame by frame
    new_root = torch.zeros_like(root)
    new_root[:, 1] = root[:, 1] - root[:, 1].mean()
    transl = new_root - j0
    # the joint rotations, fingers included, are relative to their parents: only the root turns
    hands = None if seq.hand_pose is None else seq.hand_pose.clone()
    return PoseSequence(orient.float(), seq.body_pose.clone(), transl.float(), hands)
