"""A pinhole camera, the rasterizer's and every dataset's.

Pixel convention (the same as the rasterizer's, gsplat's): the centre of pixel column ``i``, row ``j``
lies at image coordinates ``(i + 0.5, j + 0.5)``, so an image of ``W x H`` pixels covers exactly
``[0, W] x [0, H]``. Under this convention resizing an image by ``sx = W'/W``, ``sy = H'/H`` maps every
image point ``(u, v)`` to ``(sx u, sy v)``, so the intrinsics scale exactly as ``K' = diag(sx, sy, 1) K``
(the principal point included, no half-pixel correction). Calibrations made in OpenCV's integer-centre
convention are used as they are: the 0.5 px shift is below what trackers resolve, and the peers ignore it
as well.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    K [3,3] float32 intrinsics (pixels, convention in the module docstring);
    viewmat [4,4] float32 world-to-camera, OpenCV axes (x right, y down, z forward), metres;
    width, height: the image size in pixels that K refers to.
    """

    K: np.ndarray
    viewmat: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float32)
        viewmat = np.asarray(self.viewmat, dtype=np.float32)
        if K.shape != (3, 3):
            raise ValueError(f"Camera.K must be [3,3], got {K.shape}")
        if viewmat.shape != (4, 4):
            raise ValueError(f"Camera.viewmat must be [4,4], got {viewmat.shape}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}")
        K.setflags(write=False)
        viewmat.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "viewmat", viewmat)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for the image resampled to ``width x height``: K' = diag(sx, sy, 1) K."""
        sx = width / self.width
        sy = height / self.height
        K = np.diag([sx, sy, 1.0]).astype(np.float64) @ self.K.astype(np.float64)
        return Camera(K.astype(np.float32), self.viewmat, width, height)

    @property
    def position(self) -> np.ndarray:
        """The camera centre in world coordinates [3]."""
        R = self.viewmat[:3, :3].astype(np.float64)
        t = self.viewmat[:3, 3].astype(np.float64)
        return (-R.T @ t).astype(np.float32)

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points [N,3] -> image coordinates [N,2] (pixel-centre convention above)."""
        p = np.asarray(points, dtype=np.float64)
        cam = p @ self.viewmat[:3, :3].T.astype(np.float64) + self.viewmat[:3, 3]
        uvw = cam @ self.K.T.astype(np.float64)
        return (uvw[:, :2] / uvw[:, 2:3]).astype(np.float32)


class CameraTensors(NamedTuple):
    """A camera as tensors on a device, for code that draws the same cameras again and again (a training
    step): viewmat [4,4] and K [3,3] as in :class:`Camera`, width and height in pixels."""

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
