"""The in-memory records every dataset produces: a `Frame` (pixels, camera, SMPL-format parameters).

Its camera is :class:`rmavatar.render.camera.Camera` (the pixel convention is stated there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rmavatar.render.camera import Camera


@dataclass(frozen=True)
class Frame:
    """One video frame with everything needed to fit an avatar to it.

    image [H,W,3] float32 RGB in [0,1]; mask [H,W] float32 in [0,1] (soft foreground coverage);
    camera: the Camera for this image size; betas [10], global_orient [3], body_pose [69], transl [3]:
    SMPL-format parameters (axis-angle, metres, SMPL-style translation) in the same world frame as
    camera.viewmat; index: the frame's number in its source; split: the split it was requested from;
    hand_pose [90] (MANO order, left then right hand) or None where the dataset has no finger poses.
    Arrays are read-only views of the dataset's cache: copy before modifying.
    """

    image: np.ndarray
    mask: np.ndarray
    camera: Camera
    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    index: int
    split: str
    hand_pose: np.ndarray | None = None
