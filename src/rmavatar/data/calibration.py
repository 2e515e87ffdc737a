"""Multi-camera calibration files: the cameras of a calibrated rig as :class:`CalibratedCamera` records.

Two formats are read, both as the motion-capture world describes them:

- **TOML** as Pose2Sim and Anipose write it (OpenCV's model): one table per camera with ``name``,
  ``size = [width, height]``, ``matrix`` (K, pixels), ``distortions = [k1, k2, p1, p2]``, ``rotation``
  (a Rodrigues vector) and ``translation`` (metres), world to camera: ``x_cam = R X + t``.
- **Qualisys** ``.qca.txt`` (XML), converted as Pose2Sim's ``calib_qca_fun`` documents: intrinsics in
  1/64 pixel of the sensor (less the video window's corner), the camera's position in millimetres and
  its axes (x right, y up, looking down -z) in world coordinates as the rows of r11..r33; so
  ``R = diag(1, -1, -1) M`` (M the file's r11..r33 read row by row) and ``t = -R position``.

Lens distortion is read and kept (``distortion``) but not applied: rmavatar's cameras are pinholes, and
the rigs these files come from have coefficients of about 1e-3 (under a pixel at the frame's corners).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rmavatar.utils import UserError

FORMATS = ("toml", "qualisys")


@dataclass(frozen=True)
class CalibratedCamera:
    """One camera of a calibration: ``name``; K [3,3] (pixels of ``size`` = (width, height)); R [3,3],
    t [3] world to camera (OpenCV axes: x right, y down, z forward; metres); ``distortion`` [k1, k2, p1,
    p2] (read, not applied)."""

    name: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int]
    distortion: np.ndarray

    @property
    def viewmat(self) -> np.ndarray:
        """[4,4] float64 world to camera."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    def relative_to(self, other: "CalibratedCamera") -> np.ndarray:
        """[4,4] float64 from ``other``'s camera frame to this camera's: the viewmat of this camera in a
        world that is ``other``'s camera frame (how a dataset captured from ``other`` places it)."""
        return self.viewmat @ np.linalg.inv(other.viewmat)

    def scaled_K(self, width: int, height: int) -> np.ndarray:
        """K [3,3] for frames of ``width`` x ``height`` (a resized video of this camera)."""
        return np.diag([width / self.size[0], height / self.size[1], 1.0]) @ self.K


def read_calibration(path: str | Path) -> dict[str, CalibratedCamera]:
    """The cameras of the calibration file ``path`` by name (TOML or Qualisys ``.qca.txt``, told by the
    file's content). A file that is neither, or a camera with a missing or malformed entry, is a
    UserError naming the file and the entry."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise UserError(f"calibration {path}: cannot read it ({exc.strerror or exc})") from None
    if text.lstrip().startswith("<"):
        cameras = _read_qualisys(path, text)
    else:
        cameras = _read_toml(path, text)
    if not cameras:
        raise UserError(f"calibration {path} holds no camera")
    for cam in cameras.values():
        _check_camera(path, cam)
    return cameras


def pick_camera(cameras: dict[str, CalibratedCamera], name: str | None, video: str | Path | None,
                path: str | Path, option: str = "--camera") -> CalibratedCamera:
    """The camera ``name``, or (None) the one named like the ``video`` file's stem (Pose2Sim names both
    ``cam01``); a UserError listing the cameras there are otherwise."""
    names = ", ".join(sorted(cameras))
    if name is None and video is not None:
        stem = Path(video).stem
        matches = [c for c in cameras if c == stem or stem.startswith(c) or c.endswith(stem)]
        if len(matches) == 1:
            return cameras[matches[0]]
        raise UserError(f"calibration {path}: no camera is named like the video {Path(video).name} (cameras: "
                        f"{names}); name it with {option}")
    if name not in cameras:
        raise UserError(f"calibration {path} has no camera {name!r} (cameras: {names})")
    return cameras[name]


def _check_camera(path: Path, cam: CalibratedCamera) -> None:
    where = f"calibration {path}, camera {cam.name!r}"
    if not (np.all(np.isfinite(cam.K)) and np.all(np.isfinite(cam.R)) and np.all(np.isfinite(cam.t))):
        raise UserError(f"{where}: a value is not a finite number")
    if cam.K[0, 0] <= 0 or cam.K[1, 1] <= 0:
        raise UserError(f"{where}: the focal length must be positive, got {cam.K[0, 0]:g}, {cam.K[1, 1]:g}")
    if min(cam.size) <= 0:
        raise UserError(f"{where}: the image size must be positive, got {cam.size}")
    if not np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-4) or np.linalg.det(cam.R) < 0:
        raise UserError(f"{where}: the rotation is not a rotation (R R^T = I, det R = 1)")


def _number(where: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{where}: {value!r} is not a number") from None
    return out


def _rodrigues(v: np.ndarray) -> np.ndarray:
    """The rotation matrix of the axis-angle vector ``v`` [3]."""
    theta = float(np.linalg.norm(v))
    if theta < 1e-12:
        return np.eye(3)
    k = v / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


def _read_toml(path: Path, text: str) -> dict[str, CalibratedCamera]:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"calibration {path} is neither a TOML calibration (Pose2Sim, Anipose) nor a Qualisys "
                        f".qca.txt file: {exc}") from None
    cameras = {}
    for key, table in doc.items():
        if not isinstance(table, dict) or "matrix" not in table:
            continue  # e.g. Pose2Sim's [metadata]
        where = f"calibration {path}, [{key}]"
        missing = [k for k in ("size", "matrix", "rotation", "translation") if k not in table]
        if missing:
            raise UserError(f"{where} lacks {', '.join(missing)}")
        try:
            K = np.array(table["matrix"], dtype=np.float64).reshape(3, 3)
            rot = np.array(table["rotation"], dtype=np.float64)
            t = np.array(table["translation"], dtype=np.float64).reshape(3)
            w, h = (int(round(_number(where, s))) for s in table["size"])
            dist = np.array(table.get("distortions", [0, 0, 0, 0]), dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise UserError(f"{where}: malformed matrix, rotation, translation or size ({exc})") from None
        R = _rodrigues(rot.reshape(3)) if rot.size == 3 else rot.reshape(3, 3)
        name = str(table.get("name", key))
        cameras[name] = CalibratedCamera(name, K, R, t, (w, h), dist)
    return cameras


def _read_qualisys(path: Path, text: str) -> dict[str, CalibratedCamera]:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise UserError(f"calibration {path} is not valid XML (a Qualisys .qca.txt file): {exc}") from None
    cameras = {}
    flip = np.diag([1.0, -1.0, -1.0])  # Qualisys' camera looks along -z, y up; OpenCV's along +z, y down
    for i, node in enumerate(root.findall("cameras/camera")):
        name = node.get("serial") or f"camera{i + 1}"
        where = f"calibration {path}, camera {name!r}"
        tr, intr, fov = node.find("transform"), node.find("intrinsic"), node.find("fov_video")
        if tr is None or intr is None or fov is None:
            raise UserError(f"{where} lacks its transform, intrinsic or fov_video entry")
        get = lambda n, k: _number(f"{where}, {n.tag} {k}", n.get(k))  # noqa: E731
        M = np.array([[get(tr, f"r{r}{c}") for c in (1, 2, 3)] for r in (1, 2, 3)])
        position = np.array([get(tr, k) for k in "xyz"]) / 1000.0
        left, top = get(fov, "left"), get(fov, "top")
        w, h = int(get(fov, "right") - left + 1), int(get(fov, "bottom") - top + 1)
        K = np.array([[get(intr, "focalLengthU") / 64, 0.0, get(intr, "centerPointU") / 64 - left],
                      [0.0, get(intr, "focalLengthV") / 64, get(intr, "centerPointV") / 64 - top],
                      [0.0, 0.0, 1.0]])
        dist = np.array([get(intr, k) / 64 for k in ("radialDistortion1", "radialDistortion2",
                                                     "tangentalDistortion1", "tangentalDistortion2")])
        R = flip @ M
        cameras[name] = CalibratedCamera(name, K, R, -R @ position, (w, h), dist)
    return cameras
