"""``capture(INPUT, OUT, CaptureConfig)``: a video (or a folder of frames) of one person -> a native
dataset with estimated poses, ready for ``rmavatar train``.

Steps: a few frames spread over the clip are looked at first, and a clip with no person or two in
them is refused before the full pass; then every frame is decoded (subsampled, resized), MediaPipe
finds the person's landmarks and mask in it at a working size; frames without a person, or with a
second one, are dropped and reported; each frame kept is written as the dataset's own image file; then
the clip's background plate is made from frames spread over it (the camera is static) and every mask is
brought to the frame's size and snapped to the person's edges against it (:mod:`rmavatar.capture.matte`);
the body is fitted to all frames at once (:mod:`rmavatar.capture.fit`), then (Anny) its shape to the
person's masks (:mod:`rmavatar.capture.shape`); the dataset is completed with
a contact sheet of the fit. Any failure leaves nothing behind: frames wait in a temporary folder
beside OUT, and OUT appears only when everything is written. The time of each stage is measured and
returned (``rmavatar bench capture`` reports it).
"""

from __future__ import annotations

import contextlib
import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rmavatar.capture.fit import BodyFitConfig
from rmavatar.capture.hands import HandFitConfig
from rmavatar.capture.shape import ShapeFitConfig
from rmavatar.capture.views import MainClip, clip_params, open_rig, with_views
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
# Before the full pass, this many frames spread over the clip are looked at, so that a clip with no one
# or two people in it is refused in seconds, not after minutes of decoding.
SAMPLE_FRAMES = 8
# ... and a second person must show in at least this many of them (and in more than MAX_OTHER_FRAMES):
# one frame with a passer-by leaves the decision to the full pass, which drops such frames.
MIN_OTHER_LOOKED = 2
LOOK_SIDE = 640  # longer side of the frames looked at (MediaPipe's person detector sees 224x224 anyway)
# MediaPipe sees each frame scaled so that the person is about this tall: its landmark and segmentation
# model sees a 256x256 crop around the person, so more pixels only cost time (MediaPipe scales the
# frame and makes its mask at the frame's size), while fewer make that crop blurrier: on the synthetic
# 1080p turn 640 fitted as well as the full frame, 384 and 512 a little worse (docs/capture.md, "Speed").
WORK_HEIGHT = 640
WRITE_QUEUE = 4  # frames waiting for the writer thread, at most (each a full-size image and mask)


@dataclass
class CaptureConfig:
    """What ``rmavatar capture`` does. body: "anny", "anny:PRESET" or "smpl:PATH"; fov: horizontal
    field of view in degrees, or focal: pixels (of the output frames), else DEFAULT_FOCAL_LONG_SIDE;
    fps: keep at most this many frames per second (None: all); size: longer side of the frames
    written (None: the source's); frames: only the first this many frames kept (None: all);
    test_fraction: the tail of the clip held out as the test split; val_every: of the frames before it,
    every val_every-th held out as split val (0: none); calibration: a rig's calibration file whose
    camera ``camera`` (None: named like the video) gives the intrinsics, and whose other cameras film
    ``novel_views`` (synchronised videos, ``VIDEO[@CAMERA]``) for a novel_view split;
    device: "auto", "cpu", "cuda"."""

    body: str = "anny"  # body model fitted: "anny", "anny:PRESET" or "smpl:PATH"
    fov: float | None = None  # horizontal field of view in degrees (None: focal, else DEFAULT_FOCAL_LONG_SIDE)
    focal: float | None = None  # focal length in pixels of the output frames (None: see fov)
    fps: float | None = None  # keep at most this many frames per second (None: every frame)
    size: int | None = None  # longer side in pixels of the frames written (None: the source's)
    frames: int | None = None  # use only the first this many of the frames kept (None: all)
    test_fraction: float = 0.2  # tail of the clip held out as the test split
    val_every: int = 0  # of the frames before the test tail, every this many-th held out as split val (0: none)
    calibration: str | None = None  # a rig's calibration file (TOML or Qualisys): the camera's intrinsics
    camera: str | None = None  # the input's camera in the calibration (None: the one named like the video)
    novel_views: list[str] = field(default_factory=list)  # other calibrated videos, VIDEO[@CAMERA]: split novel_view
    device: str = "auto"  # where the fit runs: "auto", "cpu" or "cuda"
    fit: BodyFitConfig = field(default_factory=BodyFitConfig)  # the body fit's weights and schedule
    # the fingers' fit (None: not captured, the body's relaxed hands); bodies without fingers skip it
    hands: HandFitConfig | None = field(default_factory=HandFitConfig)
    # the body's shape fitted to the masks as offsets (None: the preset's shape); only Anny bodies, SMPL
    # bodies fit their betas with the poses
    shape: ShapeFitConfig | None = field(default_factory=ShapeFitConfig)

    def check(self) -> None:
        if self.fov is not None and self.focal is not None:
            raise UserError("give --fov or --focal, not both")
        if self.calibration is not None and (self.fov is not None or self.focal is not None):
            raise UserError("give --calibration or --fov / --focal, not both (the calibration holds the focal length)")
        if self.calibration is None and (self.camera is not None or self.novel_views):
            raise UserError("--camera and --novel-view need --calibration (the file that places the cameras)")
        if self.val_every < 0 or self.val_every == 1:
            raise UserError(f"--val-every must be 0 (none) or at least 2, got {self.val_every}")
        if self.fov is not None and not (math.isfinite(self.fov) and FOV_RANGE[0] <= self.fov <= FOV_RANGE[1]):
            raise UserError(f"--fov {self.fov:g} is not a camera's horizontal field of view: use degrees "
                            f"between {FOV_RANGE[0]:g} and {FOV_RANGE[1]:g} (a phone's main camera: "
                            f"about 65 across the longer side)")
        if self.focal is not None and not (math.isfinite(self.focal) and self.focal > 0):
            raise UserError(f"--focal must be a positive number of pixels, got {self.focal:g}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise UserError(f"--fps must be positive, got {self.fps:g}")
        if self.frames is not None and self.frames < 2:
            raise UserError(f"--frames must be at least 2 (a clip to fit), got {self.frames}")
        if self.size is not None and self.size < MIN_SIZE:
            raise UserError(f"--size must be at least {MIN_SIZE} pixels, got {self.size}")
        if not 0 < self.test_fraction < 1:
            raise UserError(f"--test-fraction must lie between 0 and 1 (exclusive), got {self.test_fraction:g}")
        if self.shape is not None:
            self.shape.check()


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
DATASET_NAMES = ("meta.yaml", "images", "masks", "*.npz", "contact_sheet.png", "background.png")


def check_out(out: Path, source: Path, overwrite: bool = False) -> None:
    """OUT may be new, empty or an earlier capture's dataset (replaced on success, see
    :mod:`rmavatar.utils.outputs`); never the input itself."""
    src = source.resolve()
    if out.resolve() == src or out.resolve() in src.parents:
        raise UserError(f"--out {out} holds the input {source}; write the dataset elsewhere")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder for the dataset")
    check_output_folder(out, DATASET_KIND, option="--out", overwrite=overwrite, writes=DATASET_NAMES)


STAGES = ("decode", "landmarks", "masks", "fit", "shape", "views", "write")


class _Stages:
    """Seconds spent per stage (STAGES), wall clock and CPU time of this process (MediaPipe's and
    torch's threads included; ffmpeg's decoding runs in a process of its own)."""

    def __init__(self):
        self.wall = dict.fromkeys(STAGES, 0.0)
        self.cpu = dict.fromkeys(STAGES, 0.0)

    @contextlib.contextmanager
    def __call__(self, stage: str):
        t, c = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[stage] += time.perf_counter() - t
            self.cpu[stage] += time.process_time() - c

    def frames(self, frames):
        """``frames`` (an iterator) with the time spent taking each item counted as decoding."""
        it = iter(frames)
        while True:
            with self("decode"):
                item = next(it, None)
            if item is None:
                return
            yield item


@dataclass
class _Look:
    """The frames looked at before the full pass (source indices), those without a person and those
    with another one, and the person's height (pixels of the output frames) in each frame with one."""

    looked: list[int] = field(default_factory=list)
    no_person: list[int] = field(default_factory=list)
    other_person: list[int] = field(default_factory=list)
    heights: list[float] = field(default_factory=list)


@dataclass
class _Clip:
    """The frames with a person, as detected: source index [T], keypoints [T,33,2], visibility [T,33],
    world [T,33,3], small masks [T,h,w] bool (for the silhouette term), the person's height (px), the
    hands' landmarks (empty when the fingers are not captured)."""

    index: list[int] = field(default_factory=list)
    keypoints: list[np.ndarray] = field(default_factory=list)
    visibility: list[np.ndarray] = field(default_factory=list)
    world: list[np.ndarray] = field(default_factory=list)
    small_masks: list[np.ndarray] = field(default_factory=list)
    heights: list[float] = field(default_factory=list)
    hands: list = field(default_factory=list)  # a rmavatar.capture.hands.HandDetection per frame
    hand_seconds: float = 0.0  # of the landmarks stage, the hands' share (wall clock)
    no_person: list[int] = field(default_factory=list)
    other_person: list[int] = field(default_factory=list)
    decoded: int = 0
    work_size: tuple[int, int] = (0, 0)  # (width, height) of the frames MediaPipe saw
    look: _Look = field(default_factory=_Look)


def _scaled(size: tuple[int, int], longer: float) -> tuple[int, int]:
    """(width, height) scaled so that the longer side is at most ``longer`` (never enlarged)."""
    from rmavatar.data.dataset import target_size

    return size if max(size) <= longer else target_size(*size, int(round(longer)))


def _look(source, cfg: CaptureConfig, kept: list[int] | None, detect, size: tuple[int, int],
          stages: _Stages) -> _Look:
    """Before the full pass: SAMPLE_FRAMES frames spread over the clip (over ``kept``, the source
    frames the full pass will read; None: unknown), each looked at on its own (MediaPipe's image mode)
    at most LOOK_SIDE pixels on the longer side, for a person and for another one."""
    import itertools

    from rmavatar.capture.frames import frames_at, read_frames, shrink

    if kept is None:  # a video of unknown length: its first frames
        frames = itertools.islice(read_frames(source, cfg.size, cfg.fps), SAMPLE_FRAMES)
    else:
        picks = np.unique(np.linspace(0, len(kept) - 1, min(SAMPLE_FRAMES, len(kept))).round().astype(int))
        frames = frames_at(source, [kept[j] for j in picks], cfg.size)
    look = _Look()
    small = _scaled(size, LOOK_SIDE)
    for i, image in stages.frames(frames):
        look.looked.append(i)
        with stages("landmarks"):
            view = shrink(image, *small)
            det = detect.look(view)
            rows = np.nonzero((det.mask > 0.5).any(1))[0] if det is not None else []
            if len(rows) == 0:
                look.no_person.append(i)
                continue
            if detect.another_person(view, det):
                look.other_person.append(i)
            look.heights.append(float(rows[-1] - rows[0] + 1) * size[1] / small[1])
    return look


def _check_look(look: _Look, source) -> None:
    """The clip refused from the frames looked at, with the messages of the full pass's checks."""
    name = source.path
    n = len(look.looked)
    if n == 0:
        raise UserError(f"input {name} has no frames")
    others = len(look.other_person)
    if others >= MIN_OTHER_LOOKED and others > MAX_OTHER_FRAMES * n:
        raise UserError(f"input {name} shows more than one person (in {others} of the {n} frames looked at, "
                        f"spread over the clip, the first at frame {look.other_person[0]}); rmavatar capture "
                        f"needs exactly one person in view")
    if n - len(look.no_person) < MIN_PERSON_FRAMES * n:
        raise UserError(f"input {name}: no person found in {len(look.no_person)} of {n} frames looked at "
                        f"(spread over the clip); the whole body of one person must be in view in most frames")


def _work_size(look: _Look, size: tuple[int, int]) -> tuple[int, int]:
    """The size of the frames MediaPipe sees in the full pass: the output frames scaled so that the
    person is about WORK_HEIGHT pixels tall (never enlarged)."""
    if not look.heights:
        return size
    scale = min(1.0, WORK_HEIGHT / float(np.median(look.heights)))
    return _scaled(size, max(size) * scale)


def _detect(source, cfg: CaptureConfig, kept: list[int] | None, scratch: Path, stages: _Stages, bar,
            hands: bool = False) -> tuple[_Clip, tuple[int, int]]:
    """Look at a few frames first (:func:`_look`, the clip refused at once when they show no person or
    two), then decode and detect every frame (with ``hands``, the hands' landmarks too), and write each
    frame with a person, as the dataset's frame files, into ``scratch`` (its images/ and masks/)."""
    import itertools

    from rmavatar.capture.detect import Detector
    from rmavatar.capture.hands import HandDetector
    from rmavatar.capture.frames import output_size, read_frames, shrink
    from rmavatar.data.dataset import target_size
    from rmavatar.data.io import to_uint8

    size = output_size(source, cfg.size)
    clip = _Clip()
    writer = _FrameWriter(scratch)
    try:
        with Detector() as detect, (HandDetector() if hands else contextlib.nullcontext()) as find_hands:
            bar.set_description(f"capture: looking at {SAMPLE_FRAMES} frames of {source.path.name}")
            clip.look = _look(source, cfg, kept, detect, size, stages)
            _check_look(clip.look, source)
            work = clip.work_size = _work_size(clip.look, size)
            # the hands' crops keep one size over the clip (a raised arm makes the mask taller, not the hand)
            hand_scale = float(np.median(clip.look.heights))
            bar.set_description(f"capture: finding the person in {source.path.name} ({work[0]}x{work[1]})")
            for i, image in stages.frames(itertools.islice(read_frames(source, cfg.size, cfg.fps), cfg.frames)):
                clip.decoded += 1
                bar.update(1)
                with stages("landmarks"):
                    view = shrink(image, *work)
                    det = detect(view)
                    rows = np.nonzero((det.mask > 0.5).any(1))[0] if det is not None else []
                    if len(rows) == 0:  # no pose, or a pose without a person's mask
                        clip.no_person.append(i)
                        continue
                    if clip.decoded % OTHER_PERSON_EVERY == 1 and detect.another_person(view, det):
                        clip.other_person.append(i)
                        continue
                with stages("write"):  # MediaPipe's own mask, at the working size: refined after the pass
                    writer.put(len(clip.index), image, to_uint8(det.mask, f"mask of frame {i}"))
                keypoints = det.keypoints * np.array([size[0] / work[0], size[1] / work[1]], np.float32)
                if find_hands is not None:
                    with stages("landmarks"):  # on the frame written: MediaPipe's working size blurs the fingers
                        start = time.perf_counter()
                        clip.hands.append(find_hands(image, keypoints, det.visibility, hand_scale))
                        clip.hand_seconds += time.perf_counter() - start
                clip.index.append(i)
                clip.keypoints.append(keypoints)
                clip.visibility.append(det.visibility)
                clip.world.append(det.world)
                clip.heights.append(float(rows[-1] - rows[0] + 1) * size[1] / work[1])
    finally:
        with stages("write"):
            writer.close()
    if clip.index:
        with stages("masks"):
            _refine_masks(clip, scratch, size, target_size(*size, min(FIT_SIDE, max(size))))
    return clip, size


def _refine_masks(clip: _Clip, folder: Path, size: tuple[int, int], small: tuple[int, int]) -> None:
    """Every frame's mask (MediaPipe's, as written at its working size) brought to the frame's size and
    snapped to its edges against the clip's background plate (:mod:`rmavatar.capture.matte`; the camera is
    static), written over it; ``clip.small_masks`` gets each at ``small`` for the fit."""
    from rmavatar.capture.matte import PLATE_FRAMES, background_plate, refine_mask
    from rmavatar.data.io import resample, to_uint8

    def frame(n: int) -> tuple[np.ndarray, np.ndarray]:
        image = read_frame_png(folder / "images" / f"{n:05d}.png")
        return image, resample(read_frame_png(folder / "masks" / f"{n:05d}.png") / np.float32(255.0), *size)

    n = len(clip.index)
    picks = np.unique(np.linspace(0, n - 1, min(PLATE_FRAMES, n)).round().astype(int))
    images, masks = zip(*(frame(int(k)) for k in picks))
    plate, seen = background_plate(np.stack(images), np.stack(masks))
    del images, masks
    write_frame_png(folder / "background.png", plate)
    for k in range(n):
        image, mask = frame(k)
        mask = refine_mask(image, mask, plate, seen)
        clip.small_masks.append(resample(mask, *small) > 0.5)
        write_frame_png(folder / "masks" / f"{k:05d}.png", to_uint8(mask, f"mask of frame {clip.index[k]}"))


class _FrameWriter:
    """Writes dataset frame n's image [H,W,3] and mask [H,W] (uint8) as the dataset's own files
    (``images/{n:05d}.png``, ``masks/{n:05d}.png`` in ``folder``), once, in a thread of its own: OpenCV's
    encoder releases the GIL, so a frame is encoded while MediaPipe looks at the next ones. At most
    WRITE_QUEUE frames wait (memory); ``put`` blocks beyond that, and re-raises the writer's error."""

    def __init__(self, folder: Path):
        from concurrent.futures import ThreadPoolExecutor

        self.folder = folder
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="capture-writer")
        self.pending = []

    def put(self, n: int, image: np.ndarray, mask: np.ndarray) -> None:
        while len(self.pending) >= WRITE_QUEUE:
            self.pending.pop(0).result()
        self.pending.append(self.pool.submit(self._write, n, image, mask))

    def _write(self, n: int, image: np.ndarray, mask: np.ndarray) -> None:
        _write_frame(self.folder, n, image, mask)

    def close(self) -> None:
        """Wait for every frame (their errors raised here); the thread ends."""
        try:
            for f in self.pending:
                f.result()
        finally:
            self.pending = []
            self.pool.shutdown(wait=True, cancel_futures=True)


def _write_frame(folder: Path, n: int, image: np.ndarray, mask: np.ndarray) -> None:
    """Dataset frame ``n``'s image and mask as ``folder``'s images/{n:05d}.png and masks/{n:05d}.png."""
    write_frame_png(folder / "images" / f"{n:05d}.png", image)
    write_frame_png(folder / "masks" / f"{n:05d}.png", mask)


def read_frame_png(path: Path) -> np.ndarray:
    """A PNG that :func:`write_frame_png` wrote: uint8 [H,W,3] RGB or [H,W] grey."""
    import cv2

    array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if array is None:
        raise UserError(f"cannot read {path} back")
    return array[..., ::-1].copy() if array.ndim == 3 else array


def write_frame_png(path: Path, array: np.ndarray) -> None:
    """uint8 [H,W,3] RGB or [H,W] grey as an 8-bit PNG, by OpenCV with zlib level 1 and the 'up' row
    filter: about as small as Pillow's level 3 on video frames, in about a third of its time (Pillow's
    encoder was most of a capture's writing; docs/capture.md)."""
    import cv2

    if array.ndim == 3:
        array = array[..., ::-1]  # OpenCV writes BGR
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
    ok, data = cv2.imencode(".png", np.ascontiguousarray(array), params)
    if not ok:
        raise UserError(f"cannot encode {path} as PNG")
    try:
        path.write_bytes(data.tobytes())
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc}") from None


def _write_dataset(tmp: Path, frames: Path, meta, camera, params: dict, size: tuple[int, int]) -> None:
    """The native dataset in ``tmp`` (see :mod:`rmavatar.data.native`) around the frames already written
    in ``frames`` (moved in, not encoded again): cameras.npz (``camera``: a Camera, or {"K", "viewmat"}
    per frame), smpl.npz and meta.yaml as ``write_native`` writes them, then opened by the format's own
    reader, which checks every key and frame file."""
    import os

    from rmavatar.data import native

    for sub in ("images", "masks", "background.png"):
        if (frames / sub).exists():
            os.replace(frames / sub, tmp / sub)
    K, viewmat = (camera["K"], camera["viewmat"]) if isinstance(camera, dict) else (camera.K, camera.viewmat)
    native.write_tables(tmp, meta, K, viewmat, params, size, meta.splits, "capture")
    native.open_native(tmp)


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


def _splits(n: int, test_fraction: float, name, which: str, val_every: int = 0) -> dict[str, list[int]]:
    """The train / (val /) test split of ``n`` frames (the test split: the clip's last ``test_fraction``;
    val: every ``val_every``-th frame before it, the first at half that, 0: none); a UserError when
    train or test would be empty."""
    n_test = max(1, int(round(test_fraction * n)))
    body = list(range(n - n_test))
    val = body[val_every // 2::val_every] if val_every else []
    if len(body) - len(val) < 1:
        raise UserError(f"input {name}: {n} frames {which} leave no training frame with --test-fraction "
                        f"{test_fraction:g} ({n_test} test frames); give a smaller --test-fraction or a longer "
                        "clip (at least 2 frames are needed)")
    splits = {"train": [i for i in body if i not in set(val)], "test": list(range(n - n_test, n))}
    return {**splits, "val": val} if val else splits


def _observations(clip: _Clip, K: np.ndarray, size: tuple[int, int], device):
    import torch

    from rmavatar.capture.fit import Observations, mask_maps
    from rmavatar.capture.landmarks import USED

    used = list(USED)
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
    index = np.asarray(clip.index)
    outside, outline, outline_weight = mask_maps(clip.small_masks, size[0])
    return Observations(
        keypoints=t(np.stack(clip.keypoints)[:, used]), visibility=t(np.stack(clip.visibility)[:, used]),
        world=t(np.stack(clip.world)[:, used]), outside=t(outside), K=t(K), size=size,
        gaps=t(np.diff(index).astype(np.float32)), height_px=float(np.median(clip.heights)),
        outline=t(outline), outline_weight=t(outline_weight),
    )


def _dataset_meta(source, clip: _Clip, cfg: CaptureConfig, splits: dict, spec: str, fx: float, losses: dict,
                  hands=None, shape=None, views=None):
    """The captured dataset's meta.yaml (a NativeMeta): body ``spec``, ``splits``, where each frame came
    from, how many frames saw each hand (``hands``: the hand fit, None when the fingers were not captured),
    the shape fit's summary (``shape``: a ShapeFitResult, None when the shape was not fitted), the other
    cameras' frames (``views``: a ViewFrames, None without them)."""
    from rmavatar.data import NativeMeta

    preset = spec.partition(":")[2] if spec.startswith("anny:") else None
    gender = (preset if preset in ("male", "female") else "neutral") if preset else None
    return NativeMeta(
        name=source.path.stem, splits=splits, fps=source.fps if cfg.fps is None else min(cfg.fps, source.fps),
        gender=gender, body=spec, poses_estimated=True,
        same_instant={} if views is None else {"novel_view": views.same_instant},
        extra={"generator": "rmavatar capture", "source": str(source.path.resolve()),
               "source_fps": source.fps, "frames_decoded": clip.decoded,
               # dataset frame i (images/{i:05d}.png) is the source's frame source_frames[i]: the video's
               # 0-based frame number, as on the contact sheet and in capture.npz's source_index
               "source_frames": list(clip.index),
               "frames_without_person": clip.no_person, "frames_with_another_person": clip.other_person,
               "frames_looked_at_first": clip.look.looked,
               "detection_size": list(clip.work_size),
               "camera": {"fov": cfg.fov, "focal": cfg.focal, "fx": fx, "calibration": cfg.calibration,
                          "name": cfg.camera},
               "novel_views": None if views is None else {"videos": cfg.novel_views, "cameras": views.summary()},
               "fit": asdict(cfg.fit), "losses": losses, "hands": _hands_found(hands, clip),
               "hand_fit": None if hands is None else asdict(cfg.hands),
               "shape": None if shape is None else shape.summary(),
               "shape_fit": None if shape is None else asdict(cfg.shape)},
    )  # fmt: skip


def _has_fingers(body) -> bool:
    """Whether ``body`` poses fingers: Anny and SMPL-H / SMPL-X files do (they have a relaxed hand pose),
    SMPL does not."""
    return getattr(body, "relaxed_hand_pose", None) is not None


def _fit_hands(body, params: dict, clip: _Clip, K: np.ndarray, fps: float, cfg: HandFitConfig):
    """The hand poses of every frame (:func:`rmavatar.capture.hands.fit_hands`) on the body's fitted pose."""
    from rmavatar.capture.hands import fit_hands

    seen = _hand_landmarks(clip)
    nb = min(10, int(getattr(body, "num_betas", 0)))
    return fit_hands(body, params["global_orient"], params["body_pose"], params["transl"], seen["hand_keypoints"],
                     seen["hand_world"], seen["hand_detected"], K, np.asarray(clip.index) / fps, cfg,
                     betas=params["betas"][:nb] if nb else None)


def _hand_landmarks(clip: _Clip) -> dict:
    """capture.npz's hand arrays: MediaPipe's hand landmarks per frame, left hand then right
    (``hand_keypoints`` [T,2,21,2] pixels, ``hand_world`` [T,2,21,3] metres, ``hand_detected`` [T,2])."""
    if not clip.hands:
        return {}
    return {"hand_keypoints": np.stack([h.keypoints for h in clip.hands]),
            "hand_world": np.stack([h.world for h in clip.hands]),
            "hand_detected": np.stack([h.found for h in clip.hands])}


def _hands_found(hands, clip: _Clip) -> dict | None:
    """How many frames saw the left and the right hand, and the seconds the hands took (MediaPipe's
    hand landmarks, of the landmarks stage; the hand fit, of the fit stage); None: not captured."""
    if hands is None:
        return None
    found = hands.found.sum(0)
    return {"frames": int(len(hands.found)), "left": int(found[0]), "right": int(found[1]),
            "landmark_seconds": round(clip.hand_seconds, 3), "fit_seconds": round(hands.seconds, 3)}


def _fit_shape(body, params: dict, obs, cfg: ShapeFitConfig | None):
    """The body's offsets fitted to the masks (:func:`rmavatar.capture.shape.fit_body_offsets`) and the
    body built with them, or (None, ``body``): no shape fit asked for, or a body that fits betas."""
    from rmavatar.body import load_body_model
    from rmavatar.capture.shape import can_fit_shape, fit_body_offsets

    if cfg is None or not can_fit_shape(body):
        return None, body
    shape = fit_body_offsets(body, params, obs, cfg)
    return shape, load_body_model(body.spec, offsets=shape.offsets).to(body.faces.device)


@dataclass
class _Fitted:
    """What :func:`_fit_clip` made: the body (rebuilt with the fitted offsets, where fitted), the
    dataset's SMPL-style params, the body fit's final losses, the hand fit (None: not fitted) and the
    shape fit (None: the preset's shape)."""

    body: object
    params: dict
    losses: dict
    hands: object
    shape: object


def _fit_clip(body, clip: _Clip, K: np.ndarray, size: tuple[int, int], fps: float, cfg: CaptureConfig,
              stages: _Stages, device, fingers: bool, progress: bool) -> _Fitted:
    """The body fitted to the clip's landmarks, then its fingers (``fingers``), then its shape to the masks."""
    from rmavatar.capture.fit import fit_body

    with stages("fit"):
        obs = _observations(clip, K, size, device)
        result = fit_body(body, obs, cfg.fit, progress=progress)
    params = {"betas": result.betas, "global_orient": result.global_orient, "body_pose": result.body_pose,
              "transl": result.transl}
    hands = None
    if fingers:
        with stages("fit"):
            hands = _fit_hands(body, params, clip, K, fps, cfg.hands)
        params.update(body_pose=hands.body_pose, hand_pose=hands.hand_pose, hand_found=hands.found)
    with stages("shape"):
        shape, body = _fit_shape(body, params, obs, cfg.shape)
    if shape is not None:
        params["body_offsets"] = shape.offsets
    return _Fitted(body, params, result.losses, hands, shape)


def capture(input_path: str | Path, out: str | Path, cfg: CaptureConfig | None = None,
            progress: bool = True, overwrite: bool = False) -> dict:
    """Make a native dataset at ``out`` from the video or image folder ``input_path``. Returns a
    summary: frames kept and dropped, the frames looked at first, the size MediaPipe saw, seconds per
    stage (``seconds``: wall clock per STAGES item; ``cpu_seconds``: this process's CPU time), the
    whole call's ``total_seconds`` and ``seconds_per_frame`` (per frame decoded), the body, the camera,
    the fit's final losses, ``hands``: how many frames saw each hand (None: the fingers not captured),
    ``shape``: the fitted offsets' mean and extremes (millimetres; None: the preset's shape)."""
    from tqdm import tqdm

    from rmavatar.body import load_body_model
    from rmavatar.capture.frames import kept_frames, open_source
    from rmavatar.capture.sheet import contact_sheet
    from rmavatar.data import Camera
    from rmavatar.utils import resolve_device
    from rmavatar.utils.files import tmp_prefix
    from rmavatar.utils.outputs import output_folder

    start = time.perf_counter()
    cfg = cfg or CaptureConfig()
    cfg.check()
    out = Path(out)
    source = open_source(input_path)
    check_out(out, source.path, overwrite)
    rig = open_rig(cfg.calibration, cfg.camera, cfg.novel_views, source.path)  # a wrong camera fails now
    kept = kept_frames(source, cfg.fps)
    if kept is not None:  # the clip's length is known: a split no frame count up to it can fill is refused now
        kept = kept[:cfg.frames]
        _splits(len(kept), cfg.test_fraction, source.path, "in all", cfg.val_every)
    device = resolve_device(cfg.device)
    body = load_body_model(cfg.body).to(device)
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    stages = _Stages()
    scratch = Path(tempfile.mkdtemp(prefix=tmp_prefix(out.name + ".frames"), dir=parent))
    for sub in ("images", "masks"):
        (scratch / sub).mkdir()
    bar = tqdm(total=len(kept) if kept is not None else None, unit="frame", disable=not progress)
    fingers = cfg.hands is not None and _has_fingers(body)
    try:
        with bar:
            clip, size = _detect(source, cfg, kept, scratch, stages, bar, hands=fingers)
        _check_clip(clip, source)
        n = len(clip.index)
        # before the fit's minutes
        splits = _splits(n, cfg.test_fraction, source.path, "with a person", cfg.val_every)
        K = rig.main.scaled_K(*size) if rig else intrinsics(*size, fov=cfg.fov, focal=cfg.focal)
        fitted = _fit_clip(body, clip, K, size, source.fps, cfg, stages, device, fingers, progress)
        body, params = fitted.body, fitted.params
        camera = Camera(K.astype(np.float32), np.eye(4, dtype=np.float32), *size)
        views = None
        if rig and rig.views:
            with stages("views"):
                views = rig.capture(body, params, splits["train"], MainClip(list(clip.index), np.stack(clip.keypoints),
                                                                            np.stack(clip.visibility)), K, size,
                                    source.fps, lambda n, image, mask: _write_frame(scratch, n, image, mask))
            params, K_all, viewmats = with_views(params, views, K)
            splits["novel_view"] = list(range(n, n + len(views.K)))
            camera = {"K": K_all, "viewmat": viewmats}
        spec = getattr(body, "spec", cfg.body)
        meta = _dataset_meta(source, clip, cfg, splits, spec, float(K[0, 0]), fitted.losses, fitted.hands,
                             fitted.shape, views)
        with stages("write"), \
                output_folder(out, DATASET_KIND, option="--out", overwrite=overwrite, writes=DATASET_NAMES) as tmp:
            _write_dataset(tmp, scratch, meta, camera, params, size)
            np.savez(tmp / "capture.npz", source_index=np.asarray(clip.index),
                     keypoints=np.stack(clip.keypoints), visibility=np.stack(clip.visibility),
                     world=np.stack(clip.world), **_hand_landmarks(clip))  # fmt: skip
            main_camera = Camera(K.astype(np.float32), np.eye(4, dtype=np.float32), *size)
            contact_sheet(tmp / "contact_sheet.png", body, main_camera, clip_params(params, n),
                          {k: v for k, v in splits.items() if k != "novel_view"}, clip, tmp / "images")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    total = time.perf_counter() - start
    return {
        "out": str(out), "frames": {k: len(v) for k, v in splits.items()}, "decoded": clip.decoded,
        "no_person": clip.no_person, "other_person": clip.other_person, "looked_at": clip.look.looked,
        "detection_size": list(clip.work_size), "body": spec,
        "camera": {"fx": float(K[0, 0]), "width": size[0], "height": size[1]},
        "losses": fitted.losses, "hands": _hands_found(fitted.hands, clip),
        "shape": None if fitted.shape is None else fitted.shape.summary(),
        "novel_views": None if views is None else views.summary(), "seconds": dict(stages.wall),
        "cpu_seconds": dict(stages.cpu),
        "total_seconds": total, "seconds_per_frame": total / max(clip.decoded, 1),
    }
