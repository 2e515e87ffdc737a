"""Motion files (SMPL-format pose sequences) for animation.

Formats read:

- AIST++ / InstantAvatar ``.npz``: ``poses (N,72)`` (global orient + 23 joints), ``trans (N,3)``,
  optional ``betas``, ``fps`` / ``mocap_framerate``.
- AMASS ``.npz``: ``poses (N,156)`` SMPL-H (or (N,165) SMPL-X); the first 66 values are SMPL's body
  joints, SMPL's two hand joints are set to zero; ``trans``, ``betas``, ``mocap_framerate``.
- GART-style ``.npy``: an ``(N,72)`` array of poses, no translation (zeros), no frame rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rmavatar.utils import UserError


@dataclass
class Motion:
    """An SMPL-format sequence (numpy float32): ``global_orient [N,3]``, ``body_pose [N,69]``,
    ``transl [N,3]``, ``betas [10]`` or None, ``fps`` or None."""

    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray | None = None
    fps: float | None = None

    def __len__(self) -> int:
        return len(self.global_orient)


def load_motion(path: str | Path) -> Motion:
    """Read a motion file (see the module docstring for the formats)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise UserError(f"motion file {path} does not exist")
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise UserError(f"cannot read motion file {path}: {exc}") from exc
    trans = betas = fps = None
    if isinstance(data, np.ndarray):
        poses = data
    else:
        with data:
            if "poses" not in data.files:
                raise UserError(f"motion file {path} has no 'poses' array (it has: {', '.join(data.files)})")
            poses = data["poses"]
            trans = data["trans"] if "trans" in data.files else data.get("transl")
            betas = data["betas"] if "betas" in data.files else None
            for key in ("fps", "mocap_framerate", "mocap_frame_rate"):
                if key in data.files:
                    fps = float(np.asarray(data[key]).reshape(-1)[0])
                    break
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 1 and poses.size in (72, 156, 165):
        poses = poses[None]
    if poses.ndim != 2 or poses.shape[1] not in (72, 156, 165):
        raise UserError(
            f"motion file {path}: poses must have shape (N, 72) (SMPL, 24 joints x 3) or (N, 156) / (N, 165) "
            f"(AMASS SMPL-H / SMPL-X), got {poses.shape}"
        )
    if poses.shape[1] != 72:  # SMPL-H/X: keep the 22 body joints, SMPL's two hand joints stay at rest
        poses = np.concatenate([poses[:, :66], np.zeros((len(poses), 6))], 1)
    if not np.isfinite(poses).all():
        rows = np.nonzero(~np.isfinite(poses).all(1))[0]
        raise UserError(f"motion file {path}: poses contain NaN/inf (first at frame {rows[0]})")
    N = len(poses)
    if trans is None:
        trans = np.zeros((N, 3))
    trans = np.asarray(trans, dtype=np.float64)
    if trans.shape != (N, 3):
        raise UserError(f"motion file {path}: trans must have shape ({N}, 3), got {trans.shape}")
    if not np.isfinite(trans).all():
        raise UserError(f"motion file {path}: trans contains NaN/inf")
    if betas is not None:
        betas = np.asarray(betas, dtype=np.float32).reshape(-1)[:10]
    return Motion(
        global_orient=poses[:, :3].astype(np.float32),
        body_pose=poses[:, 3:72].astype(np.float32),
        transl=trans.astype(np.float32),
        betas=betas,
        fps=fps,
    )
