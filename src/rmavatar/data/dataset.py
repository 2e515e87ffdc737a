"""The dataset object every source reader returns.

A dataset keeps everything but the pixels in memory (cameras and SMPL-format parameters per frame);
images and masks are read on first use, resized, and kept in a least-recently-used cache bounded in bytes.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from rmavatar.data.frame import Frame
from rmavatar.data.io import read_image, read_mask, resample
from rmavatar.render.camera import Camera
from rmavatar.utils import UserError

SPLIT_ORDER = ("train", "val", "test", "novel_pose")


@dataclass
class FrameRecord:
    """What a dataset knows about one frame before its pixels are read.

    index: the frame's number in the source; image: its image file; masks: one or more mask files
    (several are united: ZJU's mask/ and mask_cihp/); camera at the source resolution;
    betas [10], global_orient [3], body_pose [69], transl [3] float32; hand_pose [90] float32 (MANO
    order, left then right hand) and hand_found [2] bool (which hands a capture saw) where the source has
    finger poses, else None.
    """

    index: int
    image: Path
    masks: tuple[Path, ...]
    camera: Camera
    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    hand_pose: np.ndarray | None = None
    hand_found: np.ndarray | None = None


def hand_columns(recs: list[FrameRecord]) -> dict[str, np.ndarray]:
    """The records' finger poses stacked: hand_pose [n,90] and hand_found [n,2], each where every record
    has it."""
    return {key: np.stack([getattr(r, key) for r in recs]) for key in ("hand_pose", "hand_found")
            if all(getattr(r, key) is not None for r in recs)}


def target_size(width: int, height: int, size) -> tuple[int, int]:
    """``size``: None (keep), an int (the longer side, aspect kept) or (width, height)."""
    if size is None:
        return width, height
    if isinstance(size, (int, np.integer)):
        if size <= 0:
            raise UserError(f"size must be positive, got {size}")
        scale = size / max(width, height)
        return max(1, round(width * scale)), max(1, round(height * scale))
    w, h = (int(v) for v in size)
    if w <= 0 or h <= 0:
        raise UserError(f"size must be positive, got {size}")
    return w, h


class Dataset:
    """Frames per split, loaded lazily, resized on load.

    Attributes: kind ("native", "peoplesnapshot", "zju"), name, gender ("male"/"female"/"neutral"/None),
    body (a body preset such as "anny:female" or None), fps (None where unknown), root (the folder),
    poses_estimated (True when the poses were estimated from the video alone, by ``rmavatar capture``),
    body_offsets ([V] float32 metres along the Anny body's rest normals: a shape fitted to the person by
    ``rmavatar capture``; None: the preset's shape), same_instant (split -> for each of its frames, the
    source index of the frame of the same instant taken by the main camera: a calibrated second camera's
    split; empty for most datasets),
    splits (split -> list of source frame indices), source_size and image_size ((width, height) before
    and after resizing).
    ``frame(split, i)`` takes the position ``i`` in the split (0 <= i < num_frames(split)); the returned
    Frame's ``index`` is the source frame number.
    """

    def __init__(self, *, kind: str, name: str, root: Path, records: dict[str, list[FrameRecord]],
                 source_size: tuple[int, int], gender: str | None = None, body: str | None = None,
                 fps: float | None = None, size=None, cache_mb: float = 1024.0,
                 mask_reader: Callable[[Path], np.ndarray] = read_mask, poses_estimated: bool = False,
                 body_offsets: np.ndarray | None = None, same_instant: dict[str, list[int]] | None = None):
        self.kind = kind
        self.same_instant = dict(same_instant or {})
        self.body_offsets = None if body_offsets is None else np.asarray(body_offsets, np.float32)
        self.poses_estimated = bool(poses_estimated)
        self.name = name
        self.root = Path(root)
        self.gender = gender
        self.body = body
        self.fps = fps
        self._records = {s: records[s] for s in sorted(records, key=_split_key) if records[s]}
        self.splits = {s: [r.index for r in recs] for s, recs in self._records.items()}
        self.source_size = (int(source_size[0]), int(source_size[1]))
        self.image_size = target_size(*self.source_size, size)
        self._mask_reader = mask_reader
        self._cache: OrderedDict[str, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._cache_bytes = 0
        self._cache_limit = int(cache_mb * 2**20)

    def __repr__(self) -> str:
        counts = ", ".join(f"{s}={len(v)}" for s, v in self.splits.items())
        w, h = self.image_size
        return f"<{type(self).__name__} {self.kind}:{self.name} {w}x{h} {counts}>"

    def reserve_cache(self, mb: float) -> None:
        """Let the decoded-image cache hold up to ``mb`` MiB (it is never made smaller)."""
        self._cache_limit = max(self._cache_limit, int(mb * 2**20))

    def num_frames(self, split: str) -> int:
        return len(self._record_list(split))

    def camera(self, split: str, i: int) -> Camera:
        """The camera of frame ``i`` of ``split`` at the output image size (no pixels are read)."""
        return self._record(split, i).camera.resized(*self.image_size)

    def body_model(self, spec: str | None = None, gender: str | None = None):
        """The body model for this dataset's poses: ``spec`` (default: the dataset's body, else Anny) of
        ``gender`` (default: the dataset's), with the dataset's body offsets where ``spec`` is the body
        they were fitted on (a note says so where they are left out)."""
        from rmavatar.body import load_body_model

        spec = spec or self.body or "anny"
        offsets = self.body_offsets
        if offsets is not None and spec != self.body:
            print(f"note: {self.root}'s body offsets (a shape fitted to the person) are for {self.body}, not "
                  f"{spec}: using {spec}'s own shape", flush=True)
            offsets = None
        return load_body_model(spec, gender=gender or self.gender, offsets=offsets)

    def params(self, split: str) -> dict[str, np.ndarray]:
        """The split's SMPL-format parameters stacked: betas [n,10], global_orient [n,3],
        body_pose [n,69], transl [n,3], index [n] (source frame numbers), and hand_pose [n,90] and
        hand_found [n,2] where the dataset has finger poses."""
        recs = self._record_list(split)
        return {
            "betas": np.stack([r.betas for r in recs]),
            "global_orient": np.stack([r.global_orient for r in recs]),
            "body_pose": np.stack([r.body_pose for r in recs]),
            "transl": np.stack([r.transl for r in recs]),
            "index": np.array([r.index for r in recs], dtype=np.int64),
            **hand_columns(recs),
        }

    def frame(self, split: str, i: int) -> Frame:
        rec = self._record(split, i)
        image, mask = self._pixels(rec)
        return Frame(image=image, mask=mask, camera=rec.camera.resized(*self.image_size),
                     betas=rec.betas, global_orient=rec.global_orient, body_pose=rec.body_pose,
                     transl=rec.transl, index=rec.index, split=split, hand_pose=rec.hand_pose)

    def frames(self, split: str, n: int | None = None) -> "FrameView":
        """The split's first ``n`` frames (default all) as a sequence whose frames are decoded when
        indexed: a pose sweep or fit over a long video need not hold every image at once."""
        total = self.num_frames(split)
        return FrameView(self, split, total if n is None else min(n, total))

    # --- internals -------------------------------------------------------------------------------

    def _record_list(self, split: str) -> list[FrameRecord]:
        if split not in self._records:
            have = ", ".join(self._records) or "none"
            raise UserError(f"dataset {self.root} has no split '{split}' (it has: {have})")
        return self._records[split]

    def _record(self, split: str, i: int) -> FrameRecord:
        recs = self._record_list(split)
        if not -len(recs) <= i < len(recs):
            raise IndexError(f"frame {i} out of range for split '{split}' with {len(recs)} frames")
        return recs[i]

    def _read_pixels(self, rec: FrameRecord) -> tuple[np.ndarray, np.ndarray]:
        """Source-resolution image [H,W,3] and mask [H,W]; readers override this to undistort."""
        image = read_image(rec.image)
        masks = [self._mask_reader(p) for p in rec.masks]
        w, h = self.source_size
        if image.shape[:2] != (h, w):
            raise UserError(f"image {rec.image} is {image.shape[1]}x{image.shape[0]}, "
                            f"the dataset's cameras are {w}x{h}")
        for p, m in zip(rec.masks, masks):
            if m.shape != (h, w):
                raise UserError(f"mask {p} is {m.shape[1]}x{m.shape[0]}, its image is {w}x{h}")
        mask = masks[0] if len(masks) == 1 else np.maximum.reduce(masks)
        return image, mask

    def _pixels(self, rec: FrameRecord) -> tuple[np.ndarray, np.ndarray]:
        key = str(rec.image)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        image, mask = self._read_pixels(rec)
        image = resample(image, *self.image_size)
        mask = resample(mask, *self.image_size)
        image.setflags(write=False)
        mask.setflags(write=False)
        self._cache[key] = (image, mask)
        self._cache_bytes += image.nbytes + mask.nbytes
        while self._cache_bytes > self._cache_limit and len(self._cache) > 1:
            _, (im, mk) = self._cache.popitem(last=False)
            self._cache_bytes -= im.nbytes + mk.nbytes
        return image, mask


def _split_key(name: str) -> tuple[int, str]:
    return (SPLIT_ORDER.index(name) if name in SPLIT_ORDER else len(SPLIT_ORDER), name)


def warn(msg: str) -> None:
    warnings.warn(msg, UserWarning, stacklevel=3)


class FrameView(Sequence):
    """Frames 0..n-1 of a dataset split, each decoded by ``Dataset.frame`` when indexed."""

    def __init__(self, dataset: Dataset, split: str, n: int):
        self.dataset, self.split, self.n = dataset, split, n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> Frame:
        if not 0 <= i < self.n:
            raise IndexError(f"frame {i} of {self.n}")
        return self.dataset.frame(self.split, i)
