"""Which point of the body each MediaPipe pose landmark stands for.

MediaPipe's landmarks are not SMPL's joints: its hips sit higher and wider than SMPL's hip joints, its
ankles higher than the ankle joint, the face and hand landmarks are surface points. Each landmark k we
use is modelled as a point rigidly attached to one body segment:

    X_k = J[anchor_k] + G[frame_k] @ offset_k

with J the posed SMPL joints [24,3], G the posed world rotations of the SMPL joints (the rotation of
the segment that starts at that joint) and offset_k in metres in the body's canonical T-pose frame
(x = the body's left, y up, z forward). The offsets were measured on synthetic subjects whose true
poses are known (``scripts/calibrate_capture_landmarks.py``: male seed 1 and female seed 2, never the
default evaluation subject), as the least-squares fit of MediaPipe's 2D landmarks over 320 frames.
"""

from __future__ import annotations

import numpy as np
import torch

from rmavatar.body.base import SMPL_PARENTS
from rmavatar.body.lbs import axis_angle_to_matrix, global_rotations

NUM_MEDIAPIPE = 33

# MediaPipe landmark -> (name, anchor SMPL joint, frame SMPL joint). Mouth corners and thumbs are left
# out (they repeat the nose and the hand's other landmarks).
LANDMARKS: dict[int, tuple[str, int, int]] = {
    0: ("nose", 15, 15),
    2: ("left_eye", 15, 15),
    5: ("right_eye", 15, 15),
    7: ("left_ear", 15, 15),
    8: ("right_ear", 15, 15),
    11: ("left_shoulder", 16, 13),
    12: ("right_shoulder", 17, 14),
    13: ("left_elbow", 18, 16),
    14: ("right_elbow", 19, 17),
    15: ("left_wrist", 20, 18),
    16: ("right_wrist", 21, 19),
    17: ("left_pinky", 20, 20),
    18: ("right_pinky", 21, 21),
    19: ("left_index", 20, 20),
    20: ("right_index", 21, 21),
    23: ("left_hip", 1, 0),
    24: ("right_hip", 2, 0),
    25: ("left_knee", 4, 1),
    26: ("right_knee", 5, 2),
    27: ("left_ankle", 7, 4),
    28: ("right_ankle", 8, 5),
    29: ("left_heel", 7, 7),
    30: ("right_heel", 8, 8),
    31: ("left_foot_index", 10, 10),
    32: ("right_foot_index", 11, 11),
}

USED = tuple(LANDMARKS)  # MediaPipe indices in the order of the arrays below

# offset_k in metres, canonical frame (measured: see the module docstring). Regenerate with
# scripts/calibrate_capture_landmarks.py.
OFFSETS: dict[int, tuple[float, float, float]] = {
    0: (0.0, -0.006, 0.11),  # nose
    2: (0.026, 0.031, 0.09),  # left_eye
    5: (-0.026, 0.031, 0.09),  # right_eye
    7: (0.055, 0.033, 0.042),  # left_ear
    8: (-0.055, 0.033, 0.042),  # right_ear
    11: (0.01, 0.004, 0.009),  # left_shoulder
    12: (-0.01, 0.004, 0.009),  # right_shoulder
    13: (-0.001, 0.005, 0.003),  # left_elbow
    14: (0.001, 0.005, 0.003),  # right_elbow
    15: (0.018, -0.002, -0.001),  # left_wrist
    16: (-0.018, -0.002, -0.001),  # right_wrist
    17: (0.095, -0.008, -0.017),  # left_pinky
    18: (-0.095, -0.008, -0.017),  # right_pinky
    19: (0.095, -0.021, 0.001),  # left_index
    20: (-0.095, -0.021, 0.001),  # right_index
    23: (-0.006, 0.013, 0.023),  # left_hip
    24: (0.006, 0.013, 0.023),  # right_hip
    25: (-0.006, -0.007, 0.002),  # left_knee
    26: (0.006, -0.007, 0.002),  # right_knee
    27: (0.004, 0.027, 0.001),  # left_ankle
    28: (-0.004, 0.027, 0.001),  # right_ankle
    29: (-0.013, -0.031, -0.05),  # left_heel
    30: (0.013, -0.031, -0.05),  # right_heel
    31: (-0.013, 0.001, 0.047),  # left_foot_index
    32: (0.013, 0.001, 0.047),  # right_foot_index
}

# Bones for the 3D direction term: pairs of used landmarks whose direction MediaPipe's world landmarks
# give (upper and lower limbs, shoulder and hip lines, the torso sides).
BONES: tuple[tuple[int, int], ...] = (
    (11, 13), (13, 15), (12, 14), (14, 16),  # arms
    (23, 25), (25, 27), (24, 26), (26, 28),  # legs
    (11, 12), (23, 24), (11, 23), (12, 24),  # torso
    (27, 31), (28, 32),  # feet
)


def landmark_tables(device=None, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """anchor [K] and frame [K] SMPL joint indices and offsets [K,3] for the USED landmarks."""
    anchor = torch.tensor([LANDMARKS[k][1] for k in USED], device=device)
    frame = torch.tensor([LANDMARKS[k][2] for k in USED], device=device)
    offsets = torch.tensor(np.array([OFFSETS[k] for k in USED]), dtype=dtype, device=device)
    return anchor, frame, offsets


def joint_rotations(global_orient: torch.Tensor, body_pose: torch.Tensor) -> torch.Tensor:
    """World rotations of the 24 SMPL joints [B,24,3,3] from SMPL-format pose ([B,3], [B,69])."""
    local = axis_angle_to_matrix(torch.cat([global_orient, body_pose], 1).reshape(-1, 24, 3))
    return global_rotations(local, SMPL_PARENTS)


def body_landmarks(joints: torch.Tensor, rotations: torch.Tensor, offsets: torch.Tensor | None = None,
                   ) -> torch.Tensor:
    """The body's points for the USED landmarks [B,K,3]: joints [B,24,3], rotations [B,24,3,3] (from
    :func:`joint_rotations`, rotated by the camera if the joints are), offsets [K,3] (default OFFSETS)."""
    anchor, frame, default = landmark_tables(joints.device, joints.dtype)
    offsets = default if offsets is None else offsets
    return joints[:, anchor] + (rotations[:, frame] @ offsets[:, :, None])[..., 0]
