"""Mesh-embedded Gaussians and the pose-conditioned rectifier (the RMAvatar model)."""

from rmavatar.avatar.geometry import quat_multiply, quat_to_rotmat, rotmat_to_quat, triangle_frames
from rmavatar.avatar.model import GAUSSIAN_PARAMS, SH_C0, Avatar, AvatarConfig, GaussianSet, area_counts
from rmavatar.avatar.rectifier import Rectifier, positional_encoding, window_alpha

__all__ = [
    "GAUSSIAN_PARAMS",
    "SH_C0",
    "Avatar",
    "AvatarConfig",
    "GaussianSet",
    "Rectifier",
    "area_counts",
    "positional_encoding",
    "quat_multiply",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "triangle_frames",
    "window_alpha",
]
