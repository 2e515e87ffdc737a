"""PeopleSnapshot as preprocessed by InstantAvatar (the layout the peers read).

``<subject>/``: cameras.npz (intrinsic [3,3], extrinsic [4,4] world-to-camera, height, width),
images/image_%04d.png, masks/mask_%04d.npy (uint8 0/1) or mask_%04d.png (0-255 soft),
poses/anim_nerf_{train,val,test}.npz (betas [1,10], global_orient [n,3], body_pose [n,69], transl [n,3]:
each split's own betas apply to its frames) and/or poses.npz (betas, thetas [N,72], transl [N,3]: used
for a split that has no anim_nerf file). SMPL parameters are in the camera frame.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from rmavatar.data.dataset import Dataset, FrameRecord, warn
from rmavatar.data.io import load_npz
from rmavatar.render.camera import Camera
from rmavatar.utils import UserError
from rmavatar.utils.config import whole_number
from rmavatar.utils.files import read_yaml_file

# subject -> (gender, {split: (start, end inclusive, step)}), the InstantAvatar / peers' standard splits.
SUBJECTS: dict[str, tuple[str, dict[str, tuple[int, int, int]]]] = {
    "male-3-casual": ("male", {"train": (0, 455, 4), "val": (456, 456, 1), "test": (456, 675, 4)}),
    "male-4-casual": ("male", {"train": (0, 659, 6), "val": (660, 660, 1), "test": (660, 872, 6)}),
    "female-3-casual": ("female", {"train": (0, 445, 4), "val": (446, 446, 1), "test": (446, 647, 4)}),
    "female-4-casual": ("female", {"train": (0, 335, 4), "val": (335, 335, 1), "test": (335, 523, 4)}),
}
SPLITS = ("train", "val", "test")
FPS = 30.0


def split_frames(start: int, end: int, step: int) -> list[int]:
    """Frames start..end inclusive every step."""
    return list(range(start, end + 1, step))


def _gender_from_name(name: str) -> str:
    low = name.lower()
    if "female" in low:
        return "female"
    if "male" in low:
        return "male"
    return "neutral"


def _read_splits_file(path: Path) -> dict[str, list[int]]:
    """splits.yaml: {split: {start, end, step}} (end inclusive) or {split: [frame, ...]}."""
    doc = read_yaml_file(path, "splits file", mapping=False)
    if not isinstance(doc, dict) or not doc:
        raise UserError(f"{path} must map split names to {{start, end, step}} or to frame lists")
    out = {}
    for split, value in doc.items():
        if isinstance(value, dict) and {"start", "end"} <= set(value):
            unknown = sorted(map(str, set(value) - {"start", "end", "step"}))
            if unknown:
                raise UserError(f"{path}: split '{split}' has unknown key(s) {', '.join(unknown)} "
                                f"(known: start, end, step)")
            start, end = (_frame_number(value[k], path, f"{split}.{k}") for k in ("start", "end"))
            step = _frame_number(value.get("step", 1), path, f"{split}.step")
            if step < 1:
                raise UserError(f"{path}: {split}.step: expected an integer >= 1, got {step!r}")
            out[str(split)] = split_frames(start, end, step)
        elif isinstance(value, list):
            out[str(split)] = [_frame_number(v, path, f"split '{split}'") for v in value]
        else:
            raise UserError(f"{path}: split '{split}' must be {{start, end, step}} or a list of frames")
    return out


def _frame_number(value, path: Path, key: str) -> int:
    """A frame number from splits.yaml: an integer >= 0 (an integral float is accepted)."""
    number = whole_number(value, 0)
    if number is None:
        raise UserError(f"{path}: {key}: expected a frame number (an integer >= 0), got {value!r}")
    return number


def _split_params(root: Path, split: str, frames: list[int]) -> dict[str, np.ndarray]:
    """The SMPL parameters of a split's frames: its anim_nerf file, else rows of poses.npz."""
    path = root / "poses" / f"anim_nerf_{split}.npz"
    if path.is_file():
        z = load_npz(path, ("betas", "global_orient", "body_pose", "transl"))
        n = len(frames)
        for key, width in (("global_orient", 3), ("body_pose", 69), ("transl", 3)):
            if z[key].ndim != 2 or z[key].shape[1] != width:
                raise UserError(f"{path}: '{key}' must be [n,{width}], got {list(z[key].shape)}")
            if z[key].shape[0] != n:
                raise UserError(f"{path} has {z[key].shape[0]} poses ('{key}') for the {n} frames of "
                                f"split '{split}' (frames {frames[0]}..{frames[-1]})")
        betas = np.asarray(z["betas"], np.float32).reshape(-1, z["betas"].shape[-1])
        if betas.shape[-1] < 10 or betas.shape[0] not in (1, n):
            raise UserError(f"{path}: 'betas' must be [1,10] or [n,10], got {list(z['betas'].shape)}")
        return {"betas": np.broadcast_to(betas[:, :10], (n, 10)),
                "global_orient": z["global_orient"], "body_pose": z["body_pose"], "transl": z["transl"]}
    path = root / "poses.npz"
    if not path.is_file():
        raise UserError(f"split '{split}' has no poses: neither {root / 'poses' / f'anim_nerf_{split}.npz'} "
                        f"nor {path} exists")
    z = load_npz(path, ("betas", "thetas", "transl"))
    total = z["thetas"].shape[0]
    if z["thetas"].ndim != 2 or z["thetas"].shape[1] != 72 or z["transl"].shape != (total, 3):
        raise UserError(f"{path}: thetas must be [N,72] and transl [N,3], got "
                        f"{list(z['thetas'].shape)} and {list(z['transl'].shape)}")
    if frames[-1] >= total:
        raise UserError(f"{path} has {total} poses, split '{split}' needs frame {frames[-1]}")
    betas = np.asarray(z["betas"], np.float32)
    betas = betas[frames, :10] if betas.ndim == 2 and betas.shape[0] == total and total > 1 else \
        np.broadcast_to(betas.reshape(-1)[:10], (len(frames), 10))
    thetas = z["thetas"][frames]
    return {"betas": betas, "global_orient": thetas[:, :3], "body_pose": thetas[:, 3:],
            "transl": z["transl"][frames]}


def _standard_frames(root: Path, split: str, rng: tuple[int, int, int]) -> list[int]:
    """A standard split's frames, end inclusive as the standard table (docs/data.md) gives them; when the split's anim_nerf
    file has exactly the count of the end-exclusive reading (Python slicing, as in InstantAvatar's
    loader), that reading is taken, with a warning."""
    frames = split_frames(*rng)
    path = root / "poses" / f"anim_nerf_{split}.npz"
    if path.is_file():
        n = load_npz(path, ("global_orient",))["global_orient"].shape[0]
        exclusive = list(range(*rng))
        if n != len(frames) and n == len(exclusive) and exclusive:
            warn(f"{path} has {n} poses: taking split '{split}' as frames {rng[0]}..{rng[1]} "
                 f"end-exclusive, step {rng[2]}")
            return exclusive
    return frames


def read_cameras_npz(path: Path) -> Camera:
    z = load_npz(path, ("intrinsic", "extrinsic", "height", "width"))
    K, E = np.asarray(z["intrinsic"]), np.asarray(z["extrinsic"])
    if K.shape != (3, 3) or E.shape not in ((4, 4), (3, 4)):
        raise UserError(f"{path}: intrinsic must be [3,3] and extrinsic [4,4], got {list(K.shape)} "
                        f"and {list(E.shape)}")
    if E.shape == (3, 4):
        E = np.vstack([E, [0, 0, 0, 1]])
    return Camera(K, E, int(np.asarray(z["width"]).reshape(-1)[0]), int(np.asarray(z["height"]).reshape(-1)[0]))


def open_peoplesnapshot(root: Path, size=None, cache_mb: float = 1024.0, **options) -> Dataset:
    """Read one PeopleSnapshot subject folder (layout in the module docstring).

    Splits: the standard ones for the four subjects in `SUBJECTS`; for another folder name, a
    ``splits.yaml`` in the folder if present, else one split per anim_nerf file whose pose count equals
    the number of images (all frames), else every frame as ``train`` from poses.npz.
    """
    if options:
        raise UserError(f"PeopleSnapshot takes no options, got {sorted(options)}")
    root = Path(root)
    name = root.name
    camera = read_cameras_npz(root / "cameras.npz")
    images = _numbered(root / "images", "image")
    masks_dir = root / "masks"
    masks = _numbered(masks_dir, "mask", suffixes=(".npy", ".png"))

    if name in SUBJECTS:
        gender, table = SUBJECTS[name]
        splits = {s: _standard_frames(root, s, r) for s, r in table.items()}
    else:
        gender = _gender_from_name(name)
        if (root / "splits.yaml").is_file():
            splits = _read_splits_file(root / "splits.yaml")
        else:
            splits = {}
            all_frames = sorted(images)
            for split in SPLITS:
                path = root / "poses" / f"anim_nerf_{split}.npz"
                if path.is_file():
                    n = load_npz(path, ("global_orient",))["global_orient"].shape[0]
                    if n != len(all_frames):
                        raise UserError(
                            f"{path} has {n} poses and {root / 'images'} {len(all_frames)} images; "
                            f"'{name}' is not one of the standard subjects ({', '.join(SUBJECTS)}), so "
                            f"say which frames each split uses in {root / 'splits.yaml'} "
                            f"(e.g. train: {{start: 0, end: 455, step: 4}})")
                    splits[split] = all_frames
            if not splits:
                warn(f"{name}: not a standard subject and no anim_nerf files; every frame is 'train'")
                splits = {"train": all_frames}

    records = {}
    for split, frames in splits.items():
        if not frames:
            continue
        for i in frames:
            if i not in images:
                raise UserError(f"frame {i} of split '{split}' has no image: "
                                f"{root / 'images' / f'image_{i:04d}.png'} does not exist")
            if i not in masks:
                raise UserError(f"frame {i} of split '{split}' has no mask: neither "
                                f"{masks_dir / f'mask_{i:04d}.npy'} nor .png exists")
        p = _split_params(root, split, frames)
        records[split] = [
            FrameRecord(index=i, image=images[i], masks=(masks[i],), camera=camera,
                        betas=np.array(p["betas"][k], np.float32),
                        global_orient=np.array(p["global_orient"][k], np.float32),
                        body_pose=np.array(p["body_pose"][k], np.float32),
                        transl=np.array(p["transl"][k], np.float32))
            for k, i in enumerate(frames)]
    return Dataset(kind="peoplesnapshot", name=name, root=root, records=records,
                   source_size=(camera.width, camera.height), gender=gender, fps=FPS, size=size,
                   cache_mb=cache_mb)


def _numbered(folder: Path, prefix: str, suffixes=(".png",)) -> dict[int, Path]:
    """{frame number: file} for files named PREFIX_NNNN.SUFFIX (the first suffix wins on a tie)."""
    if not folder.is_dir():
        raise UserError(f"folder {folder} does not exist")
    pattern = re.compile(rf"{prefix}_(\d+)(\.[A-Za-z]+)$")
    out: dict[int, Path] = {}
    rank: dict[int, int] = {}
    for entry in os.listdir(folder):
        m = pattern.match(entry)
        if not m or m.group(2).lower() not in suffixes:
            continue
        i, r = int(m.group(1)), suffixes.index(m.group(2).lower())
        if i not in out or r < rank[i]:
            out[i], rank[i] = folder / entry, r
    return out
