"""Turning a motion file into poses an avatar can show in front of a camera.

Motion files come in whatever world their capture used: AIST++ is y-up, AMASS z-up, trackers' poses
live in the camera frame (y down). :func:`recenter_motion` rotates the whole motion so the body's up
axis is +y and its first frame faces +z (towards a front camera), and removes the root's horizontal
travel so the person dances in place and stays in view, keeping the vertical motion (jumps, squats).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import roma
import torch

from rmavatar.utils import UserError


@dataclass
class PoseSequence:
    """SMPL-convention poses: global_orient [N,3], body_pose [N,69], transl [N,3] (float32 tensors)."""

    global_orient: torch.Tensor
    body_pose: torch.Tensor
    transl: torch.Tensor

    def __len__(self) -> int:
        return int(self.global_orient.shape[0])

    def select(self, index) -> "PoseSequence":
        return PoseSequence(self.global_orient[index], self.body_pose[index], self.transl[index])

    def to(self, device) -> "PoseSequence":
        return PoseSequence(self.global_orient.to(device), self.body_pose.to(device), self.transl.to(device))


def motion_to_sequence(motion, source: str = "motion") -> PoseSequence:
    """Check a loaded ``Motion``'s arrays and return them as a :class:`PoseSequence`.

    ``source`` names the file in error messages.
    """
    arrays = {}
    for name, width in (("global_orient", 3), ("body_pose", 69), ("transl", 3)):
        a = getattr(motion, name, None)
        if a is None:
            raise UserError(f"{source}: motion has no {name}")
        a = np.asarray(a)
        if a.ndim != 2 or a.shape[1] != width:
            raise UserError(f"{source}: {name} must have shape (frames, {width}), got {a.shape}")
        arrays[name] = a
    counts = {a.shape[0] for a in arrays.values()}
    if len(counts) != 1:
        raise UserError(f"{source}: global_orient, body_pose and transl have different frame counts "
                        f"{[a.shape[0] for a in arrays.values()]}")
    if counts.pop() == 0:
        raise UserError(f"{source}: motion has no frames")
    for name, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise UserError(f"{source}: {name} contains NaN or infinite values")
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32))  # noqa: E731
    return PoseSequence(t(arrays["global_orient"]), t(arrays["body_pose"]), t(arrays["transl"]))


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
    """Poses of ``seq`` made upright, facing +z, with the root kept above the origin.

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
    return PoseSequence(orient.float(), seq.body_pose.clone(), transl.float())


def rest_pose(kind: str = "tpose") -> tuple[torch.Tensor, torch.Tensor]:
    """Canonical poses (global_orient [3], body_pose [69]): 'tpose' (all zero) or 'apose'
    (arms lowered 45 degrees at the shoulders, as many avatar methods train in)."""
    go = torch.zeros(3)
    pose = torch.zeros(69)
    if kind == "apose":
        # body_pose holds joints 1..23; SMPL joints 16/17 are the left/right shoulders.
        # The body's left arm points along +x, so lowering it is a negative turn about z.
        pose[(16 - 1) * 3 + 2] = -np.pi / 4
        pose[(17 - 1) * 3 + 2] = np.pi / 4
    elif kind != "tpose":
        raise UserError(f"unknown rest pose {kind!r} (choose tpose or apose)")
    return go, pose
