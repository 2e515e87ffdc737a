"""Checks of a dataset before any long work: cameras, SMPL-format parameters, and every frame's files.

``check_cameras`` and ``check_params`` read no pixels (milliseconds); ``check_files`` opens every image
(header and PNG checksums, not the pixels) and reads every mask, so a 0-byte PNG, a missized frame, a
mask saved 0/1 instead of 0-255 or a split whose masks are all empty is found before training starts,
not an hour into it. ``rmavatar inspect --check`` runs them all.
"""

from __future__ import annotations

import warnings
from typing import Iterable

import numpy as np

from rmavatar.data.dataset import Dataset
from rmavatar.utils import UserError


def check_cameras(ds: Dataset, splits: Iterable[str] | None = None) -> None:
    """UserError for a camera that no image can be rendered with: non-finite K or view matrix, focal lengths
    not positive, principal point outside the image, a rotation that is not one."""
    seen: set[int] = set()
    for split in splits or ds.splits:
        for rec in ds._record_list(split):
            cam = rec.camera
            if id(cam) in seen:
                continue
            seen.add(id(cam))
            K, V = cam.K.astype(np.float64), cam.viewmat.astype(np.float64)
            where = f"dataset {ds.root}: camera of frame {rec.index} ({split})"
            if not (np.isfinite(K).all() and np.isfinite(V).all()):
                raise UserError(f"{where} has non-finite values (K {K.tolist()})")
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                raise UserError(f"{where}: focal lengths must be positive, got fx {K[0, 0]:g}, fy {K[1, 1]:g}")
            if not (0 <= K[0, 2] <= cam.width and 0 <= K[1, 2] <= cam.height):
                raise UserError(f"{where}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the "
                                f"{cam.width}x{cam.height} image")
            R = V[:3, :3]
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
                raise UserError(f"{where}: the view matrix's 3x3 block is not a rotation")


def check_params(ds: Dataset, splits: Iterable[str] | None = None) -> None:
    """UserError for non-finite poses, translations or shapes."""
    for split in splits or ds.splits:
        p = ds.params(split)
        for key in ("betas", "global_orient", "body_pose", "transl"):
            bad = ~np.isfinite(p[key]).reshape(len(p[key]), -1).all(-1)
            if bad.any():
                raise UserError(f"dataset {ds.root}: {key} of frame {int(p['index'][bad.argmax()])} ({split}) "
                                "is not finite")


def check_files(ds: Dataset, splits: Iterable[str] | None = None, progress: bool = False) -> dict:
    """Open every image and read every mask of ``splits`` (default all); UserError naming the first file
    that is unreadable or of the wrong size, and a split whose masks are all empty. Returns
    {"images": n, "masks": n}."""
    from PIL import Image
    from tqdm import tqdm

    w, h = ds.source_size
    counts = {"images": 0, "masks": 0}
    splits = list(splits or ds.splits)
    total = sum(ds.num_frames(s) for s in splits)
    with tqdm(total=total, desc="checking frames", unit="frame", disable=not progress) as bar:
        for split in splits:
            empty = True
            for rec in ds._record_list(split):
                try:
                    with Image.open(rec.image) as im:
                        size = im.size
                        im.verify()  # chunk checksums: finds truncated and corrupt files without decoding
                except FileNotFoundError:
                    raise UserError(f"image {rec.image} does not exist") from None
                except Exception as exc:  # PIL raises many types for a corrupt or non-image file
                    raise UserError(f"cannot read image {rec.image}: {exc or type(exc).__name__}") from None
                if size != (w, h):
                    raise UserError(f"image {rec.image} is {size[0]}x{size[1]}, the dataset's cameras are {w}x{h}")
                counts["images"] += 1
                for path in rec.masks:
                    mask = ds._mask_reader(path)
                    if mask.shape != (h, w):
                        raise UserError(f"mask {path} is {mask.shape[1]}x{mask.shape[0]}, its image is {w}x{h}")
                    empty = empty and not mask.any()
                    counts["masks"] += 1
                bar.update(1)
            if empty and ds.num_frames(split):
                raise UserError(f"dataset {ds.root}: every mask of split '{split}' is empty (all background); "
                                "masks must be white (255) where the person is")
    return counts


def check_dataset(ds: Dataset, splits: Iterable[str] | None = None, progress: bool = False) -> dict:
    """Every check above; returns check_files' counts. Warnings (e.g. 0/1 masks rescaled) are shown once."""
    splits = list(splits or ds.splits)
    check_cameras(ds, splits)
    check_params(ds, splits)
    with warnings.catch_warnings():
        warnings.simplefilter("once")
        return check_files(ds, splits, progress)
