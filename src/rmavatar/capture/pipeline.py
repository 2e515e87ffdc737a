"""``capture(INPUT, OUT, CaptureConfig)``: a video (or a folder of frames) of one person -> a native
dataset with estimated poses, ready for ``rmavatar train``.

Steps: decode (and subsample, resize) the frames; MediaPipe finds the person's landmarks and mask in
each (the mask then snapped to the frame's colour edges, :mod:`rmavatar.capture.matte`); frames
without a person, or with a second one, are dropped and reported; the body is fitted to all frames at
once (:mod:`rmavatar.capture.fit`); the dataset is written atomically with a contact sheet of the fit.
Any failure leaves nothing behind: frames wait in a temporary folder beside OUT, and OUT appears only
when everything is written.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rmavatar.capture.fit import BodyFitConfig
from rmavatar.utils import UserError
from rmavatar.utils.outputs import check_output_folder

# A phone's main camera (26 mm equivalent, with the crop of video stabilisation) sees about 65 degrees
# across the longer side of the frame: f = 0.8 x the longer side.
DEFAULT_FOCAL_LONG_SIDE = 0.8
FOV_RANGE = (10.0, 150.0)  # degrees across the width; outside it a value is a typo, not a lens
MIN_SIZE = 64
OTHER_PERSON_EVERY = 5  # look for a second person in every 5th frame (it costs a second detection)
MAX_OTHER_FRAMES = 0.1  # more of the frames looked at than this with a second person: refused
MIN_PERSON_FRAMES = 0.5  # fewer frames than this with a person: the clip is refused
FIT_SIDE = 256  # longer side of the masks the silhouette term compares with


@dataclass
class CaptureConfig:
    """What ``rmavatar capture`` does. body: "anny", "anny:PRESET" or "smpl:PATH"; fov: horizontal
    field of view in degrees, or focal: pixels (of the output frames), else DEFAULT_FOCAL_LONG_SIDE;
    fps: keep at most this many frames per second (None: all); size: longer side of the frames
    written (None: the source's); test_fraction: the tail of the clip held out as the test split;
    device: "auto", "cpu", "cuda"."""

    body: str = "anny"  # body model fitted: "anny", "anny:PRESET" or "smpl:PATH"
    fov: float | None = None  # horizontal field of view in degrees (None: focal, else DEFAULT_FOCAL_LONG_SIDE)
    focal: float | None = None  # focal length in pixels of the output frames (None: see fov)
    fps: float | None = None  # keep at most this many frames per second (None: every frame)
    size: int | None = None  # longer side in pixels of the frames written (None: the source's)
    test_fraction: float = 0.2  # tail of the clip held out as the test split
    device: str = "auto"  # where the fit runs: "auto", "cpu" or "cuda"
    fit: BodyFitConfig = field(default_factory=BodyFitConfig)  # the body fit's weights and schedule

    def check(self) -> None:
        if self.fov is not None and self.focal is not None:
            raise UserError("give --fov or --focal, not both")
        if self.fov is not None and not (math.isfinite(self.fov) and FOV_RANGE[0] <= self.fov <= FOV_RANGE[1]):
            raise UserError(f"--fov {self.fov:g} is not a camera's horizontal field of view: use degrees "
                            f"between {FOV_RANGE[0]:g} and {FOV_RANGE[1]:g} (a phone's main camera: "
                            f"about 65 across the longer side)")
        if self.focal is not None and not (math.isfinite(self.focal) and self.focal > 0):
            raise UserError(f"--focal must be a positive number of pixels, got {self.focal:g}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise UserError(f"--fps must be positive, got {self.fps:g}")
        if self.size is not None and self.size < MIN_SIZE:
            raise UserError(f"--size must be at least {MIN_SIZE} pixels, got {self.size}")
        if not 0 < self.test_fraction < 1:
            raise UserError(f"the test fraction must lie between 0 and 1, got {self.test_fraction:g}")


def intrinsics(width: int, height: int, fov: float | None = None, focal: float | None = None) -> np.ndarray:
    """K [3,3] for ``width`` x ``height`` frames: from the horizontal field of view (degrees) or the
    focal length (pixels), else a phone's main camera; square pixels, principal point at the centre.
    A focal length whose horizontal field of view falls outside FOV_RANGE is refused."""
    if fov is not None:
        f = width / 2 / math.tan(math.radians(fov) / 2)
    elif focal is not None:
        f = float(focal)
        implied = math.degrees(2 * math.atan(width / 2 / f))
        if not FOV_RANGE[0] <= implied <= FOV_RANGE[1]:
            raise UserError(f"--focal {focal:g} px gives a horizontal field of view of {implied:.1f} degrees "
                            f"for {width}-pixel-wide frames; a camera has {FOV_RANGE[0]:g}-{FOV_RANGE[1]:g} "
                            f"(the focal length is in pixels of the frames written, see --size)")
    else:
        f = DEFAULT_FOCAL_LONG_SIDE * max(width, height)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=np.float64)


DATASET_KIND = "capture-dataset"
DATASET_NAMES = ("meta.yaml", "images", "masks", "*.npz", "contact_sheet.png")


def check_out(out: Path, source: Path, overwrite: bool = False) -> None:
    """OUT may be new, empty or an earlier capture's dataset (replaced on success, see
    :mod:`rmavatar.utils.outputs`); never the input itself."""
    src = source.resolve()
    if out.resolve() == src or out.resolve() in src.parents:
        raise UserError(f"--out {out} holds the input {source}; write the dataset elsewhere")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder for the dataset")
    check_output_folder(out, DATASET_KIND, option="--out", overwrite=overwrite, writes=DATASET_NAMES)


@dataclass
class _Clip:
    """The frames with a person, as detected: source index [T], keypoints [T,33,2], visibility [T,33],
    world [T,33,3], small masks [T,h,w] bool (for the silhouette term), the person's height (px)."""

    index: list[int] = field(default_factory=list)
    keypoints: list[np.ndarray] = field(default_factory=list)
    visibility: list[np.ndarray] = field(default_factory=list)
    world: list[np.ndarray] = field(default_factory=list)
    small_masks: list[np.ndarray] = field(default_factory=list)
    heights: list[float] = field(default_factory=list)
    no_person: list[int] = field(default_factory=list)
    other_person: list[int] = field(default_factory=list)
    decoded: int = 0


def _detect(source, cfg: CaptureConfig, scratch: Path, progress: bool) -> tuple[_Clip, tuple[int, int]]:
    """Decode, detect, and keep each frame with a person as PNGs in ``scratch``."""
    from tqdm import tqdm

    from rmavatar.capture.detect import Detector
    from rmavatar.capture.frames import output_size, read_frames
    from rmavatar.capture.matte import refine_mask
    from rmavatar.data.dataset import target_size
    from rmavatar.data.io import resample, to_uint8, write_png

    size = output_size(source, cfg.size)
    small = target_size(*size, min(FIT_SIDE, max(size)))
    total = None
    if source.count:
        total = source.count if cfg.fps is None or cfg.fps >= source.fps else \
            int(math.ceil(source.count * cfg.fps / source.fps))
    clip = _Clip()
    with Detector() as detect, tqdm(total=total, desc=f"capture: finding the person in {source.path.name}",
                                    unit="frame", disable=not progress) as bar:
        for i, image in read_frames(source, cfg.size, cfg.fps):
            clip.decoded += 1
            bar.update(1)
            det = detect(image)
            rows = np.nonzero((det.mask > 0.5).any(1))[0] if det is not None else []
            if len(rows) == 0:  # no pose, or a pose without a person's mask
                clip.no_person.append(i)
                continue
            if clip.decoded % OTHER_PERSON_EVERY == 1 and detect.another_person(image, det):
                clip.other_person.append(i)
                continue
            n = len(clip.index)
            mask = refine_mask(image, det.mask)
            write_png(scratch / f"image{n:06d}.png", image)
            write_png(scratch / f"mask{n:06d}.png", to_uint8(mask, f"mask of frame {i}"))
            clip.index.append(i)
            clip.keypoints.append(det.keypoints)
            clip.visibility.append(det.visibility)
            clip.world.append(det.world)
            clip.small_masks.append(resample(mask, *small) > 0.5)
            clip.heights.append(float(rows[-1] - rows[0] + 1))
    return clip, size


def _check_clip(clip: _Clip, source) -> None:
    name = source.path
    if clip.decoded == 0:
        raise UserError(f"input {name} has no frames")
    kept = len(clip.index)
    looked = (clip.decoded + OTHER_PERSON_EVERY - 1) // OTHER_PERSON_EVERY
    if len(clip.other_person) > MAX_OTHER_FRAMES * looked:
        raise UserError(f"input {name} shows more than one person (in {len(clip.other_person)} of the {looked} "
                        f"frames looked at, the first at frame {clip.other_person[0]}); rmavatar capture needs "
                        f"exactly one person in view")
    if kept < MIN_PERSON_FRAMES * clip.decoded or kept < 2:
        raise UserError(f"input {name}: no person found in {len(clip.no_person)} of {clip.decoded} frames; "
                        f"the whole body of one person must be in view in most frames")


def _splits(n: int, test_fraction: float, name, which: str) -> dict[str, list[int]]:
    """The train / test split of ``n`` frames (the test split: the clip's last ``test_fraction``); a
    UserError when either would be empty."""
    n_test = max(1, int(round(test_fraction * n)))
    if n - n_test < 1:
        raise UserError(f"input {name}: {n} frames {which} leave no training frame with --test-fraction "
                        f"{test_fraction:g} ({n_test} test frames); give a smaller --test-fraction or a longer "
                        "clip (at least 2 frames are needed)")
    return {"train": list(range(n - n_test)), "test": list(range(n - n_test, n))}


def _observations(clip: _Clip, K: np.ndarray, size: tuple[int, int], device):
    import torch
    from scipy import ndimage

    from rmavatar.capture.fit import Observations, mask_outline
    from rmavatar.capture.landmarks import USED

    used = list(USED)
    w_small = clip.small_masks[0].shape[1]
    px = size[0] / w_small  # full-image pixels per small-mask pixel
    # a mask too thin to survive the reduction leaves no foreground: every point then counts as inside
    outside = np.stack([ndimage.distance_transform_edt(~m) * px if m.any() else np.zeros(m.shape)
                        for m in clip.small_masks]).astype(np.float32)  # fmt: skip
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
    index = np.asarray(clip.index)
    outline, outline_weight = mask_outline(clip.small_masks, px)
    return Observations(
        keypoints=t(np.stack(clip.keypoints)[:, used]), visibility=t(np.stack(clip.visibility)[:, used]),
        world=t(np.stack(clip.world)[:, used]), outside=t(outside), K=t(K), size=size,
        gaps=t(np.diff(index).astype(np.float32)), height_px=float(np.median(clip.heights)),
        outline=t(outline), outline_weight=t(outline_weight),
    )


def capture(input_path: str | Path, out: str | Path, cfg: CaptureConfig | None = None,
            progress: bool = True, overwrite: bool = False) -> dict:
    """Make a native dataset at ``out`` from the video or image folder ``input_path``. Returns a
    summary (frames kept and dropped, timings, the body, the camera, the fit's final losses)."""
    from rmavatar.body import load_body_model
    from rmavatar.capture.fit import fit_body
    from rmavatar.capture.frames import open_source
    from rmavatar.capture.sheet import contact_sheet
    from rmavatar.data import Camera, NativeMeta, write_native
    from rmavatar.data.io import read_image, read_mask
    from rmavatar.utils import resolve_device
    from rmavatar.utils.files import tmp_prefix
    from rmavatar.utils.outputs import output_folder

    cfg = cfg or CaptureConfig()
    cfg.check()
    out = Path(out)
    source = open_source(input_path)
    check_out(out, source.path, overwrite)
    device = resolve_device(cfg.device)
    body = load_body_model(cfg.body).to(device)
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    if source.count:  # the clip's length is known: a split no frame count up to it can fill is refused now
        total = source.count if cfg.fps is None or cfg.fps >= source.fps else \
            int(math.ceil(source.count * cfg.fps / source.fps))
        _splits(total, cfg.test_fraction, source.path, "in all")
    timings = {}
    scratch = Path(tempfile.mkdtemp(prefix=tmp_prefix(out.name + ".frames"), dir=parent))
    try:
        t0 = time.perf_counter()
        clip, size = _detect(source, cfg, scratch, progress)
        timings["detect_seconds"] = time.perf_counter() - t0
        _check_clip(clip, source)
        n = len(clip.index)
        splits = _splits(n, cfg.test_fraction, source.path, "with a person")  # before the fit's minutes
        K = intrinsics(*size, fov=cfg.fov, focal=cfg.focal)
        obs = _observations(clip, K, size, device)
        result = fit_body(body, obs, cfg.fit, progress=progress)
        timings["fit_seconds"] = result.seconds
        out_fps = source.fps if cfg.fps is None else min(cfg.fps, source.fps)
        spec = getattr(body, "spec", cfg.body)
        preset = spec.partition(":")[2] if spec.startswith("anny:") else None
        gender = (preset if preset in ("male", "female") else "neutral") if preset else None
        meta = NativeMeta(
            name=source.path.stem, splits=splits, fps=out_fps, gender=gender, body=spec, poses_estimated=True,
            extra={"generator": "rmavatar capture", "source": str(source.path.resolve()),
                   "source_fps": source.fps, "frames_decoded": clip.decoded,
                   "frames_without_person": clip.no_person, "frames_with_another_person": clip.other_person,
                   "camera": {"fov": cfg.fov, "focal": cfg.focal, "fx": float(K[0, 0])},
                   "fit": asdict(cfg.fit), "losses": result.losses},
        )  # fmt: skip
        params = {"betas": result.betas, "global_orient": result.global_orient, "body_pose": result.body_pose,
                  "transl": result.transl}
        camera = Camera(K.astype(np.float32), np.eye(4, dtype=np.float32), *size)
        t0 = time.perf_counter()
        with output_folder(out, DATASET_KIND, option="--out", overwrite=overwrite, writes=DATASET_NAMES) as tmp:
            images = (read_image(scratch / f"image{i:06d}.png") for i in range(n))
            masks = (read_mask(scratch / f"mask{i:06d}.png") for i in range(n))
            write_native(tmp, meta, camera, params, images, masks, progress=progress)
            np.savez(tmp / "capture.npz", source_index=np.asarray(clip.index),
                     keypoints=np.stack(clip.keypoints), visibility=np.stack(clip.visibility),
                     world=np.stack(clip.world))  # fmt: skip
            contact_sheet(tmp / "contact_sheet.png", body, camera, params, splits, clip, scratch)
        timings["write_seconds"] = time.perf_counter() - t0
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    total = sum(timings.values())
    return {
        "out": str(out), "frames": {k: len(v) for k, v in splits.items()}, "decoded": clip.decoded,
        "no_person": clip.no_person, "other_person": clip.other_person, "body": spec,
        "camera": {"fx": float(K[0, 0]), "width": size[0], "height": size[1]},
        "losses": result.losses, "seconds": timings, "seconds_per_frame": total / max(clip.decoded, 1),
    }
