"""``rmavatar bench capture``: ``rmavatar capture`` on one clip, its time per frame by stage, and how well
it did.

INPUT is a video (or a folder of frames) of one person. Without it, a synthetic clip: the default
subject (``rmavatar synth``, seed 0) turning in an A-pose, rendered at 1080x1080 and padded to a 1920x1080
frame with its white background, 80 frames at 7.5 frames/s, captured with its true field of view; it is
made once in --work and reused.

Reported, per frame decoded: wall-clock seconds of each stage of the capture (decode, landmarks, masks,
fit, shape: the body's offsets and building the body with them, views: other calibrated cameras'
frames, write; ``other``: loading the body and
MediaPipe, the frames looked at first are in decode and landmarks) and the same as this process's CPU
seconds (less sensitive to other load on the machine; ffmpeg's decoding runs in a process of its own
and is not in them). Then: the share of frames with a person; the share of MediaPipe's 33 landmarks
it saw (visibility > 0.5) in those frames; and the silhouette IoU of the fitted body, posed by the
fitted poses and rasterised by the dataset's camera, against the masks written (at most 512 pixels on
the longer side), mean over frames: with the fitted shape (smpl.npz's body offsets,
``silhouette_iou``) and the preset's (``silhouette_iou_preset``; the same where no shape was fitted). ``shape``: the fitted offsets' mean and extremes (mm). For the
synthetic clip also the fit against the truth: 2D joint error (% of the body's height in the image),
3D joint error with the roots aligned (mm), and the IoU of the masks written with the true masks.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np

SYNTH_TRAIN, SYNTH_TEST = 64, 16  # frames of the synthetic turn (1.75 turns over both)
SYNTH_SIDE, SYNTH_WIDTH = 1080, 1920
IOU_SIDE = 512  # longer side at which silhouettes and masks are compared


def synthetic_clip(work: Path, progress: bool = True) -> tuple[Path, Path, float]:
    """The synthetic 1920x1080 clip in ``work`` (made on first use): (video, truth dataset, horizontal
    field of view in degrees of the 1920-pixel-wide frame). The truth is the 1080x1080 rendering; video
    frame i is its frame i."""
    from rmavatar.animate.video import frame_writer
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import SynthConfig, synthesize

    truth, video = work / "synth1080_truth", work / "synth1080.mp4"
    if not (truth / "meta.yaml").is_file():
        synthesize(truth, SynthConfig(size=SYNTH_SIDE, seed=0, train=SYNTH_TRAIN, test=SYNTH_TEST, novel_pose=0,
                                      ss=2), progress=progress)
    ds = load_dataset(truth)
    fx = float(ds.camera("train", 0).K[0, 0])
    if not video.is_file():
        pad = (SYNTH_WIDTH - SYNTH_SIDE) // 2
        with frame_writer(video, ds.fps or 7.5, SYNTH_WIDTH, SYNTH_SIDE) as write:
            for i in sorted(set(ds.splits["train"] + ds.splits["test"])):
                frame = np.full((SYNTH_SIDE, SYNTH_WIDTH, 3), 255, np.uint8)  # the renderer's white background
                frame[:, pad:pad + SYNTH_SIDE] = _truth_image(truth, i)
                write(frame)
    return video, truth, math.degrees(2 * math.atan(SYNTH_WIDTH / 2 / fx))


def _truth_image(truth: Path, i: int) -> np.ndarray:
    from PIL import Image

    with Image.open(truth / "images" / f"{i:05d}.png") as im:
        return np.asarray(im.convert("RGB"))


def _iou_size(data: Path, side: int) -> tuple[dict, int, int]:
    """A captured dataset's meta.yaml and its image size scaled to at most ``side`` pixels on the longer
    side (width, height)."""
    import yaml

    from rmavatar.data.dataset import target_size

    meta = yaml.safe_load((data / "meta.yaml").read_text())
    w, h = int(meta["width"]), int(meta["height"])
    return (meta, *target_size(w, h, min(side, max(w, h))))


def captured_masks(data: Path, side: int = IOU_SIDE) -> np.ndarray:
    """The masks of a captured dataset's clip frames [N,h,w] float 0..1, at most ``side`` pixels on the
    longer side, in dataset frame order (those :func:`body_silhouettes` is compared with)."""
    from rmavatar.data.io import read_mask, resample

    _, tw, th = _iou_size(data, side)
    return np.stack([resample(read_mask(data / "masks" / f"{i:05d}.png"), tw, th) for i in range(_clip_frames(data))])


def _clip_frames(data: Path) -> int:
    """How many of a captured dataset's frames are the clip's own (the main camera's; other calibrated
    cameras' frames, split novel_view, come after them)."""
    with np.load(data / "capture.npz") as z:
        return len(z["source_index"])


def body_silhouettes(data: Path, side: int = IOU_SIDE, offsets=True) -> np.ndarray:
    """The fitted body's silhouettes [N,h,w] bool of a captured dataset, at most ``side`` pixels on the
    longer side, dataset frame order. ``offsets``: True, the body with the dataset's offsets (smpl.npz
    ``body_offsets``, its fitted shape; the preset without them); False, the preset; or offsets [V] to
    try."""
    import torch

    from rmavatar.body import load_body_model
    from rmavatar.capture.sheet import body_silhouette

    meta, tw, th = _iou_size(data, side)
    w, h = int(meta["width"]), int(meta["height"])
    K = np.load(data / "cameras.npz")["K"].astype(np.float64)
    K = np.diag([tw / w, th / h, 1.0]) @ (K if K.ndim == 2 else K[0])
    with np.load(data / "smpl.npz") as z:
        params = {k: torch.as_tensor(z[k]) for k in ("betas", "global_orient", "body_pose", "transl")}
        stored = z["body_offsets"] if "body_offsets" in z.files else None
    if offsets is True:
        offsets = stored
    body = load_body_model(meta["body"], offsets=None if offsets is False else offsets)
    n = _clip_frames(data)
    betas = None
    if int(getattr(body, "num_betas", 0)):
        betas = params["betas"].reshape(-1, 10)[:, : body.num_betas].expand(n, -1)
    faces = body.faces.numpy()
    sil = []
    with torch.no_grad():
        for start in range(0, n, 32):
            sl = slice(start, min(start + 32, n))
            out = body(None if betas is None else betas[sl], params["global_orient"][sl], params["body_pose"][sl],
                       params["transl"][sl])
            for v in out.vertices.numpy().astype(np.float64):
                sil.append(body_silhouette(v, faces, K, tw, th))
    return np.stack(sil)


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-frame intersection over union of boolean stacks [N,h,w] -> [N] (1 where both are empty)."""
    inter = (a & b).reshape(len(a), -1).sum(1)
    union = (a | b).reshape(len(a), -1).sum(1)
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def assess(data: Path, truth: Path | None = None, truth_pad: int = 0) -> dict:
    """What a captured dataset ``data`` says about the capture: share of visible landmarks, silhouette IoU
    of the fitted body with the masks; with ``truth`` (the synthetic dataset the clip was rendered from,
    ``truth_pad`` pixels padded on each side of its width in the clip) the fit's joint errors and the
    IoU of the masks with the true ones."""
    masks = captured_masks(data)
    sil, preset = body_silhouettes(data), body_silhouettes(data, offsets=False)
    with np.load(data / "capture.npz") as z:
        visible = float((z["visibility"] > 0.5).mean())
        source = z["source_index"]
    out = {"landmarks_visible": round(visible, 4),
           "silhouette_iou": round(float(iou(sil, masks > 0.5).mean()), 4),
           "silhouette_iou_preset": round(float(iou(preset, masks > 0.5).mean()), 4)}
    if truth is not None:
        out["truth"] = _against_truth(data, truth, source, truth_pad)
    return out


def _against_truth(data: Path, truth: Path, source: np.ndarray, pad: int) -> dict:
    """The fit against the synthetic truth: 2D joint error (% of height), root-aligned 3D joint error
    (mm) over the 24 joints, and the IoU of the masks written with the true masks (at their own size,
    the clip's padding cut off)."""
    import torch
    import yaml

    from rmavatar.body import load_body_model
    from rmavatar.data.io import read_mask, resample

    meta = yaml.safe_load((data / "meta.yaml").read_text())
    w, h = int(meta["width"]), int(meta["height"])
    true = np.load(truth / "smpl_true.npz")
    cams = np.load(truth / "cameras.npz")
    fit = np.load(data / "smpl.npz")
    K = np.load(data / "cameras.npz")["K"].astype(np.float64)
    tbody = load_body_model(yaml.safe_load((truth / "meta.yaml").read_text())["body"])
    fbody = load_body_model(meta["body"])
    betas = None
    if int(getattr(fbody, "num_betas", 0)):
        betas = torch.as_tensor(fit["betas"]).reshape(-1, 10)[:, : fbody.num_betas].expand(len(source), -1)
    with torch.no_grad():
        t = tbody(None, *(torch.tensor(true[k][source]) for k in ("global_orient", "body_pose", "transl")))
        f = fbody(betas, *(torch.tensor(fit[k]) for k in ("global_orient", "body_pose", "transl")))
    V = cams["viewmat"][source].astype(np.float64)
    cam = lambda x: np.einsum("nij,nkj->nki", V[:, :3, :3], x.numpy()) + V[:, None, :3, 3]  # noqa: E731
    jt, vt, jf = cam(t.joints), cam(t.vertices), f.joints.numpy().astype(np.float64)
    tw = int(yaml.safe_load((truth / "meta.yaml").read_text())["width"])
    scale = w / (tw + 2 * pad)  # truth pixels -> the dataset's pixels
    Kt = cams["K"][source].astype(np.float64)
    Kt = Kt + np.array([[0, 0, pad], [0, 0, 0], [0, 0, 0]])
    Kt = np.diag([scale, scale, 1.0]) @ Kt

    def proj(x, k):
        return x[..., :2] / x[..., 2:] * k[..., None, [0, 1], [0, 1]] + k[..., None, :2, 2]

    ys = proj(vt, Kt)[..., 1]
    height = ys.max(1) - ys.min(1)
    e2 = np.linalg.norm(proj(jt, Kt) - proj(jf, np.broadcast_to(K, Kt.shape)), axis=-1) / height[:, None] * 100
    e3 = np.linalg.norm((jt - jt[:, :1]) - (jf - jf[:, :1]), axis=-1) * 1000
    ious = []
    for n, s in enumerate(source):
        m = read_mask(data / "masks" / f"{n:05d}.png")
        x0, x1 = round(pad * scale), w - round(pad * scale)
        m = m[:, x0:x1]
        tm = read_mask(truth / "masks" / f"{int(s):05d}.png")
        if tm.shape != m.shape:
            tm = resample(tm, m.shape[1], m.shape[0])
        ious.append(iou((m > 0.5)[None], (tm > 0.5)[None])[0])
    return {"joint_2d_percent_height": round(float(e2.mean()), 3),
            "joint_3d_root_aligned_mm": round(float(e3.mean()), 1),
            "mask_iou": round(float(np.mean(ious)), 4)}


def run(opts) -> int:
    """``opts``: the options of ``rmavatar bench capture`` (input, size, fps, frames, still, fov, device,
    work, json, overwrite)."""
    from rmavatar.bench.timing import machine_info
    from rmavatar.capture import CaptureConfig, capture
    from rmavatar.capture.fit import BodyFitConfig
    from rmavatar.utils.outputs import write_json

    from rmavatar.capture.pipeline import DATASET_KIND, DATASET_NAMES
    from rmavatar.utils.outputs import check_output_folder

    keep = opts.work is not None
    work = Path(opts.work) if keep else Path(tempfile.mkdtemp(prefix="rmavatar-bench-capture."))
    if keep:  # the captured dataset's folder follows the output rule; checked before the clip is made
        check_output_folder(work / "captured", DATASET_KIND, option="--work", overwrite=opts.overwrite,
                            writes=DATASET_NAMES)
    work.mkdir(parents=True, exist_ok=True)
    try:
        truth, pad, fov = None, 0, opts.fov
        if opts.input is None:
            clip, truth, true_fov = synthetic_clip(work, progress=not opts.quiet)
            fov, pad = (fov if fov is not None else true_fov), (SYNTH_WIDTH - SYNTH_SIDE) // 2
            # the turn is held in an A-pose: captured as the recording instructions ask
            still = True
        else:
            clip, still = Path(opts.input), opts.still
        fit = BodyFitConfig().still() if still else BodyFitConfig()
        cfg = CaptureConfig(fov=fov, size=opts.size, fps=opts.fps, frames=opts.frames, device=opts.device, fit=fit)
        before = machine_info()["load_average"]
        s = capture(clip, work / "captured", cfg, progress=not opts.quiet, overwrite=opts.overwrite)
        after = machine_info()["load_average"]
        n = s["decoded"]
        per = {k: round(v / n, 4) for k, v in s["seconds"].items()}
        per["other"] = round(s["total_seconds"] / n - sum(s["seconds"].values()) / n, 4)
        per["total"] = round(s["total_seconds"] / n, 4)
        kept = sum(s["frames"].values())
        report = {
            "benchmark": "capture",
            "input": str(clip) if opts.input is not None else f"synthetic {SYNTH_WIDTH}x{SYNTH_SIDE} turn (seed 0)",
            "options": {"size": opts.size, "fps": opts.fps, "frames": opts.frames, "still": still, "fov": fov,
                        "device": opts.device},
            "frame_size": [s["camera"]["width"], s["camera"]["height"]],
            "detection_size": s["detection_size"],
            "frames_decoded": n,
            "frames_with_person": kept,
            "share_with_person": round(kept / max(n, 1), 4),
            "frames_looked_at_first": len(s["looked_at"]),
            "seconds_per_frame": per,
            "cpu_seconds_per_frame": {k: round(v / n, 4) for k, v in s["cpu_seconds"].items()},
            "shape": None if s["shape"] is None else {k: v for k, v in s["shape"].items() if k != "losses"},
            **assess(work / "captured", truth, pad),
            "machine": {**machine_info(), "load_average_before": before, "load_average_after": after},
        }
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(report, indent=2))
    if opts.json:
        write_json(opts.json, report, overwrite=opts.overwrite)
        print(f"wrote {opts.json}")
    return 0
