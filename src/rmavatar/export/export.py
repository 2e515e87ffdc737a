"""Exporting a posed avatar: pick the pose, compute its world-space Gaussians, write the PLY."""

from __future__ import annotations

import os
from pathlib import Path

from rmavatar.avatar.trained import TrainedAvatar
from rmavatar.body import PoseSequence, motion_to_sequence
from rmavatar.export.ply import DEFAULT_UP, write_ply
from rmavatar.utils import UserError
from rmavatar.utils.outputs import check_output_file


def check_ply_output(path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Fail early, before loading anything, when ``path`` cannot become a PLY file."""
    return check_output_file(path, option="--ply", overwrite=overwrite, suffixes=(".ply",))


def pose_for_export(trained: TrainedAvatar, motion_path: str | None, frame: int, rest: str = "tpose") -> PoseSequence:
    """One pose: frame ``frame`` of a motion file, else the rest pose ``rest`` at the origin
    ('tpose', 'apose' or 'train', see :meth:`TrainedAvatar.rest_pose`)."""
    if motion_path is None:
        return trained.rest_pose(rest)
    from rmavatar.body import load_motion

    seq = motion_to_sequence(load_motion(motion_path), source=str(motion_path))
    n = len(seq)
    if not -n <= frame < n:
        raise UserError(f"--frame {frame} is out of range: {motion_path} has {n} frames")
    k = frame % n
    return seq.select(slice(k, k + 1))


def export_ply(trained: TrainedAvatar, seq: PoseSequence, out: str | os.PathLike, overwrite: bool = False,
               up: str = DEFAULT_UP) -> int:
    """Write the avatar posed by the single pose ``seq`` to ``out``; returns the Gaussian count.

    ``up``: the file's world convention, "-y" (default: y down, as stock 3DGS viewers expect) or "y"
    (SMPL's y-up world); see :mod:`rmavatar.export.ply`."""
    gs = trained.pose(seq, 0)
    write_ply(out, gs.means, gs.quats, gs.scales, gs.opacities, gs.world_sh(), up=up, overwrite=overwrite)
    return int(gs.means.shape[0])
