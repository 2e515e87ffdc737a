"""Measure `rmavatar capture` on a synthetic subject whose true poses are known.

    PYTHONPATH=src python scripts/measure_capture.py WORK [--size 256] [--seed 0] [--iters 1000]
        [--refine-poses auto|on|off] [--no-still] [--skip-training] [--json OUT]

Makes the subject (`rmavatar synth`, default 100 train + 30 test + 30 novel-pose frames), renders its
turn (train + test frames) and its novel motion into MP4s, captures both with the true field of view
(the turn, where the subject holds its A-pose, with ``--still``; with --no-still, without it, into
``WORK/captured_turn_free``), and reports the fitted body against the truth per split: mean 2D joint
error (% of the body's height in the image), root-aligned 3D joint error (mm) over the 24 joints, the
IoU of the masks written with the true masks (``mask_iou``), and the mean 2D distance (px) of the
body's vertices the true image shows from where the fitted body puts them (``visible_vertex_px``: what
an avatar trained on the poses has to reconcile).
Unless --skip-training, it then trains one avatar on the true poses and one on the captured turn with
the demo's config (--iters, max 40k Gaussians, seed 0) and evaluates both on the synthetic dataset's
test and novel_pose splits (true poses, the run's own body), and on test after fitting every frame's
pose to its image (100 steps from the true poses); both also on the same test images posed with the
captured test poses, as given and fitted from them (``WORK/captured_turn_true_images``: the captured
dataset with the truth's images and masks), and it reports the same errors of the training poses
the captured avatar was trained on (``training_poses``: its first pass's refined ones, and the
refits'). --refine-poses sets the captured-data run's ``poses.refine`` (auto: on, as the
captured dataset says its poses are estimated); its run is ``WORK/run_captured`` for auto and
``WORK/run_captured_refine_{on,off}`` otherwise (``_free`` appended with --no-still). Everything goes under WORK; finished steps are reused.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import yaml


def write_video(truth: Path, path: Path, frames: list[int], fps: float) -> None:
    from rmavatar.animate.video import frame_writer
    from rmavatar.data.io import read_image

    first = read_image(truth / "images" / f"{frames[0]:05d}.png")
    with frame_writer(path, fps, first.shape[1], first.shape[0]) as write:
        for i in frames:
            write((read_image(truth / "images" / f"{i:05d}.png") * 255 + 0.5).astype(np.uint8))


def visible_vertices(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int,
                     tolerance: float = 0.01) -> np.ndarray:
    """Which camera-frame vertices [V,3] of a mesh the camera sees [V] bool: the vertex's pixel holds no
    surface more than ``tolerance`` metres nearer (a z-buffer of the mesh itself, one sample per pixel)."""
    from rmavatar.data.synth.raster import rasterize

    depth = rasterize(vertices, faces, K, width, height, ss=1).depth
    u = vertices[:, 0] / vertices[:, 2] * K[0, 0] + K[0, 2]
    v = vertices[:, 1] / vertices[:, 2] * K[1, 1] + K[1, 2]
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    c, r = np.clip(u.astype(int), 0, width - 1), np.clip(v.astype(int), 0, height - 1)
    return inside & (vertices[:, 2] <= depth[r, c] + tolerance)


def fit_errors(truth: Path, captured: Path, first: int, poses: Path | None = None) -> dict:
    """Per split of the captured dataset: mean 2D joint error (% of height) and root-aligned 3D joint
    error (mm) over the 24 joints, and the mean 2D distance (px) of the body's vertices the true image
    shows from where the fitted body puts them (what an avatar trained on the poses sees); ``first``
    is the synthetic frame the video started at; ``poses``: a run's ``poses.npz`` (refined training
    poses) replacing the fit's poses of its frames."""
    from rmavatar.body import load_body_model

    true = np.load(truth / "smpl_true.npz")
    cams = np.load(truth / "cameras.npz")
    meta = yaml.safe_load((captured / "meta.yaml").read_text())
    fit = dict(np.load(captured / "smpl.npz"))
    if poses is not None:
        with np.load(poses) as p:
            for k in ("global_orient", "body_pose", "transl"):
                fit[k] = fit[k].copy()
                fit[k][p["index"]] = p[k]
    K = np.load(captured / "cameras.npz")["K"]
    src = np.load(captured / "capture.npz")["source_index"] + first
    tbody = load_body_model(yaml.safe_load((truth / "meta.yaml").read_text())["body"])
    fbody = load_body_model(meta["body"])
    betas = torch.tensor(fit["betas"])[None].expand(len(src), -1) if fbody.num_betas else None
    with torch.no_grad():
        t = tbody(None, *(torch.tensor(true[k][src]) for k in ("global_orient", "body_pose", "transl")))
        f = fbody(betas, *(torch.tensor(fit[k]) for k in ("global_orient", "body_pose", "transl")))
    V = cams["viewmat"][src]
    cam = lambda x: np.einsum("nij,nkj->nki", V[:, :3, :3], x.numpy()) + V[:, None, :3, 3]  # noqa: E731
    jt, vt, jf = cam(t.joints), cam(t.vertices), f.joints.numpy()
    Kt = cams["K"][src]
    proj = lambda x, k: x[..., :2] / x[..., 2:] * k[..., None, [0, 1], [0, 1]] + k[..., None, :2, 2]  # noqa: E731
    ys = proj(vt, Kt)[..., 1]
    height = ys.max(1) - ys.min(1)
    e2 = np.linalg.norm(proj(jt, Kt) - proj(jf, np.broadcast_to(K, Kt.shape)), axis=-1) / height[:, None] * 100
    e3 = np.linalg.norm((jt - jt[:, :1]) - (jf - jf[:, :1]), axis=-1) * 1000
    ev = None
    if tbody.faces.shape == fbody.faces.shape and bool((tbody.faces == fbody.faces).all()):
        tmeta = yaml.safe_load((truth / "meta.yaml").read_text())
        w, h = int(tmeta["width"]), int(tmeta["height"])
        faces = tbody.faces.numpy()
        seen = np.stack([visible_vertices(vt[n], faces, Kt[n], w, h) for n in range(len(src))])
        d = np.linalg.norm(proj(vt, Kt) - proj(f.vertices.numpy(), np.broadcast_to(K, Kt.shape)), axis=-1)
        ev = (d * seen).sum(1) / seen.sum(1).clip(1)
    iou = mask_ious(truth, captured, src)
    out = {}
    for split, idx in meta["splits"].items():
        out[split] = {"frames": len(idx), "joint_2d_percent_height": round(float(e2[idx].mean()), 3),
                      "joint_3d_root_aligned_mm": round(float(e3[idx].mean()), 1),
                      "mask_iou": round(float(iou[idx].mean()), 4)}
        if ev is not None:
            out[split]["visible_vertex_px"] = round(float(ev[idx].mean()), 3)
    return out


def mask_ious(truth: Path, captured: Path, source: np.ndarray) -> np.ndarray:
    """IoU [N] of each captured mask (> 0.5) with the true mask of its source frame (> 0.5)."""
    from rmavatar.data.io import read_mask

    out = []
    for n, s in enumerate(source):
        a = read_mask(captured / "masks" / f"{n:05d}.png") > 0.5
        b = read_mask(truth / "masks" / f"{int(s):05d}.png") > 0.5
        out.append((a & b).sum() / max((a | b).sum(), 1))
    return np.asarray(out)


def with_true_images(truth: Path, captured: Path, out: Path) -> Path:
    """A copy of the captured dataset (its poses and camera) holding the truth's images and masks of the
    same frames: the captured test poses on the true images, to score any avatar with them."""
    import shutil

    if (out / "meta.yaml").is_file():
        return out
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(captured, tmp)
    for i, s in enumerate(np.load(captured / "capture.npz")["source_index"]):
        for folder in ("images", "masks"):
            shutil.copyfile(truth / folder / f"{s:05d}.png", tmp / folder / f"{i:05d}.png")
    tmp.rename(out)
    return out


def train_and_eval(data: Path, run: Path, truth: Path, iters: int, size: int, refine: bool | None = None,
                   captured_poses: Path | None = None) -> dict:
    from rmavatar.evaluate import evaluate_run
    from rmavatar.evaluate.fit import PoseFitConfig
    from rmavatar.train import TrainConfig, train

    if not (run / "checkpoints" / "last.pt").is_file():
        cfg = TrainConfig()
        cfg.data.path, cfg.data.size, cfg.optim.iters = str(data), size, iters
        cfg.seed, cfg.density.max_gaussians = 0, 40_000
        cfg.poses.refine = refine
        t = time.perf_counter()
        train(cfg, run, progress=True)
        print(f"trained {run} in {time.perf_counter() - t:.0f} s")
    out = {}
    for split, fit in (("test", None), ("novel_pose", None), ("test_fitted", PoseFitConfig(smooth=0))):
        res = evaluate_run(run, data=str(truth), split=split.removesuffix("_fitted"), progress=False, fit=fit)
        out[split] = {k: round(float(v), 4) for k, v in res["mean"].items()}
    if captured_poses is not None:  # the same test images, posed and fitted from the captured test poses
        for split, fit in (("test_captured_poses", None), ("test_fitted_from_captured", PoseFitConfig(smooth=0))):
            res = evaluate_run(run, data=str(captured_poses), split="test", progress=False, fit=fit)
            out[split] = {k: round(float(v), 4) for k, v in res["mean"].items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("work")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--refine-poses", choices=("auto", "on", "off"), default="auto")
    parser.add_argument("--no-still", action="store_true", help="capture the turn without --still")
    parser.add_argument("--skip-training", action="store_true")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()

    from rmavatar.capture import CaptureConfig, capture
    from rmavatar.capture.fit import BodyFitConfig
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import SynthConfig, synthesize

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    truth = work / "truth"
    if not (truth / "meta.yaml").is_file():
        synthesize(truth, SynthConfig(size=args.size, seed=args.seed))
    ds = load_dataset(truth)
    fx = float(ds.camera("train", 0).K[0, 0])
    fov = math.degrees(2 * math.atan(ds.image_size[0] / 2 / fx))
    result = {"fov": fov, "fit": {}, "seconds_per_frame": {}}
    clips = {"turn": ds.splits["train"] + ds.splits["test"], "novel": ds.splits["novel_pose"]}
    free = "_free" if args.no_still else ""  # the turn's capture and run without --still
    captured = {"turn": work / f"captured_turn{free}", "novel": work / "captured_novel"}
    for name, frames in clips.items():
        video, out = work / f"{name}.mp4", captured[name]
        if not video.is_file():
            write_video(truth, video, frames, ds.fps or 7.5)
        if not (out / "meta.yaml").is_file():
            still = name == "turn" and not args.no_still
            fit = BodyFitConfig().still() if still else BodyFitConfig()
            # the turn's test tail is the truth's test split, so that no test frame is trained on
            test = len(ds.splits["test"]) / len(frames) if name == "turn" else 0.2
            s = capture(video, out, CaptureConfig(fov=fov, fit=fit, test_fraction=test), progress=True)
            result["seconds_per_frame"][name] = s["seconds_per_frame"]
        result["fit"][name] = fit_errors(truth, out, frames[0])
    print(json.dumps(result, indent=1))
    if not args.skip_training:
        hybrid = with_true_images(truth, captured["turn"], work / f"captured_turn{free}_true_images")
        result["avatar_true_poses"] = train_and_eval(truth, work / "run_true", truth, args.iters, args.size,
                                                     captured_poses=hybrid)
        refine = {"auto": None, "on": True, "off": False}[args.refine_poses]
        run = work / (("run_captured" if refine is None else f"run_captured_refine_{args.refine_poses}") + free)
        result["refine_poses"] = args.refine_poses
        result["avatar_captured"] = train_and_eval(captured["turn"], run, truth, args.iters, args.size, refine,
                                                   captured_poses=hybrid)
        # the poses the captured avatar trained on: the first pass's refined ones, and the refits' (if any)
        for name, path in (("first_pass", run / "pose_pass" / "poses.npz"), ("trained_on", run / "poses.npz")):
            if path.is_file():
                result.setdefault("training_poses", {})[name] = fit_errors(truth, captured["turn"], clips["turn"][0],
                                                                           path)["train"]
        print(json.dumps({k: result[k] for k in ("avatar_true_poses", "avatar_captured", "training_poses") if k in result},
                         indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
