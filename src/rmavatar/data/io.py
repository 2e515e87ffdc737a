"""Reading and writing images and masks, and resampling them, with errors that name the file."""

from __future__ import annotations

import contextlib
import importlib
import pickle
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from rmavatar.utils import UserError
from rmavatar.utils.errors import load_error


def read_image(path: Path) -> np.ndarray:
    """An RGB image file -> [H,W,3] float32 in [0,1] (8- or 16-bit; grey and alpha are dropped to RGB)."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float32) / 65535.0
                return np.repeat(arr[..., None], 3, axis=2)
            arr = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise UserError(f"image {path} does not exist") from None
    except Exception as exc:  # PIL raises many types for a corrupt or non-image file
        raise UserError(f"cannot read image {path}: {exc}") from None
    return arr


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays, scalars and plain containers only: any other class (the way a hostile file
    runs code) is refused."""

    def find_class(self, module: str, name: str):
        if module in ("numpy", "numpy.core.multiarray", "numpy._core.multiarray") and \
                name in ("ndarray", "dtype", "_reconstruct", "scalar"):
            for where in (module, "numpy._core.multiarray", "numpy.core.multiarray", "numpy"):
                with contextlib.suppress(ImportError, AttributeError):
                    return getattr(importlib.import_module(where), name)
        if module == "builtins" and name in ("dict", "list", "tuple", "set", "frozenset", "slice", "complex"):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load class {module}.{name}: not an array file's")


def load_object_npy(path: Path):
    """A ``.npy`` file holding a pickled object array (e.g. ZJU-MoCap's dicts) -> the array's single item
    (or the array), unpickled with numpy classes only; UserError naming the file otherwise."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            _, _, dtype = read(fh)
            if not dtype.hasobject:
                fh.seek(0)
                return np.load(fh, allow_pickle=False)
            arr = _ArrayUnpickler(fh, encoding="latin1").load()
    except FileNotFoundError:
        raise UserError(f"{path} does not exist") from None
    except pickle.UnpicklingError as exc:
        raise UserError(f"cannot read {path}: {exc}") from None
    except Exception as exc:
        raise UserError(f"cannot read {path}: {load_error(exc)}") from None
    return arr.item() if isinstance(arr, np.ndarray) and arr.shape == () else arr


def _read_raw(path: Path) -> np.ndarray:
    """A mask file's values [H,W] as stored (palette images give their indices, not colours)."""
    try:
        if path.suffix.lower() == ".npy":
            arr = np.load(path, allow_pickle=False)
        else:
            with Image.open(path) as im:
                im.load()
                arr = np.asarray(im)
    except FileNotFoundError:
        raise UserError(f"mask {path} does not exist") from None
    except Exception as exc:
        raise UserError(f"cannot read mask {path}: {load_error(exc)}") from None
    if arr.ndim == 3 and arr.shape[2] in (2, 4) and np.ptp(arr[..., -1]) > 0:
        arr = arr[..., -1]  # a cut-out saved with transparency: the alpha is the mask
    elif arr.ndim == 3:
        arr = arr[..., 0]  # grey stored as RGB(A)
    if arr.ndim != 2:
        raise UserError(f"mask {path} must be a 2-D array or a grey image, got shape {arr.shape}")
    return arr


def read_mask(path: Path) -> np.ndarray:
    """A soft mask file -> [H,W] float32 in [0,1].

    ``.npy``: bool, uint8 0/1 (PeopleSnapshot), uint8 0-255, or float in [0,1].
    Images (``.png``, ``.jpg``): 8-bit 0-255 soft coverage (or 16-bit 0-65535).
    """
    arr = _read_raw(path)
    if arr.dtype == bool:
        return arr.astype(np.float32)
    if np.issubdtype(arr.dtype, np.floating):
        out = arr.astype(np.float32)
        if not np.isfinite(out).all() or out.min() < 0 or out.max() > 1:
            raise UserError(f"mask {path}: float masks must lie in [0,1]")
        return out
    if path.suffix.lower() == ".npy" and arr.max(initial=0) <= 1:
        return arr.astype(np.float32)
    if arr.dtype == np.uint16 or arr.max(initial=0) > 255:
        return arr.astype(np.float32) / 65535.0
    if arr.max(initial=0) == 1:
        # Saved as 0/1 instead of 0-255: read as 0-255 every target would be background.
        if path.parent not in _WARNED_01:
            _WARNED_01.add(path.parent)
            warnings.warn(f"masks in {path.parent} hold only 0 and 1 (e.g. {path.name}): read as 0/1 masks "
                          "(save them as 0-255 to silence this)", UserWarning, stacklevel=2)
        return arr.astype(np.float32)
    return arr.astype(np.float32) / 255.0


_WARNED_01: set = set()


def read_binary_mask(path: Path) -> np.ndarray:
    """A label mask (ZJU's mask/ and mask_cihp/: any non-zero value is the person) -> [H,W] float32 0/1."""
    return (_read_raw(path) != 0).astype(np.float32)


def resample(arr: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample [H,W] or [H,W,C] float32 to ``width x height``.

    Area averaging (box filter) when shrinking, bilinear when enlarging: both treat pixels as squares
    with centres at +0.5, matching `Camera.resized`.
    """
    h, w = arr.shape[:2]
    if (w, h) == (width, height):
        return arr
    method = Image.Resampling.BOX if width <= w and height <= h else Image.Resampling.BILINEAR
    chans = [arr] if arr.ndim == 2 else [arr[..., c] for c in range(arr.shape[2])]
    out = [np.asarray(Image.fromarray(np.ascontiguousarray(c, dtype=np.float32), mode="F").resize(
        (width, height), method), dtype=np.float32) for c in chans]
    res = out[0] if arr.ndim == 2 else np.stack(out, axis=2)
    return np.clip(res, 0.0, 1.0)


def to_uint8(arr: np.ndarray, what: str) -> np.ndarray:
    """uint8 as is, bool as 0/255, float in [0,1] scaled to 0-255 (rounded)."""
    arr = np.asarray(arr)
    if arr.dtype == np.uint8:
        return arr
    if arr.dtype == bool:
        return arr.astype(np.uint8) * 255
    if np.issubdtype(arr.dtype, np.floating):
        if not np.isfinite(arr).all():
            raise UserError(f"{what} holds NaN or Inf")
        return np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
    raise UserError(f"{what} must be uint8, bool or float in [0,1], got {arr.dtype}")


def write_png(path: Path, arr: np.ndarray) -> None:
    """Write [H,W] or [H,W,3] uint8 as PNG (fast compression: datasets are large)."""
    Image.fromarray(arr).save(path, format="PNG", compress_level=3)


def load_npz(path: Path, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """The arrays of an .npz file (no pickles); UserError naming the file when it is missing, unreadable or lacks ``keys``."""
    if not path.is_file():
        raise UserError(f"{path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise UserError(f"cannot read {path}: {load_error(exc)}") from None
    missing = [k for k in keys if k not in data]
    if missing:
        raise UserError(f"{path} is missing {missing} (it has {sorted(data)})")
    return data
