"""The synthetic clothed subject (`rmavatar synth`): the Anny body in a loose striped tunic, trousers,
shoes, hair and a painted face, turning round in front of a static camera like PeopleSnapshot's
subjects, rendered by a textured-mesh rasterizer independent of the Gaussian one. See docs/synth.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rmavatar.utils import UserError
from rmavatar.utils.outputs import check_output_folder, output_folder

PRESETS = ("neutral", "male", "female", "child")
MAX_SIZE = 4096  # pixels; the supersampled frame of a larger one would not fit in memory


@dataclass
class SynthConfig:
    """What to make. Frame counts per split; ``turns`` full turns over the train+test frames;
    ``novel_views`` extra cameras rendering the test poses (split ``novel_view``); ``pose_noise`` degrees
    of tracker-like noise on the *stored* poses (the images always show the true ones); ``ss`` samples
    per pixel side (anti-aliasing); ``distance`` metres from the camera to the person."""

    size: int = 256  # image width and height in pixels
    seed: int = 0  # picks the outfit colours, the motion's small variations and the pose noise
    preset: str = "neutral"  # Anny body preset, one of PRESETS
    train: int = 100  # training frames (the head of the turn)
    test: int = 30  # test frames (the turn's contiguous tail)
    novel_pose: int = 30  # frames of a different motion (walking, then arm raises), same camera
    novel_views: int = 0  # extra cameras rendering the test poses (split novel_view)
    turns: float = 1.75  # full turns over the train + test frames
    pose_noise: float = 0.0  # degrees of tracker-like noise on the stored poses (images show the true ones)
    ss: int = 3  # supersampling: samples per pixel side (anti-aliasing)
    distance: float = 3.6  # metres from the camera to the person
    fps: float = 7.5  # frame rate stored in meta.yaml (PeopleSnapshot's 30 fps subsampled by 4)
    hand_motion: bool = False  # fingers open, close, point and spread (finger poses stored as hand_pose)

    def check(self) -> None:
        if not 16 <= self.size <= MAX_SIZE:
            raise UserError(f"--size must be in 16..{MAX_SIZE} pixels, got {self.size}")
        if self.seed < 0:
            raise UserError(f"--seed must be >= 0, got {self.seed}")
        for name in ("turns", "pose_noise", "distance", "fps"):  # NaN passes every comparison below
            if not math.isfinite(getattr(self, name)):
                raise UserError(f"--{name.replace('_', '-')} must be a finite number, got {getattr(self, name)}")
        if self.preset not in PRESETS:
            raise UserError(f"--preset must be one of {', '.join(PRESETS)}, got {self.preset!r}")
        for name in ("train", "test"):
            if getattr(self, name) < 1:
                raise UserError(f"--{name} must be at least 1, got {getattr(self, name)}")
        for name in ("novel_pose", "novel_views"):
            if getattr(self, name) < 0:
                raise UserError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}")
        if self.turns <= 0:
            raise UserError(f"--turns must be positive, got {self.turns}")
        if self.pose_noise < 0:
            raise UserError(f"--pose-noise must be >= 0 degrees, got {self.pose_noise}")
        if not 1 <= self.ss <= 8:
            raise UserError(f"--ss must be between 1 and 8, got {self.ss}")
        if self.distance < 1.5:
            raise UserError(f"--distance must be at least 1.5 m, got {self.distance}")


@dataclass
class Shot:
    """One frame to render: true SMPL parameters, camera, split."""

    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    K: np.ndarray
    viewmat: np.ndarray
    split: str
    hand_pose: np.ndarray | None = None


def plan(cfg: SynthConfig, body_y: tuple[float, float] = (-1.31, 0.52), hand_axes=None) -> list[Shot]:
    """The frames in output order: train, test (the turn's contiguous tail, as in PeopleSnapshot),
    novel_pose, then novel_view. Poses are noise-free. Deterministic for ``cfg.seed``.
    ``body_y``: the standing body's lowest and highest y (m), for framing; ``hand_axes``: the body's
    :class:`~rmavatar.body.hands.HandAxes`, needed with ``cfg.hand_motion``."""
    from rmavatar.data.synth.motion import finger_motion, look_at, novel_motion, turn_motion

    rng = np.random.default_rng([cfg.seed, 1])
    n_turn = cfg.train + cfg.test
    turn = turn_motion(n_turn, cfg.turns, rng)
    novel = novel_motion(max(cfg.novel_pose, 1), rng)
    for motion in (turn, novel):  # a stream of its own: the body's motion stays what it was without hands
        hands = np.random.default_rng([cfg.seed, 3, len(motion["transl"])])
        n_motion = len(motion["transl"])
        motion["hand_pose"] = finger_motion(n_motion, hand_axes, hands) if cfg.hand_motion else [None] * n_motion
    S = cfg.size
    # Framing: 115% of the body's height (room for raised arms) fill 90% of the image.
    lo, hi = body_y
    f = S * 0.9 * cfg.distance / (1.15 * (hi - lo))
    K = np.array([[f, 0.0, S / 2], [0.0, f, S / 2], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.5 * (lo + hi), 0.0])
    eye = target + np.array([0.0, 0.1, cfg.distance])
    main = look_at(eye, target)
    shots = []
    for i in range(n_turn):
        split = "train" if i < cfg.train else "test"
        shots.append(Shot(turn["global_orient"][i], turn["body_pose"][i], turn["transl"][i], K, main, split,
                          turn["hand_pose"][i]))
    for i in range(cfg.novel_pose):
        shots.append(Shot(novel["global_orient"][i], novel["body_pose"][i], novel["transl"][i], K, main,
                          "novel_pose", novel["hand_pose"][i]))  # fmt: skip
    # Novel views: cameras around the person at other heights; each renders every N-th test pose.
    for c in range(cfg.novel_views):
        az = 2 * np.pi * (c + 1) / (cfg.novel_views + 1)
        height = (0.9, -0.5)[c % 2]
        pos = target + np.array([np.sin(az) * cfg.distance, height, np.cos(az) * cfg.distance])
        vm = look_at(pos, target)
        for i in range(cfg.train + c, n_turn, cfg.novel_views):
            shots.append(Shot(turn["global_orient"][i], turn["body_pose"][i], turn["transl"][i], K, vm,
                              "novel_view", turn["hand_pose"][i]))  # fmt: skip
    return shots


DATASET_KIND = "synth-dataset"
DATASET_NAMES = ("meta.yaml", "images", "masks", "*.npz", "contact_sheet.png")


def synthesize(out: str | Path, cfg: SynthConfig, progress: bool = True, overwrite: bool = False) -> dict:
    """Render the subject and write a native dataset to ``out`` (atomically: a temporary folder renamed
    at the end). Also writes ``contact_sheet.png`` and ``smpl_true.npz`` (the noise-free poses) there.
    Returns a summary dict (frames per split, seconds)."""
    from scipy.spatial.transform import Rotation
    from tqdm import tqdm

    from rmavatar.body import PoseSequence, load_body_model, posed_vertices
    from rmavatar.body.hands import hand_axes
    from rmavatar.data.native import NativeMeta, write_native
    from rmavatar.data.synth.motion import add_pose_noise
    from rmavatar.data.synth.render import render
    from rmavatar.data.synth.subject import build_subject, garment_state

    cfg.check()
    start = time.time()
    out = Path(out)
    # Only a dataset synth made is replaced (see rmavatar.utils.outputs), never one converted from a video.
    check_output_folder(out, DATASET_KIND, option="OUT", overwrite=overwrite, writes=DATASET_NAMES)
    body = load_body_model(f"anny:{cfg.preset}")
    subject = build_subject(body, cfg.seed)
    ys = body.v_template[:, 1]
    axes = hand_axes(body) if cfg.hand_motion else None
    shots = plan(cfg, (float(ys.min()), float(ys.max())), axes)
    n = len(shots)
    keys = ("global_orient", "body_pose", "transl") + (("hand_pose",) if cfg.hand_motion else ())
    true = {k: np.stack([getattr(s, k) for s in shots]) for k in keys}
    poses = PoseSequence.from_arrays(true["global_orient"], true["body_pose"], true["transl"], true.get("hand_pose"))
    verts = posed_vertices(body, poses, chunk=64).numpy()
    stored = add_pose_noise(true, cfg.pose_noise, np.random.default_rng([cfg.seed, 2]))
    params = {k: v.astype(np.float32) for k, v in stored.items()}
    params["betas"] = np.zeros(10, dtype=np.float32)  # Anny's shape comes from the preset, not betas
    splits: dict[str, list[int]] = {}
    for i, s in enumerate(shots):
        splits.setdefault(s.split, []).append(i)
    splits["val"] = splits["test"][:1]  # PeopleSnapshot keeps one validation frame at the test start
    pick = _sheet_picks(splits)
    sheet: dict[int, np.ndarray] = {}
    masks: list[np.ndarray] = []
    bar = tqdm(total=n, desc="synth: rendering", unit="frame", disable=not progress)

    def images():
        for i, s in enumerate(shots):
            image, mask = render(subject, verts[i], Rotation.from_rotvec(s.global_orient).as_matrix(),
                                 garment_state(s.body_pose), s.K, s.viewmat, cfg.size, cfg.size, ss=cfg.ss)  # fmt: skip
            masks.append(mask)
            if i in pick:
                sheet[i] = image
            bar.update(1)
            yield image

    def mask_stream():
        for _ in range(n):
            yield masks.pop(0)

    gender = cfg.preset if cfg.preset in ("male", "female") else "neutral"
    meta = NativeMeta(
        name=f"synth-seed{cfg.seed}", splits=splits, fps=cfg.fps, gender=gender, body=body.spec,
        extra={"generator": "rmavatar synth", "config": asdict(cfg),
               "test_split": "contiguous tail of the turn (as PeopleSnapshot)",
               "novel_pose": "walking on the spot while turning, then arm raises"},
    )  # fmt: skip
    cameras = {"K": np.stack([s.K for s in shots]).astype(np.float32),
               "viewmat": np.stack([s.viewmat for s in shots]).astype(np.float32)}  # fmt: skip
    with output_folder(out, DATASET_KIND, option="OUT", overwrite=overwrite, writes=DATASET_NAMES) as tmp:
        write_native(tmp, meta, cameras, params, images(), mask_stream(), progress=False)
        bar.close()
        np.savez(tmp / "smpl_true.npz", **{k: v.astype(np.float32) for k, v in true.items()})
        write_contact_sheet(tmp / "contact_sheet.png", [(splits_of(i, shots), sheet[i]) for i in sorted(sheet)])
    return {"frames": {k: len(v) for k, v in splits.items()}, "seconds": time.time() - start, "out": str(out)}


def true_poses(dataset, split: str):
    """The noise-free poses (a PoseSequence) of ``split`` of a synthetic subject written with
    ``smpl_true.npz`` beside its stored (possibly noisy) poses; None for any other dataset."""
    from rmavatar.body import PoseSequence

    path = Path(dataset.root) / "smpl_true.npz"
    if not path.is_file():
        return None
    index = dataset.params(split)["index"]
    try:
        with np.load(path) as data:
            keys = ("global_orient", "body_pose", "transl") + (("hand_pose",) if "hand_pose" in data.files else ())
            rows = {k: data[k][index] for k in keys}
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise UserError(f"{path} does not hold the true poses of {dataset.root}'s frames: {exc}") from None
    return PoseSequence.from_arrays(rows["global_orient"], rows["body_pose"], rows["transl"], rows.get("hand_pose"))


def splits_of(i: int, shots: list[Shot]) -> str:
    return f"{shots[i].split} {i}"


def _sheet_picks(splits: dict[str, list[int]], per_split: int = 6) -> set[int]:
    picks: set[int] = set()
    for name in ("train", "test", "novel_pose", "novel_view"):
        idx = splits.get(name, [])
        if idx:
            sel = np.linspace(0, len(idx) - 1, min(per_split, len(idx))).round().astype(int)
            picks.update(idx[j] for j in sel)
    return picks


def write_contact_sheet(path: Path, tiles: list[tuple[str, np.ndarray]], per_row: int = 6) -> None:
    """A grid of labelled frames (rows grouped by split) saved as PNG."""
    from PIL import Image, ImageDraw

    rows: dict[str, list[tuple[str, np.ndarray]]] = {}
    for label, img in tiles:
        rows.setdefault(label.split()[0], []).append((label, img))
    h, w = tiles[0][1].shape[:2]
    pad = 14
    lines = [group[k:k + per_row] for group in rows.values() for k in range(0, len(group), per_row)]
    canvas = Image.new("RGB", (per_row * w, len(lines) * (h + pad)), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r, line in enumerate(lines):
        for c, (label, img) in enumerate(line):
            tile = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
            canvas.paste(tile, (c * w, r * (h + pad) + pad))
            draw.text((c * w + 3, r * (h + pad) + 1), label, fill=(0, 0, 0))
    canvas.save(path)
