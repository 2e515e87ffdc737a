"""Corrections to SMPL-format poses, and how far apart two sets of poses are.

A correction of one frame is a vector [75]: 24 axis-angle rotations (the global orientation, then the
23 body joints) and a translation in metres. It acts as a rotation composed on the left of each joint's
own, ``R' = exp(delta_j) R_j``, and an added translation, ``t' = t + delta_t``.

Why a composed rotation rather than adding ``delta_j`` to the axis-angle: a step of size ``|delta|``
then turns the joint by exactly ``|delta|`` radians whatever its current rotation, so one learning rate
means the same thing for every joint and frame. Added axis-angle is distorted by the exponential map's
Jacobian, badly so near pi (a global orientation facing away from the camera, common in turning
sequences), where a small step in the vector can turn the body by a lot or by almost nothing. Composing
on the left expresses the correction in the same (parent, world-aligned) axes as the pose itself; the
angle error below is then exactly the correction's length.
"""

from __future__ import annotations

import math

import roma
import torch

from rmavatar.body.poses import PoseSequence

NUM_JOINTS = 24  # the global orientation and SMPL's 23 body joints
CORRECTION_DIM = NUM_JOINTS * 3 + 3  # rotations (rad), then the translation (m)


def apply_pose_corrections(poses: PoseSequence, delta: torch.Tensor) -> PoseSequence:
    """The corrected poses: ``delta`` [n,75] (see the module docstring) applied to ``poses`` (n frames).

    Differentiable in ``delta`` (and in the poses); a zero ``delta`` gives the poses back up to rounding.
    """
    n = len(poses)
    if delta.shape != (n, CORRECTION_DIM):
        raise ValueError(f"delta must be [{n},{CORRECTION_DIM}], got {tuple(delta.shape)}")
    rot = poses.joint_rotvecs().to(delta.dtype)
    fixed = roma.rotvec_composition([delta[:, : NUM_JOINTS * 3].reshape(n, NUM_JOINTS, 3), rot])
    return PoseSequence(fixed[:, 0], fixed[:, 1:].reshape(n, 69), poses.transl.to(delta.dtype) + delta[:, -3:],
                        poses.hand_pose)


def pose_corrections(base: PoseSequence, target: PoseSequence) -> torch.Tensor:
    """The corrections [n,75] that take ``base`` to ``target``: the inverse of
    :func:`apply_pose_corrections`, ``apply_pose_corrections(base, pose_corrections(base, target))``
    equals ``target`` up to rounding. Each rotation is ``log(R_target R_base^T)``."""
    n = len(base)
    if len(target) != n:
        raise ValueError(f"pose sets of different lengths: {n} and {len(target)}")
    rb = base.joint_rotvecs()
    rt = target.joint_rotvecs().to(rb)
    delta = roma.rotvec_composition([rt, roma.rotvec_inverse(rb)])
    return torch.cat((delta.reshape(n, NUM_JOINTS * 3), target.transl.to(rb) - base.transl), 1)


def joint_angle_errors(a: PoseSequence, b: PoseSequence) -> torch.Tensor:
    """Geodesic angle in degrees between the matching joint rotations of ``a`` and ``b``: [n,24]
    (column 0 the global orientation), float64 on the CPU.

    The angle of ``R_a^T R_b`` as atan2(sin, cos), which stays accurate for small angles (acos of the
    trace loses about 0.03 degrees to float32 rounding near zero).
    """
    if len(a) != len(b):
        raise ValueError(f"pose sets of different lengths: {len(a)} and {len(b)}")

    def mats(p: PoseSequence) -> torch.Tensor:
        return roma.rotvec_to_rotmat(p.joint_rotvecs().detach().cpu().double())

    R = mats(a).transpose(-1, -2) @ mats(b)
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    skew = torch.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1)
    sin = torch.linalg.vector_norm(skew, dim=-1) / 2.0
    return torch.atan2(sin, cos) * (180.0 / math.pi)


def smooth_poses(poses: PoseSequence, frame_ids, radius: int, sigma_deg: float = 15.0) -> PoseSequence:
    """Each frame's pose averaged with the frames of its video within ``radius`` frames of it, per joint
    and weighted by how close that neighbour's rotation of the joint is: weight exp(-a^2 / (2 sigma^2))
    for a neighbour at angle a. Rotations are averaged as their weighted chordal mean (the mean of the
    matrices projected back onto the nearest rotation), translations with the global orientation's
    weights. ``frame_ids`` [n]: each frame's number in its video (a neighbour is a frame whose number
    differs by at most ``radius``; gaps are allowed).

    Why: a tracker's error is largely frame-to-frame jitter of a few degrees, and where a joint moves
    slowly next to the frame rate the average of a few neighbours is closer to the truth than any one of
    them (`rmavatar synth --pose-noise 3`, radius 2: 4.77 -> 2.19 degrees over the 24 joints of the
    training frames; 9.54 -> 4.87 at --pose-noise 6). Where a
    joint turns by much more than ``sigma_deg`` between neighbouring frames (fast motion, or a video
    subsampled coarsely) its neighbours get almost no weight, so real motion is not averaged away.
    radius 0 gives the poses back.
    """
    n = len(poses)
    if radius < 0 or sigma_deg <= 0:
        raise ValueError(f"radius must be >= 0 and sigma_deg > 0, got {radius} and {sigma_deg}")
    ids = torch.as_tensor([int(i) for i in frame_ids], dtype=torch.long)
    if ids.shape != (n,):
        raise ValueError(f"frame_ids must have one number per frame ({n}), got {tuple(ids.shape)}")
    if radius == 0 or n < 2:
        return poses
    order = torch.argsort(ids)
    ids = ids[order]
    R = roma.rotvec_to_rotmat(poses.joint_rotvecs().detach().cpu().double()[order])  # [n,24,3,3]
    transl = poses.transl.detach().cpu().double()[order]
    total = torch.zeros_like(R)
    weight_sum = torch.zeros(n, NUM_JOINTS, dtype=torch.float64)
    t_total = torch.zeros_like(transl)
    for offset in range(-radius, radius + 1):  # frames with distinct numbers: neighbours lie within radius places
        shifted = torch.arange(n) + offset
        k = shifted.clamp(0, n - 1)
        near = ((ids[k] - ids).abs() <= radius) & (shifted >= 0) & (shifted < n)
        cos = ((R.transpose(-1, -2) @ R[k]).diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
        angle = torch.arccos(cos.clamp(-1.0, 1.0))  # [n,24]
        w = torch.exp(-0.5 * (angle / math.radians(sigma_deg)) ** 2) * near[:, None]
        total += w[..., None, None] * R[k]
        weight_sum += w
        t_total += w[:, :1] * transl[k]
    mean = roma.special_procrustes(total / weight_sum[..., None, None])
    rotvec = roma.rotmat_to_rotvec(mean).reshape(n, NUM_JOINTS * 3)
    back = torch.argsort(order)
    rotvec, transl = rotvec[back].float(), (t_total / weight_sum[:, :1])[back].float()
    return PoseSequence(rotvec[:, :3], rotvec[:, 3:], transl, poses.hand_pose)


def pose_error(a: PoseSequence, b: PoseSequence) -> dict:
    """How far poses ``a`` are from ``b``: {"joint_angle_deg": mean per-joint geodesic angle over the 24
    joints and all frames, "per_joint_deg": [24] its mean per joint, "transl_mm": mean distance of the
    translations in millimetres, "frames": n}."""
    angles = joint_angle_errors(a, b)
    dist = torch.linalg.vector_norm(a.transl.detach().cpu().double() - b.transl.detach().cpu().double(), dim=-1)
    return {
        "frames": len(a),
        "joint_angle_deg": float(angles.mean()),
        "per_joint_deg": [round(float(v), 4) for v in angles.mean(0)],
        "transl_mm": float(dist.mean() * 1000.0),
    }


BETA1, BETA2, EPS = 0.9, 0.999, 1e-12


def _per_joint(x: torch.Tensor) -> torch.Tensor:
    """[k,75] -> [k,25]: sums over each joint's 3 rotation values and over the translation's 3."""
    return torch.cat((x[:, : NUM_JOINTS * 3].unflatten(-1, (NUM_JOINTS, 3)).sum(-1), x[:, -3:].sum(-1, keepdim=True)), 1)


@torch.no_grad()
def correction_adam_step(delta: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
                         steps: torch.Tensor, rows: slice, lr: torch.Tensor) -> None:
    """One Adam step, in place, on the corrections ``delta[rows]`` [k,75] with their gradient ``grad`` [k,75].

    Adam with a second moment per frame or per joint instead of one per coordinate: ``exp_avg_sq`` is
    either [n], the running mean of the squared norm of the frame's whole gradient, or [n,25], of each
    joint's rotation gradient (24) and of the translation's (1). ``exp_avg`` [n,75] and the step counts
    ``steps`` [n] are per frame, so a frame's state changes only on the steps that update it. A step
    moves the frame's correction (or each joint's) along its momentum-averaged gradient by at most ``lr``
    [75] (radians for the rotations, metres for the translation) when the gradient points one way,
    keeping the gradient's proportions within the group: per-coordinate Adam moves every coordinate by
    about ``lr`` whatever its gradient's size, so poorly constrained ones (a hand's roll) drift as fast
    as the observed ones are corrected.

    Per frame suits training, where a frame is visited rarely and every joint's drift counts; per joint
    suits test-time fitting, which has many steps on one frame and is scored on the image: a per-frame
    step limits the whole pose to ``lr``, so the joints that are far off are corrected one after another
    (measured, 50 fitting steps: 24.5 dB per frame against 30.8 dB per joint). No host synchronisation.
    """
    steps[rows] += 1
    t = steps[rows].to(grad.dtype)
    per_joint = exp_avg_sq.dim() == 2
    sq = _per_joint(grad.square()) if per_joint else grad.square().sum(-1)
    exp_avg[rows] = BETA1 * exp_avg[rows] + (1 - BETA1) * grad
    exp_avg_sq[rows] = BETA2 * exp_avg_sq[rows] + (1 - BETA2) * sq
    m_hat = exp_avg[rows] / (1 - BETA1**t)[:, None]
    bias = 1 - BETA2**t
    denom = (exp_avg_sq[rows] / (bias[:, None] if per_joint else bias)).sqrt() + EPS
    if per_joint:
        denom = torch.cat((denom[:, :NUM_JOINTS].repeat_interleave(3, 1), denom[:, NUM_JOINTS:].expand(-1, 3)), 1)
    else:
        denom = denom[:, None]
    delta[rows] -= lr * m_hat / denom
