"""rmavatar's native dataset format: what `rmavatar synth` writes and what a user converts a video to.

A folder::

    meta.yaml     format: rmavatar-native, version: 1, name, gender, body, fps, width, height,
                  num_frames, splits: {train: [frame indices], val: [...], test: [...], novel_pose: [...]},
                  poses: given | estimated (optional, default given), extra: {free-form provenance},
                  same_instant: {split: [frame indices]} (optional: for each frame of a split seen by
                  another camera, the frame of the same instant the main camera took; see docs/data.md)
    cameras.npz   K [N,3,3] or [3,3] (one camera for all frames), viewmat [N,4,4] or [4,4]
                  (world-to-camera, OpenCV axes, metres); float32
    smpl.npz      betas [N,10] or [10], global_orient [N,3], body_pose [N,69], transl [N,3]; float32;
                  optional finger poses: hand_pose [N,90] float32 (per hand 15 joints x 3 axis-angle, MANO
                  order, left hand then right) and hand_found [N,2] bool (a capture saw that hand);
                  optional body_offsets [V] float32: the Anny body's offsets, metres along its rest
                  normals (a shape fitted to the person by rmavatar capture; body must be anny)
    images/00000.png ...   8-bit RGB, frame i is f"{i:05d}.png"
    masks/00000.png  ...   8-bit grey, 0-255 soft foreground coverage

Frames are numbered 0..N-1; a frame may belong to several splits. The full description, with the
conventions (pixel centres, SMPL world frame), is in docs/data.md.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import yaml

from rmavatar.data.dataset import Dataset, FrameRecord, hand_columns, warn
from rmavatar.data.io import load_npz, to_uint8, write_png
from rmavatar.render.camera import Camera
from rmavatar.utils import UserError
from rmavatar.utils.config import whole_number
from rmavatar.utils.outputs import check_output_folder, output_folder

NATIVE_KIND = "native-dataset"

FORMAT = "rmavatar-native"
VERSION = 1
GENDERS = ("male", "female", "neutral")
# meta.yaml's 'poses': "given" (a tracker's or the true ones) or "estimated" (fitted from the video alone
# by `rmavatar capture`; what pose refinement during training switches on by).
POSE_SOURCES = ("given", "estimated")
PARAM_KEYS = ("betas", "global_orient", "body_pose", "transl")
HAND_KEYS = ("hand_pose", "hand_found")  # optional in smpl.npz; hand_found needs hand_pose


@dataclass
class NativeMeta:
    """meta.yaml's content besides what is derived from the arrays (size, frame count).

    name: the subject's name; splits: split name -> frame indices (0-based, into the N frames);
    fps: the video's frame rate; gender: "male", "female", "neutral" or None (picks the SMPL file);
    body: a body preset the data was made with (e.g. "anny:female"), or None;
    poses_estimated: the poses were estimated from the video alone (``rmavatar capture``);
    extra: free-form provenance (tracker, synth seed, ...) kept verbatim;
    same_instant: split -> for each of its frames, the frame of the same instant taken by the main camera
    (a calibrated second camera's frames, ``rmavatar capture --novel-view``); evaluation poses such a
    frame as the training run posed that instant.
    """

    name: str
    splits: dict[str, list[int]]
    fps: float = 30.0
    gender: str | None = None
    body: str | None = None
    poses_estimated: bool = False
    extra: dict[str, Any] = field(default_factory=dict)
    same_instant: dict[str, list[int]] = field(default_factory=dict)


def _as_meta(meta: NativeMeta | Mapping) -> NativeMeta:
    if isinstance(meta, NativeMeta):
        return meta
    known = {"name", "splits", "fps", "gender", "body", "poses_estimated", "extra", "same_instant"}
    unknown = set(meta) - known
    if unknown:
        raise UserError(f"unknown meta keys {sorted(unknown)} (allowed: {sorted(known)})")
    return NativeMeta(**meta)


def _stack_cameras(cameras, n: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    """Camera | sequence of Camera | {"K", "viewmat"} -> K, viewmat arrays (single or per frame)."""
    size = None
    if isinstance(cameras, Camera):
        K, V, size = cameras.K, cameras.viewmat, (cameras.width, cameras.height)
    elif isinstance(cameras, Mapping):
        missing = [k for k in ("K", "viewmat") if k not in cameras]
        if missing:
            raise UserError(f"cameras is missing {missing}")
        K, V = np.asarray(cameras["K"]), np.asarray(cameras["viewmat"])
    else:
        cams = list(cameras)
        if not cams or not all(isinstance(c, Camera) for c in cams):
            raise UserError("cameras must be a Camera, a list of Camera, or a dict with K and viewmat")
        sizes = {(c.width, c.height) for c in cams}
        if len(sizes) != 1:
            raise UserError(f"all cameras must share one image size, got {sorted(sizes)}")
        size = sizes.pop()
        K, V = np.stack([c.K for c in cams]), np.stack([c.viewmat for c in cams])
    K, V = np.asarray(K, np.float32), np.asarray(V, np.float32)
    if K.shape not in ((3, 3), (n, 3, 3)):
        raise UserError(f"camera K must be [3,3] or [{n},3,3] for {n} frames, got {list(K.shape)}")
    if V.shape not in ((4, 4), (n, 4, 4)):
        raise UserError(f"camera viewmat must be [4,4] or [{n},4,4] for {n} frames, got {list(V.shape)}")
    if not (np.isfinite(K).all() and np.isfinite(V).all()):
        raise UserError("cameras hold NaN or Inf")
    return K, V, size


def _check_params(params, where: str) -> dict[str, np.ndarray]:
    """SMPL-format parameters (mapping or object with attributes) -> validated float32 arrays."""
    out = {}
    for key in PARAM_KEYS:
        value = params.get(key) if isinstance(params, Mapping) else getattr(params, key, None)
        if value is None:
            raise UserError(f"{where}: SMPL parameters are missing '{key}'")
        out[key] = np.asarray(value, dtype=np.float32)
    n = out["global_orient"].shape[0] if out["global_orient"].ndim == 2 else -1
    want = {"global_orient": (n, 3), "body_pose": (n, 69), "transl": (n, 3)}
    for key, shape in want.items():
        if n < 0 or out[key].shape != shape:
            raise UserError(f"{where}: '{key}' must be [N,{shape[1]}] with N frames as global_orient, "
                            f"got {list(out[key].shape)}")
    get = params.get if isinstance(params, Mapping) else lambda key: getattr(params, key, None)
    if get("hand_pose") is not None:
        out["hand_pose"] = np.asarray(get("hand_pose"), dtype=np.float32)
        if out["hand_pose"].shape != (n, 90):
            raise UserError(f"{where}: 'hand_pose' must be [N,90] (15 joints x 3 per hand, left then right) "
                            f"with N frames as global_orient, got {list(out['hand_pose'].shape)}")
    if get("hand_found") is not None:
        if "hand_pose" not in out:
            raise UserError(f"{where}: 'hand_found' is given without 'hand_pose'")
        found = np.asarray(get("hand_found"))
        if found.shape != (n, 2) or found.dtype.kind not in "bui":
            raise UserError(f"{where}: 'hand_found' must be [N,2] booleans (left, right hand seen), got "
                            f"{list(found.shape)} {found.dtype}")
        out["hand_found"] = found.astype(bool)
    if get("body_offsets") is not None:
        out["body_offsets"] = np.asarray(get("body_offsets"), dtype=np.float32)
        if out["body_offsets"].ndim != 1:
            raise UserError(f"{where}: 'body_offsets' must be [V] (one value per body vertex), got "
                            f"{list(out['body_offsets'].shape)}")
    betas = out["betas"]
    if betas.ndim == 2 and betas.shape[0] == 1:
        betas = betas[0]
    if betas.shape not in ((10,), (n, 10)):
        raise UserError(f"{where}: 'betas' must be [10] or [{n},10], got {list(out['betas'].shape)}")
    out["betas"] = betas
    for key, value in out.items():
        if not np.isfinite(value).all():
            raise UserError(f"{where}: '{key}' holds NaN or Inf")
    return out


def _check_splits(splits: Mapping, n: int, where: str) -> dict[str, list[int]]:
    if not isinstance(splits, Mapping) or not splits:
        raise UserError(f"{where}: 'splits' must map split names to lists of frame indices")
    out = {}
    for name, idx in splits.items():
        if not isinstance(idx, (list, tuple, np.ndarray)):
            raise UserError(f"{where}: split '{name}' must be a list of frame indices, got {_shown(idx)}")
        if isinstance(idx, np.ndarray):
            if idx.ndim != 1:
                raise UserError(f"{where}: split '{name}' must be a list of frame indices, got an array of "
                                f"shape {list(idx.shape)}")
            idx = idx.tolist()
        idx = [_frame_index(i, f"{where}: split '{name}'") for i in idx]
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise UserError(f"{where}: split '{name}' refers to frames {bad[:5]} outside 0..{n - 1}")
        seen: set[int] = set()
        twice = sorted({i for i in idx if i in seen or seen.add(i)})
        if twice:
            raise UserError(f"{where}: split '{name}' lists frame(s) {twice[:5]} more than once "
                            f"(each frame at most once per split)")
        out[str(name)] = idx
    return out


def _check_same_instant(same: Mapping | None, splits: dict[str, list[int]], n: int, where: str) -> dict[str, list[int]]:
    """meta's ``same_instant`` checked: each key a split, each list one frame index in 0..n-1 per frame of
    that split."""
    if same is None:
        return {}
    if not isinstance(same, Mapping):
        raise UserError(f"{where}: 'same_instant' must map split names to lists of frame indices, got {_shown(same)}")
    out = {}
    for name, idx in same.items():
        if name not in splits:
            raise UserError(f"{where}: 'same_instant' names split '{name}', which the dataset does not have "
                            f"(splits: {', '.join(splits)})")
        if not isinstance(idx, (list, tuple, np.ndarray)) or len(idx) != len(splits[name]):
            raise UserError(f"{where}: same_instant '{name}' must list one frame index per frame of split "
                            f"'{name}' ({len(splits[name])}), got {_shown(idx)}")
        idx = [_frame_index(i, f"{where}: same_instant '{name}'") for i in idx]
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise UserError(f"{where}: same_instant '{name}' refers to frames {bad[:5]} outside 0..{n - 1}")
        out[str(name)] = idx
    return out


def _frame_index(value, where: str) -> int:
    """A frame index: an integer (numpy's too; an integral float is accepted), never true/false or text."""
    if isinstance(value, (float, np.floating)) and float(value).is_integer():
        return int(value)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise UserError(f"{where} must hold frame indices (integers), got {_shown(value)}")
    return int(value)


def _shown(value) -> str:
    """A value for a message, cut to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_fields(values: Mapping, where: str) -> dict:
    """meta.yaml's (or NativeMeta's) name, gender, body, fps, poses and extra checked for their type and
    range; returns them normalised (name a string, fps a float or None, extra a dict). Messages name
    ``where`` (the file), the key and what was expected."""
    out = dict(values)
    name = values.get("name")
    if isinstance(name, bool) or not isinstance(name, (str, int)):  # `name: 2024` is read as an integer
        raise UserError(f"{where}: name must be a string, got {_shown(name)}")
    out["name"] = str(name)
    gender = values.get("gender")
    if gender is not None and (not isinstance(gender, str) or gender not in GENDERS):
        raise UserError(f"{where}: gender must be one of {GENDERS} or null, got {_shown(gender)}")
    body = values.get("body")
    if body is not None and (not isinstance(body, str) or not body.strip()):
        raise UserError(f"{where}: body must be a body spec (a string such as anny:female) or null, "
                        f"got {_shown(body)}")
    fps = values.get("fps")
    if fps is not None:
        number = None
        if isinstance(fps, (int, float, np.number)) and not isinstance(fps, (bool, np.bool_)):
            number = float(fps)
        elif isinstance(fps, str):  # PyYAML reads 3e1 (no dot) as a string
            try:
                number = float(fps)
            except ValueError:
                number = None
        if number is None or not np.isfinite(number) or number <= 0:
            raise UserError(f"{where}: fps must be a number > 0 (frames per second) or null, got {_shown(fps)}")
        out["fps"] = number
    poses = values.get("poses", "given")
    if not isinstance(poses, str) or poses not in POSE_SOURCES:
        raise UserError(f"{where}: poses must be one of {POSE_SOURCES}, got {_shown(poses)}")
    extra = values.get("extra")
    if extra is not None and not isinstance(extra, Mapping):
        raise UserError(f"{where}: extra must be a mapping (free-form key: value lines) or null, "
                        f"got {_shown(extra)}")
    out["extra"] = dict(extra or {})
    return out


def _positive_int(value, where: str, key: str) -> int:
    """meta.yaml's width, height or num_frames: an integer >= 1 (an integral float is accepted)."""
    number = whole_number(value, 1)
    if number is None:
        raise UserError(f"{where}: {key} must be an integer >= 1, got {_shown(value)}")
    return number


def write_native(out_dir: str | os.PathLike, meta: NativeMeta | Mapping, cameras, params,
                 images: Iterable[np.ndarray], masks: Iterable[np.ndarray], *,
                 progress: bool = True) -> Path:
    """Write a dataset in the native format to ``out_dir``, atomically (a temporary folder renamed at
    the end; an existing ``out_dir`` is replaced only on success).

    meta: NativeMeta or a dict with its fields. cameras: one Camera (all frames), a list of N Cameras,
    or {"K": [3,3]|[N,3,3], "viewmat": [4,4]|[N,4,4]}. params: mapping or object with betas [10]|[N,10],
    global_orient [N,3], body_pose [N,69], transl [N,3] (N = the frame count). images: N arrays
    [H,W,3] (uint8, or float in [0,1]); masks: N arrays [H,W] (float in [0,1], bool, or uint8 0-255).
    Both may be iterators: frames are written as they come, so a long video streams.
    An existing ``out_dir`` is replaced only if it is empty or a dataset written by this function (its
    ``.rmavatar`` marker, see :mod:`rmavatar.utils.outputs`). Returns the path written.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"cannot write a dataset to {out_dir}: it is a file")
    check_output_folder(out_dir, NATIVE_KIND, option="dataset")
    meta = _as_meta(meta)
    p = _check_params(params, "write_native")
    n = p["global_orient"].shape[0]
    if n == 0:
        raise UserError("write_native: no frames")
    K, V, cam_size = _stack_cameras(cameras, n)
    splits = _check_splits(meta.splits, n, "write_native")
    _check_same_instant(meta.same_instant, splits, n, "write_native")
    if meta.gender is not None and meta.gender not in GENDERS:
        raise UserError(f"write_native: gender must be one of {GENDERS} or None, got {meta.gender!r}")
    _check_fields({"name": meta.name, "gender": meta.gender, "body": meta.body, "fps": meta.fps,
                   "extra": meta.extra}, "write_native")

    with output_folder(out_dir, NATIVE_KIND, option="dataset") as tmp:
        size = _write_frames(tmp, images, masks, n, cam_size, f"writing {out_dir.name}", progress)
        write_tables(tmp, meta, K, V, p, size, splits, "write_native")
    return out_dir


def write_tables(folder: Path, meta: NativeMeta, K: np.ndarray, viewmat: np.ndarray, params, size: tuple[int, int],
                 splits: dict[str, list[int]], where: str) -> None:
    """A native dataset's tables in ``folder`` beside its frames (written apart, e.g. by a capture that
    encodes frames as it goes): cameras.npz (K [3,3]|[N,3,3], viewmat [4,4]|[N,4,4]), smpl.npz (``params``
    checked as :func:`write_native` checks them, ``where`` naming the caller in errors) and meta.yaml
    (frames of ``size`` (W, H), ``splits``)."""
    p = _check_params(params, where)
    n = p["global_orient"].shape[0]
    _check_same_instant(meta.same_instant, splits, n, where)
    np.savez(folder / "cameras.npz", K=np.asarray(K, np.float32), viewmat=np.asarray(viewmat, np.float32))
    np.savez(folder / "smpl.npz", **p)
    with open(folder / "meta.yaml", "w") as f:
        yaml.safe_dump(_meta_doc(meta, size, n, splits), f, sort_keys=False, default_flow_style=None, width=100)


def _next_frame(image_iter, mask_iter, i: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``i``'s image and mask from their iterators, as uint8; returns (image, mask).
    Raises UserError when either iterator ran out before ``n`` frames."""
    try:
        image = next(image_iter)
    except StopIteration:
        raise UserError(f"write_native: {i} images for {n} frames of SMPL parameters") from None
    try:
        mask = next(mask_iter)
    except StopIteration:
        raise UserError(f"write_native: {i} masks for {n} frames of SMPL parameters") from None
    return to_uint8(image, f"image {i}"), to_uint8(mask, f"mask {i}")


def _check_frame(image: np.ndarray, mask: np.ndarray, i: int, size, cam_size) -> tuple[int, int]:
    """Check frame ``i``'s shapes against the cameras' size and image 0's ``size`` (None at frame 0);
    returns the dataset's (width, height). Raises UserError on a mismatch."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise UserError(f"write_native: image {i} must be [H,W,3], got {list(image.shape)}")
    if size is None:
        size = (image.shape[1], image.shape[0])
        if cam_size is not None and cam_size != size:
            raise UserError(f"write_native: cameras are {cam_size[0]}x{cam_size[1]}, "
                            f"images {size[0]}x{size[1]}")
    if (image.shape[1], image.shape[0]) != size:
        raise UserError(f"write_native: image {i} is {image.shape[1]}x{image.shape[0]}, "
                        f"image 0 is {size[0]}x{size[1]}")
    if mask.shape != image.shape[:2]:
        raise UserError(f"write_native: mask {i} is {list(mask.shape)}, its image "
                        f"{list(image.shape[:2])}")
    return size


def _write_frames(tmp: Path, images: Iterable[np.ndarray], masks: Iterable[np.ndarray], n: int, cam_size,
                  desc: str, progress: bool) -> tuple[int, int]:
    """Write ``n`` images and masks as PNGs to ``tmp/images`` and ``tmp/masks`` as they come; returns the
    frames' (width, height). Raises UserError on too few or too many frames or mismatched shapes."""
    from tqdm import tqdm

    (tmp / "images").mkdir()
    (tmp / "masks").mkdir()
    size = None
    image_iter, mask_iter = iter(images), iter(masks)
    bar = tqdm(total=n, desc=desc, unit="frame", disable=not progress)
    for i in range(n):
        image, mask = _next_frame(image_iter, mask_iter, i, n)
        size = _check_frame(image, mask, i, size, cam_size)
        write_png(tmp / "images" / f"{i:05d}.png", image)
        write_png(tmp / "masks" / f"{i:05d}.png", mask)
        bar.update(1)
    bar.close()
    for what, it in (("images", image_iter), ("masks", mask_iter)):
        if next(it, None) is not None:
            raise UserError(f"write_native: more {what} than the {n} frames of SMPL parameters")
    return size


def _meta_doc(meta: NativeMeta, size: tuple[int, int], n: int, splits: dict[str, list[int]]) -> dict:
    """The contents of ``meta.yaml``, in file order; returns them as a plain dict."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "name": str(meta.name),
        "gender": meta.gender,
        "body": meta.body,
        "fps": float(meta.fps) if meta.fps is not None else None,
        "width": int(size[0]),
        "height": int(size[1]),
        "num_frames": int(n),
        "splits": splits,
        "poses": POSE_SOURCES[bool(meta.poses_estimated)],
        **({"same_instant": _plain(meta.same_instant)} if meta.same_instant else {}),
        "extra": _plain(meta.extra),
    }


def _plain(value):
    """numpy scalars/arrays inside ``extra`` -> plain YAML-safe Python values."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


META_KEYS = ("format", "version", "name", "gender", "body", "fps", "width", "height", "num_frames", "splits",
             "poses", "same_instant", "extra")
REQUIRED_KEYS = ("name", "width", "height", "num_frames", "splits")


def read_meta(root: Path) -> dict:
    """``root/meta.yaml``, checked against the schema (module docstring, docs/data.md) before anything
    else is read: every key's type and range, frame indices in 0..num_frames-1 and each at most once per
    split. Returns its keys normalised (width, height, num_frames ints; fps a float or None; name a
    string; splits {name: [int]}; poses and extra filled in). Every problem is a UserError naming the
    file, the key and what was expected."""
    from rmavatar.utils.files import read_yaml_file

    path = root / "meta.yaml"
    doc = read_yaml_file(path, "dataset file", mapping=False)
    if not isinstance(doc, dict):
        raise UserError(f"{path} must hold a mapping (key: value lines), got {_shown(doc)}")
    if doc.get("format") != FORMAT:
        raise UserError(f"{path}: 'format' must be {FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != VERSION:
        raise UserError(f"{path}: format version {doc.get('version')!r} is not supported (this "
                        f"rmavatar reads version {VERSION})")
    unknown = sorted(str(k) for k in doc if k not in META_KEYS)
    if unknown:
        raise UserError(f"{path}: unknown key(s) {', '.join(unknown)} (known: {', '.join(META_KEYS)}; "
                        f"free-form notes go under extra:)")
    for key in REQUIRED_KEYS:
        if key not in doc:
            raise UserError(f"{path} is missing '{key}'")
    doc = _check_fields(doc, str(path))
    for key in ("width", "height", "num_frames"):
        doc[key] = _positive_int(doc[key], str(path), key)
    doc["splits"] = _check_splits(doc["splits"], doc["num_frames"], str(path))
    doc["same_instant"] = _check_same_instant(doc.get("same_instant"), doc["splits"], doc["num_frames"], str(path))
    doc.setdefault("poses", "given")
    return doc


def open_native(root: Path, size=None, cache_mb: float = 1024.0, **options) -> Dataset:
    """Read a native-format folder (layout in the module docstring). Frames without an image or a
    mask, arrays whose frame count differs from meta.yaml's, and missing keys are errors naming the file."""
    if options:
        raise UserError(f"the native format takes no options, got {sorted(options)}")
    root = Path(root)
    doc = read_meta(root)
    n = doc["num_frames"]
    width, height = doc["width"], doc["height"]
    splits = doc["splits"]
    cam = load_npz(root / "cameras.npz", ("K", "viewmat"))
    try:
        K, V, _ = _stack_cameras({"K": cam["K"], "viewmat": cam["viewmat"]}, n)
    except UserError as exc:
        raise UserError(f"{root / 'cameras.npz'}: {exc}") from None
    p = _check_params(load_npz(root / "smpl.npz", PARAM_KEYS), str(root / "smpl.npz"))
    if p["global_orient"].shape[0] != n:
        raise UserError(f"{root / 'smpl.npz'} has {p['global_orient'].shape[0]} frames, "
                        f"meta.yaml says {n}")
    images = _listing(root / "images")
    masks = _listing(root / "masks")
    used = sorted({i for idx in splits.values() for i in idx})
    for i in used:
        name = f"{i:05d}.png"
        if name not in images:
            raise UserError(f"frame {i} has no image: {root / 'images' / name} does not exist")
        if name not in masks:
            raise UserError(f"frame {i} has no mask: {root / 'masks' / name} does not exist")
    extra_images = len(images) - n
    if extra_images > 0:
        warn(f"{root / 'images'} holds {len(images)} files for {n} frames; the extra ones are ignored")
    betas = p["betas"] if p["betas"].ndim == 2 else np.broadcast_to(p["betas"], (n, 10))
    Ks = K if K.ndim == 3 else np.broadcast_to(K, (n, 3, 3))
    Vs = V if V.ndim == 3 else np.broadcast_to(V, (n, 4, 4))
    cameras: dict[int, Camera] = {}
    records = {}
    for split, idx in splits.items():
        recs = []
        for i in idx:
            if i not in cameras:
                cameras[i] = Camera(Ks[i], Vs[i], width, height)
            recs.append(FrameRecord(
                index=i, image=root / "images" / f"{i:05d}.png", masks=(root / "masks" / f"{i:05d}.png",),
                camera=cameras[i], betas=np.array(betas[i]), global_orient=p["global_orient"][i],
                body_pose=p["body_pose"][i], transl=p["transl"][i],
                **{k: p[k][i] for k in HAND_KEYS if k in p}))
        records[split] = recs
    return Dataset(kind="native", name=doc["name"], root=root, records=records,
                   source_size=(width, height), gender=doc.get("gender"), body=doc.get("body"),
                   fps=doc.get("fps"), size=size, cache_mb=cache_mb,
                   poses_estimated=doc["poses"] == "estimated", body_offsets=p.get("body_offsets"),
                   same_instant=doc["same_instant"])


def _listing(folder: Path) -> set[str]:
    if not folder.is_dir():
        raise UserError(f"folder {folder} does not exist")
    return set(os.listdir(folder))




def export_native(ds: Dataset, out_dir: str | os.PathLike, *, name: str | None = None,
                  progress: bool = True) -> Path:
    """Write any Dataset (PeopleSnapshot, ZJU, native) in the native format, at its current image size.

    Every (split, frame) becomes a native frame; a source frame that several splits share with the same
    parameters and camera is written once. ZJU's Rh/Th conversion is baked in (with the body the
    dataset was opened with). Returns the path written.
    """
    import itertools

    entries: list[tuple[str, int]] = []
    seen: dict[tuple, int] = {}
    splits: dict[str, list[int]] = {}
    for split in ds.splits:
        splits[split] = []
        listed: set[int] = set()
        for i in range(ds.num_frames(split)):
            rec = ds._record(split, i)
            key = (str(rec.image), rec.betas.tobytes(), rec.global_orient.tobytes(), rec.body_pose.tobytes(),
                   rec.transl.tobytes(), rec.camera.K.tobytes(), rec.camera.viewmat.tobytes(),
                   None if rec.hand_pose is None else rec.hand_pose.tobytes())
            if key not in seen:
                seen[key] = len(entries)
                entries.append((split, i))
            if seen[key] not in listed:  # a frame the source split lists twice is one native frame, once
                listed.add(seen[key])
                splits[split].append(seen[key])
    cameras = [ds.camera(s, i) for s, i in entries]
    recs = [ds._record(s, i) for s, i in entries]
    params = {**{key: np.stack([getattr(r, key) for r in recs]) for key in PARAM_KEYS}, **hand_columns(recs)}
    if ds.body_offsets is not None:
        params["body_offsets"] = ds.body_offsets
    frames_a, frames_b = itertools.tee(ds.frame(s, i) for s, i in entries)
    meta = NativeMeta(name=name or ds.name, splits=splits, fps=ds.fps if ds.fps is not None else 30.0,
                      gender=ds.gender, body=ds.body, poses_estimated=ds.poses_estimated,
                      extra={"source": {"kind": ds.kind, "path": str(ds.root), "frames": [
                          {"split": s, "index": r.index} for (s, _), r in zip(entries, recs)]}})
    return write_native(out_dir, meta, cameras, params, (f.image for f in frames_a),
                        (f.mask for f in frames_b), progress=progress)


__all__ = ["NativeMeta", "write_native", "export_native", "open_native", "read_meta", "FORMAT", "VERSION"]
