"""Procedural motions in SMPL format (y-up world, axis-angle) and the static camera.

- :func:`turn_motion`: PeopleSnapshot-like: the person turns around on the spot in an A-pose, with small
  natural variation (arms drift, torso twists and sways, weight shifts from leg to leg as they step
  round), at a constant turning speed.
- :func:`novel_motion`: a different motion for the ``novel_pose`` split: walking on the spot while
  slowly turning, then raising the arms sideways and forwards.
- :func:`finger_motion`: hands that open, close into a fist, point with the index and spread, in turn.
- :func:`look_at`: an OpenCV world->camera matrix.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# Index of SMPL joint j's 3 values in the 69-vector is 3 * (j - 1).
_J = {
    "hip_l": 1, "hip_r": 2, "spine1": 3, "knee_l": 4, "knee_r": 5, "spine2": 6, "ankle_l": 7,
    "ankle_r": 8, "spine3": 9, "neck": 12, "collar_l": 13, "collar_r": 14, "head": 15,
    "shoulder_l": 16, "shoulder_r": 17, "elbow_l": 18, "elbow_r": 19, "wrist_l": 20, "wrist_r": 21,
}  # fmt: skip

A_POSE_DEG = 62.0  # arms lowered from SMPL's T-pose by this much


def _set(pose: np.ndarray, joint: str, x=0.0, y=0.0, z=0.0) -> None:
    i = 3 * (_J[joint] - 1)
    pose[:, i] += x
    pose[:, i + 1] += y
    pose[:, i + 2] += z


def _wave(rng: np.random.Generator, t: np.ndarray, amp: float, periods=(0.6, 1.6)) -> np.ndarray:
    """A slow random sinusoid over ``t`` in 0..1 (sum of two with random periods and phases)."""
    out = np.zeros_like(t)
    for _ in range(2):
        cycles = rng.uniform(*periods) * 2.0
        out += np.sin(2 * np.pi * cycles * t + rng.uniform(0, 2 * np.pi))
    return amp * out / 2.0


def yaw_rotvec(yaw: np.ndarray) -> np.ndarray:
    """Axis-angle [N,3] of rotations about the world's y axis, the angle wrapped into [-pi, pi)."""
    yaw = np.mod(yaw + np.pi, 2 * np.pi) - np.pi
    return np.stack([np.zeros_like(yaw), yaw, np.zeros_like(yaw)], 1)


def turn_motion(n: int, turns: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """``n`` frames of turning on the spot ``turns`` times in an A-pose. Returns global_orient [n,3],
    body_pose [n,69], transl [n,3] (float64)."""
    t = np.linspace(0.0, 1.0, n)
    deg = np.pi / 180
    pose = np.zeros((n, 69))
    arm_l = A_POSE_DEG * deg + _wave(rng, t, 6 * deg)
    arm_r = A_POSE_DEG * deg + _wave(rng, t, 6 * deg)
    _set(pose, "shoulder_l", z=-arm_l, y=_wave(rng, t, 5 * deg))
    _set(pose, "shoulder_r", z=arm_r, y=_wave(rng, t, 5 * deg))
    _set(pose, "elbow_l", y=-(8 * deg + _wave(rng, t, 5 * deg)))
    _set(pose, "elbow_r", y=8 * deg + _wave(rng, t, 5 * deg))
    # Stepping round: weight shifts from leg to leg twice per turn, the hips and torso counter-twist.
    step = 2 * np.pi * 2.0 * turns * t + rng.uniform(0, 2 * np.pi)
    shift = np.sin(step)
    for side, sign in (("l", 1.0), ("r", -1.0)):
        lift = np.clip(sign * shift, 0, None)
        _set(pose, f"hip_{side}", x=-10 * deg * lift, z=sign * (4 * deg + 2 * deg * shift * sign))
        _set(pose, f"knee_{side}", x=18 * deg * lift)
        _set(pose, f"ankle_{side}", x=-6 * deg * lift)
    twist = 8 * deg * np.sin(step + 0.7) + _wave(rng, t, 3 * deg)
    for j in ("spine1", "spine2", "spine3"):
        _set(pose, j, y=twist / 3, z=(3 * deg * shift + _wave(rng, t, 1.5 * deg)) / 3,
             x=_wave(rng, t, 2 * deg) / 3)
    _set(pose, "head", x=_wave(rng, t, 5 * deg), y=_wave(rng, t, 6 * deg))
    _set(pose, "neck", z=_wave(rng, t, 3 * deg))
    yaw = 2 * np.pi * turns * t + rng.uniform(-0.2, 0.2)
    transl = np.stack([0.02 * shift, np.zeros(n), np.zeros(n)], 1)
    return {"global_orient": yaw_rotvec(yaw), "body_pose": pose, "transl": transl}


def novel_motion(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """``n`` frames of a motion unlike the training one: walking on the spot (first half) while turning
    from about -40 to +40 degrees, then raising the arms sideways and forwards (second half)."""
    t = np.linspace(0.0, 1.0, n)
    deg = np.pi / 180
    pose = np.zeros((n, 69))
    walk = t < 0.5
    gait = 2 * np.pi * 2.5 * np.clip(t / 0.5, 0, 1) + rng.uniform(0, 2 * np.pi)
    wk = walk.astype(float)
    for side, sign in (("l", 1.0), ("r", -1.0)):
        swing = np.sin(gait + (0 if sign > 0 else np.pi))
        _set(pose, f"hip_{side}", x=-28 * deg * swing * wk, z=sign * 3 * deg)
        _set(pose, f"knee_{side}", x=(35 * deg * np.clip(swing, 0, None) + 5 * deg) * wk)
        _set(pose, f"ankle_{side}", x=-8 * deg * swing * wk)
        # Arms swing against the legs while walking.
        _set(pose, f"shoulder_{side}", x=22 * deg * swing * wk)
    _set(pose, "spine2", y=6 * deg * np.sin(gait) * wk)
    # Arm raise: from the A-pose up to about 30 degrees above horizontal, partly forwards, with elbows.
    raise_t = np.clip((t - 0.5) / 0.5, 0, 1)
    lift = np.sin(np.pi * raise_t) ** 2 * (~walk)
    arm = (A_POSE_DEG * deg) * (1 - lift) - 30 * deg * lift
    _set(pose, "shoulder_l", z=-arm, y=-25 * deg * lift)
    _set(pose, "shoulder_r", z=arm, y=25 * deg * lift)
    _set(pose, "elbow_l", y=-(10 * deg + 35 * deg * lift))
    _set(pose, "elbow_r", y=10 * deg + 35 * deg * lift)
    _set(pose, "spine3", x=-6 * deg * lift)
    yaw = np.where(walk, -0.7 + 1.4 * np.clip(t / 0.5, 0, 1), 0.5 - 1.0 * raise_t)
    transl = np.stack([np.zeros(n), 0.01 * np.abs(np.sin(gait)) * wk, np.zeros(n)], 1)
    return {"global_orient": yaw_rotvec(yaw), "body_pose": pose, "transl": transl}


def add_pose_noise(params: dict[str, np.ndarray], deg: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Tracker-like noise: every joint's rotation (and the global one) is composed with a random
    rotation whose axis-angle components are i.i.d. N(0, ``deg``^2 degrees)."""
    if deg <= 0:
        return params
    out = dict(params)
    sigma = np.deg2rad(deg)
    for key, k in (("global_orient", 1), ("body_pose", 23)):
        r = params[key].reshape(-1, 3)
        noise = rng.normal(0.0, sigma, r.shape)
        noisy = (Rotation.from_rotvec(noise) * Rotation.from_rotvec(r)).as_rotvec()
        out[key] = noisy.reshape(-1, 3 * k)
    return out


# Key hand shapes in degrees: per finger (thumb, index, middle, ring, pinky) the bend of joints 1-3, and
# the spread of each finger's first joint.
_THUMB_IN = (20.0, 35.0, 40.0)
_CURLED = (80.0, 95.0, 60.0)
HAND_SHAPES = {
    "open": ([(5.0, 5.0, 5.0)] * 5, [0.0] * 5),
    "fist": ([_THUMB_IN] + [_CURLED] * 4, [0.0] * 5),
    "point": ([_THUMB_IN, (0.0, 0.0, 0.0)] + [_CURLED] * 3, [0.0] * 5),
    "spread": ([(0.0, 0.0, 0.0)] * 5, [20.0, 12.0, 0.0, 10.0, 18.0]),
}
_HAND_CYCLE = ("open", "fist", "open", "point", "spread")


def finger_motion(n: int, axes, rng: np.random.Generator, frames_per_shape: float = 6.0) -> np.ndarray:
    """``[n,90]`` hand poses: both hands go through open, fist, open, pointing and spread in turn
    (``frames_per_shape`` frames from one shape to the next, eased), the right hand half a shape behind
    the left, with a random start. ``axes``: :class:`rmavatar.body.hands.HandAxes` of the body."""
    import torch

    from rmavatar.body.hands import hand_pose_from_angles

    shapes = [HAND_SHAPES[name] for name in _HAND_CYCLE]
    bends = np.deg2rad(np.array([b for b, _ in shapes]))  # [S,5,3]
    spreads = np.deg2rad(np.array([s for _, s in shapes]))  # [S,5]
    start = rng.uniform(0, len(shapes))
    bend = np.zeros((n, 2, 5, 3))
    spread = np.zeros((n, 2, 5))
    for hand, lag in ((0, 0.0), (1, 0.5)):
        phase = start + np.arange(n) / frames_per_shape - lag
        a = np.floor(phase).astype(int) % len(shapes)
        b = (a + 1) % len(shapes)
        w = phase - np.floor(phase)
        w = (w * w * (3 - 2 * w))[:, None]  # smoothstep: hold a little at each shape
        bend[:, hand] = (1 - w[..., None]) * bends[a] + w[..., None] * bends[b]
        spread[:, hand] = (1 - w) * spreads[a] + w * spreads[b]
    pose = hand_pose_from_angles(torch.from_numpy(bend).float(), torch.from_numpy(spread).float(), axes)
    return pose.numpy()


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV world->camera [4,4] (x right, y down, z forward) for a camera at ``eye`` looking at
    ``target`` with world ``up``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    return M
