"""Motion files (SMPL-format pose sequences) for animation.

Formats read:

- AIST++ / InstantAvatar ``.npz``: ``poses (N,72)`` (global orient + 23 joints), ``trans (N,3)``,
  optional ``betas``, ``fps`` / ``mocap_framerate``.
- AMASS ``.npz``: ``poses (N,156)`` SMPL-H (or (N,165) SMPL-X); the first 66 values are SMPL's body
  joints, SMPL's two hand joints are set to zero; the last 90 are the finger poses (``hand_pose``,
  left hand then right, MANO's joint order); SMPL-X's jaw and eyes in between are dropped. ``trans``,
  ``betas``, ``mocap_framerate`` (or ``mocap_frame_rate``); ``gender`` is ignored. AMASS is Z-up: it is
  turned to SMPL's y-up (-90 degrees about x, about the origin) unless ``keep_up=True``.
- GART-style ``.npy``: an ``(N,72)`` array of poses, no translation (zeros), no frame rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rmavatar.body.poses import PoseSequence
from rmavatar.utils import UserError
from rmavatar.utils.errors import load_error


@dataclass
class Motion:
    """An SMPL-format sequence (numpy float32): ``global_orient [N,3]``, ``body_pose [N,69]``,
    ``transl [N,3]``, ``betas [10]`` or None, ``fps`` or None, ``hand_pose [N,90]`` (SMPL-H / SMPL-X
    files) or None (the file has no finger poses: bodies show their relaxed hands)."""

    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray | None = None
    fps: float | None = None
    hand_pose: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.global_orient)


def load_motion(path: str | Path, keep_up: bool = False) -> Motion:
    """Read a motion file (see the module docstring for the formats).

    ``keep_up``: leave AMASS sequences Z-up instead of turning them y-up.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise UserError(f"motion file {path} does not exist")
    _check_magic(path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise UserError(f"cannot read motion file {path}: {load_error(exc)}") from None
    trans = betas = fps = None
    amass = False
    try:
        if isinstance(data, np.ndarray):
            poses = data
        else:
            with data:
                if "poses" not in data.files:
                    raise UserError(f"motion file {path} has no 'poses' array (it has: {', '.join(data.files)})")
                poses = data["poses"]
                trans = data["trans"] if "trans" in data.files else data.get("transl")
                betas = data["betas"] if "betas" in data.files else None
                amass = "mocap_framerate" in data.files or "mocap_frame_rate" in data.files
                for key in ("fps", "mocap_framerate", "mocap_frame_rate"):
                    if key in data.files:
                        rate = _numbers(data[key], path, key).reshape(-1)
                        fps = float(rate[0]) if rate.size else float("nan")
                        if not (np.isfinite(fps) and fps > 0):  # else a command would blame its own --fps
                            raise UserError(f"motion file {path}: {key} must be a positive number of frames per "
                                            f"second, got {fps:g}")
                        break
    except ValueError as exc:  # an npz member is read only when accessed: object arrays fail here
        if "allow_pickle" not in str(exc):
            raise
        raise UserError(f"cannot read motion file {path}: {load_error(exc)}") from None
    poses = _numbers(poses, path, "poses")
    if poses.ndim == 1 and poses.size in (72, 156, 165):
        poses = poses[None]
    if poses.ndim != 2 or poses.shape[1] not in (72, 156, 165):
        raise UserError(
            f"motion file {path}: poses must have shape (N, 72) (SMPL, 24 joints x 3) or (N, 156) / (N, 165) "
            f"(AMASS SMPL-H / SMPL-X), got {poses.shape}"
        )
    amass = amass or poses.shape[1] != 72
    has_hands = poses.shape[1] != 72
    if has_hands:
        # SMPL-H/X: the 22 body joints, then SMPL's two hand joints at rest (SMPL-H / SMPL-X have none;
        # rmavatar's fingers hang from them), then the fingers: the last 90 values in both layouts
        poses = np.concatenate([poses[:, :66], np.zeros((len(poses), 6)), poses[:, -90:]], 1)
    if not np.isfinite(poses).all():
        rows = np.nonzero(~np.isfinite(poses).all(1))[0]
        raise UserError(f"motion file {path}: poses contain NaN/inf (first at frame {rows[0]})")
    N = len(poses)
    if trans is None:
        trans = np.zeros((N, 3))
    trans = _numbers(trans, path, "trans")
    if trans.shape != (N, 3):
        raise UserError(f"motion file {path}: trans must have shape ({N}, 3), got {trans.shape}")
    if not np.isfinite(trans).all():
        raise UserError(f"motion file {path}: trans contains NaN/inf")
    if betas is not None:
        betas = _numbers(betas, path, "betas").astype(np.float32).reshape(-1)[:10]
    if amass and not keep_up:
        poses, trans = _z_up_to_y_up(poses, trans)  # the finger poses are relative to their parents: kept
    return Motion(
        global_orient=poses[:, :3].astype(np.float32),
        body_pose=poses[:, 3:72].astype(np.float32),
        transl=trans.astype(np.float32),
        betas=betas,
        fps=fps,
        hand_pose=poses[:, 72:].astype(np.float32) if has_hands else None,
    )


def _check_magic(path: Path) -> None:
    """UserError unless ``path`` starts like a .npy, a .npz (zip) or a pickle (which np.load refuses with
    its own reason): a text file given as a motion would otherwise be called a pickle."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError as exc:
        raise UserError(f"cannot read motion file {path}: {exc.strerror or exc}") from None
    if head.startswith((b"\x93NUMPY", b"PK\x03\x04", b"PK\x05\x06", b"\x80")):
        return
    if not head:
        why = "it is empty"
    elif all(b >= 0x20 or b in b"\t\r\n" for b in head[:32].removeprefix(b"\xef\xbb\xbf")):
        why = f"it looks like a text file (it starts {head[:24].decode('utf-8', 'replace')!r})"
    else:
        why = f"it starts {head[:8]!r}"
    fmt = f"'{path.suffix}' " if path.suffix else ""
    raise UserError(f"cannot read motion file {path}: unsupported format {fmt}- it is not a NumPy .npz or .npy "
                    f"file ({why}); supported motion formats: .npz (AIST++, InstantAvatar, AMASS) and .npy "
                    "(GART) arrays")


def _numbers(value, path: Path, key: str) -> np.ndarray:
    """``value`` as float64; UserError naming the file and key for strings or other non-numbers."""
    arr = np.asarray(value)
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool) or arr.size == 0:
        raise UserError(f"motion file {path}: '{key}' must hold numbers, got {arr.dtype} of shape {arr.shape}")
    return arr.astype(np.float64)


def _z_up_to_y_up(poses: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turn a sequence by -90 degrees about x (Z-up -> y-up), about the world origin.

    SMPL rotates about the rest pelvis J0, so the translation becomes ``R (t + J0) - J0``; J0 depends on
    the body shape, and a typical one is used (the error is (R - I) times the shape's J0 difference, mm).
    """
    from scipy.spatial.transform import Rotation

    from rmavatar.body.base import SMPL_REST_JOINTS

    turn = Rotation.from_euler("x", -90, degrees=True)
    poses = poses.copy()
    poses[:, :3] = (turn * Rotation.from_rotvec(poses[:, :3])).as_rotvec()
    J0 = SMPL_REST_JOINTS[0]
    return poses, turn.apply(trans + J0) - J0


def motion_to_sequence(motion, source: str = "motion") -> PoseSequence:
    """Check a loaded ``Motion``'s arrays and return them as a :class:`PoseSequence` (with the finger
    poses where the motion has them).

    ``source`` names the file in error messages.
    """
    arrays = {}
    for name, width in (("global_orient", 3), ("body_pose", 69), ("transl", 3), ("hand_pose", 90)):
        a = getattr(motion, name, None)
        if a is None:
            if name == "hand_pose":  # optional: a motion without fingers
                continue
            raise UserError(f"{source}: motion has no {name}")
        a = np.asarray(a)
        if a.ndim != 2 or a.shape[1] != width:
            raise UserError(f"{source}: {name} must have shape (frames, {width}), got {a.shape}")
        arrays[name] = a
    counts = {a.shape[0] for a in arrays.values()}
    if len(counts) != 1:
        raise UserError(f"{source}: {', '.join(arrays)} have different frame counts "
                        f"{[a.shape[0] for a in arrays.values()]}")
    if counts.pop() == 0:
        raise UserError(f"{source}: motion has no frames")
    for name, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise UserError(f"{source}: {name} contains NaN or infinite values")
    return PoseSequence.from_params(arrays)
