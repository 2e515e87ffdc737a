"""Mesh-embedded Gaussians and the pose-conditioned rectifier (the RMAvatar model), and a trained avatar
read back from its run folder (``load_trained``)."""

from rmavatar.avatar.geometry import (
    quat_multiply,
    quat_to_rotmat,
    rotmat_to_quat,
    triangle_frames,
)
from rmavatar.avatar.model import (
    GAUSSIAN_PARAMS,
    SH_C0,
    Avatar,
    AvatarConfig,
    AvatarExtras,
    area_counts,
)
from rmavatar.avatar.frame import RenderedFrame, pose_frame, render_frame
from rmavatar.avatar.rectifier import Rectifier, positional_encoding, window_alpha
from rmavatar.avatar.trained import TrainedAvatar, load_trained

__all__ = [
    "GAUSSIAN_PARAMS",
    "SH_C0",
    "Avatar",
    "AvatarConfig",
    "AvatarExtras",
    "Rectifier",
    "RenderedFrame",
    "TrainedAvatar",
    "area_counts",
    "load_trained",
    "pose_frame",
    "positional_encoding",
    "quat_multiply",
    "render_frame",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "triangle_frames",
    "window_alpha",
]
