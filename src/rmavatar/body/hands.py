"""Finger poses in words a person would use: how much each joint bends, how far each finger spreads.

A hand pose (``hand_pose [..., 90]``, :data:`rmavatar.body.base.HAND_JOINT_NAMES`) is 30 axis-angle
rotations. Each finger joint mostly bends about one axis (flexion, towards the palm), and a finger's
first joint also turns in the palm's plane (spread). :func:`hand_axes` reads both axes off a body's flat
hand, and :func:`hand_pose_from_angles` builds a hand pose from angles about them; the synthetic
subject's finger motion and the capture's hand fit use them, so "bend 60 degrees" means the same to both.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from rmavatar.body.base import FINGERS, HAND_JOINT_NAMES, HAND_POINT_NAMES, HAND_POSE_DIM


@dataclass
class HandAxes:
    """``flexion [2,5,3]``: per hand (left, right) and finger (thumb, index, middle, ring, pinky) the unit
    axis a positive turn about which bends the finger towards the palm; ``palm [2,3]``: each palm's
    unit normal, pointing out of the palm (a positive turn about it spreads a finger towards the thumb
    side on the left hand; :func:`hand_pose_from_angles` flips it for the right)."""

    flexion: torch.Tensor
    palm: torch.Tensor


@torch.no_grad()
def hand_axes(body) -> HandAxes:
    """The axes of ``body``'s flat hand (zero hand pose, zero body pose), in the rest frame where hand
    poses are expressed. Needs a body with fingers (``hand_points``)."""
    device = body.v_template.device
    zero = torch.zeros(1, 3, device=device)
    out = body(None, zero, torch.zeros(1, 69, device=device), zero, hand_pose=torch.zeros(1, HAND_POSE_DIM, device=device))
    if out.hand_points is None:
        raise ValueError(f"the body {body.spec} has no fingers")
    points = out.hand_points[0].double().reshape(2, 21, 3)
    at = {name: k for k, name in enumerate(HAND_POINT_NAMES)}
    wrist, index, pinky = points[:, at["wrist"]], points[:, at["index1"]], points[:, at["pinky1"]]
    palm = torch.linalg.cross(index - wrist, pinky - wrist)
    # out of the palm: the palm faces the side the fingers bend to, below the back of the hand at rest
    # (T-pose, palms down), so the normal's y is negative
    palm = palm * -torch.sign(palm[:, 1:2])
    palm = palm / palm.norm(dim=-1, keepdim=True)
    flexion = []
    for f in FINGERS:
        direction = points[:, at[f"{f}2"]] - points[:, at[f"{f}1"]]
        axis = torch.linalg.cross(direction, palm)
        flexion.append(axis / axis.norm(dim=-1, keepdim=True))
    return HandAxes(torch.stack(flexion, 1).float().cpu(), palm.float().cpu())


def hand_pose_from_angles(bend: torch.Tensor, spread: torch.Tensor, axes: HandAxes) -> torch.Tensor:
    """A hand pose ``[..., 90]`` from ``bend [..., 2, 5, 3]`` (radians per hand, finger and joint, positive
    towards the palm) and ``spread [..., 2, 5]`` (radians per finger's first joint, positive away from the
    middle finger for index, ring and pinky: a spread hand is positive everywhere)."""
    flex = axes.flexion.to(bend)  # [2,5,3]
    palm = axes.palm.to(bend)  # [2,3]
    # away from the middle finger: towards the thumb for the index, towards the little finger for ring and
    # pinky, and mirrored between the hands
    side = torch.tensor([[1.0, 1.0, 0.0, -1.0, -1.0], [-1.0, -1.0, 0.0, 1.0, 1.0]]).to(bend)
    rot = bend[..., None] * flex[..., None, :]  # [..., 2, 5, 3 joints, 3]
    rot[..., 0, :] = rot[..., 0, :] + (spread * side)[..., None] * palm[:, None, :]
    order = [FINGERS.index(name[:-1]) * 3 + int(name[-1]) - 1 for name in HAND_JOINT_NAMES]
    return rot.reshape(*rot.shape[:-4], 2, 15, 3)[..., order, :].reshape(*rot.shape[:-4], HAND_POSE_DIM)
