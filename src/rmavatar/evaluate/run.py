"""Evaluate a trained run on a dataset split with a stated protocol: ``evaluate_run``.

Protocol (written into the result): full images (not masked); the ground truth is the frame composited
over the chosen background with its mask (as in training); the render uses the same background and is
clamped to [0, 1]; the dataset's own poses are used (the run's refined ones on its own training frames),
unless ``fit`` asks for test-time pose fitting (:mod:`rmavatar.evaluate.fit`); PSNR, SSIM and LPIPS as
defined in :mod:`rmavatar.evaluate.metrics`, computed per frame and then averaged.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rmavatar import __version__
from rmavatar.utils import UserError, resolve_device
from rmavatar.utils.outputs import check_output_folder, output_folder

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
# The error heat map spans mean absolute error 0 .. HEAT_MAX (per pixel, averaged over RGB).
HEAT_MAX = 0.25
# A copy of the result beside the images; the folder's ownership marker is rmavatar.utils.outputs'.
IMAGES_MARKER = "metrics.json"
IMAGES_KIND = "eval-images"

# A perceptually ordered dark-to-bright ramp (anchors of matplotlib's "inferno", as plain numbers).
_HEAT_ANCHORS = np.array(
    [[0, 0, 4], [87, 16, 110], [188, 55, 84], [249, 142, 9], [252, 255, 164]], dtype=np.float64
) / 255.0


def heat_map(render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per-pixel mean absolute RGB error [H,W] mapped to colours [H,W,3] in [0,1]; HEAT_MAX and above
    are the brightest colour."""
    err = np.abs(render.astype(np.float64) - target.astype(np.float64)).mean(-1)
    t = np.clip(err / HEAT_MAX, 0.0, 1.0)
    xs = np.linspace(0.0, 1.0, len(_HEAT_ANCHORS))
    return np.stack([np.interp(t, xs, _HEAT_ANCHORS[:, c]) for c in range(3)], -1)


def side_by_side(render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """render | ground truth | error heat map, as uint8 [H, 3W, 3]."""
    row = np.concatenate([render, target, heat_map(render, target)], axis=1)
    return (np.clip(row, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _finite_or_none(value: float) -> float | None:
    """JSON has no infinity: PSNR of a pixel-exact render is written as null."""
    return float(value) if math.isfinite(value) else None


def check_images_dir(path: Path, overwrite: bool = False) -> None:
    """Refuse an images folder that holds files an earlier evaluation did not write (see utils.outputs)."""
    check_output_folder(path, IMAGES_KIND, option="--images", overwrite=overwrite,
                        writes=("*.png", IMAGES_MARKER))


def evaluate_run(
    run_dir: str | os.PathLike,
    data: str | None = None,
    split: str = "test",
    bg: str = "white",
    size: int | None = None,
    out_dir: str | os.PathLike | None = None,
    *,
    device: str = "auto",
    max_frames: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
    fit=None,
) -> dict[str, Any]:
    """Render every frame of ``split`` with the run's avatar and score it against the ground truth.

    run_dir: a training run (``RUN/checkpoints/last.pt``); data: dataset spec (default: the run's own);
    split: a split of the dataset ("test", "novel_pose", "val", "novel_view", "train");
    bg: "white" or "black"; size: longer image side in pixels (default: the size the run was trained
    at; None there means the dataset's own); device: "auto" (CUDA when available), "cpu", "cuda[:N]";
    out_dir: where to write side-by-side images (render | ground truth | error heat map) and a copy of
    the result (``metrics.json``), or None for no images; replaced atomically, and only if it is empty
    or an earlier evaluation's (``overwrite``: see :mod:`rmavatar.utils.outputs`); max_frames: evaluate only
    the first N frames of the split; fit: a :class:`rmavatar.evaluate.fit.FitConfig` to fit every frame's pose
    to its image before scoring (the avatar and its checkpoint stay untouched), or None.

    Returns {"protocol": {...}, "frames": [{"position", "index", "psnr", "ssim", "lpips"}, ...],
    "mean": {"psnr", "ssim", "lpips"}}, and for a synthetic subject with true poses "pose_error" (the
    used poses' error, see :func:`rmavatar.body.pose_error`). A PSNR of infinity is None.
    """
    from PIL import Image
    from tqdm import tqdm

    from rmavatar.avatar.trained import load_trained
    from rmavatar.body import PoseSequence, pose_error, posed_vertices, smooth_poses
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import true_poses
    from rmavatar.evaluate.metrics import lpips, psnr, ssim

    if bg not in BACKGROUNDS:
        raise UserError(f"background must be one of {', '.join(BACKGROUNDS)}, not {bg!r}")
    if size is not None and size < 32:
        raise UserError(f"size must be at least 32 pixels (LPIPS needs 32x32), got {size}")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"max_frames must be >= 1, got {max_frames}")
    if out_dir is not None:
        out_dir = Path(out_dir)
        check_images_dir(out_dir, overwrite)

    dev = resolve_device(device)
    run = load_trained(run_dir, device=dev)
    spec = data if data is not None else run.data_spec
    if size is None:
        size = run.size
    dataset = load_dataset(spec, size=size)
    total = dataset.num_frames(split)  # a UserError naming the splits there are when missing
    n = total if max_frames is None else min(total, max_frames)
    params = dataset.params(split)
    given = PoseSequence.from_arrays(params["global_orient"], params["body_pose"], params["transl"])
    poses, pose_source = given, "the dataset's"
    if run.training_poses is not None and split == run.training_split and spec == run.data_spec:
        poses, pose_source = run.training_poses, "refined in training"
    width, height = dataset.image_size
    if min(width, height) < 32:
        raise UserError(f"images of {width}x{height} are too small to score (LPIPS needs 32x32); pass a larger size")
    background = torch.tensor(BACKGROUNDS[bg], dtype=torch.float32, device=dev)
    if fit is not None and fit.smooth and pose_source == "the dataset's":
        poses = smooth_poses(poses, params["index"], fit.smooth)  # over the whole split, before the first n
        pose_source += f", averaged over +-{fit.smooth} frames"
    poses = poses.select(slice(0, n))
    if fit is not None:
        from rmavatar.evaluate.fit import fit_poses

        if progress:
            print(f"fitting the poses of {n} frames ({fit.steps} steps, {fit.batch} frames at a time) ...", flush=True)
        poses = fit_poses(run.avatar, run.body, poses, params["betas"][:n] if run.body.num_betas > 0 else None,
                          dataset.frames(split, n), background, fit)
        pose_source += ", then fitted to each test image"
    truth = true_poses(dataset, split)
    errors = None
    if truth is not None:
        truth = truth.select(slice(0, n))
        errors = {"given": pose_error(given.select(slice(0, n)), truth), "used": pose_error(poses, truth)}

    rows: list[dict[str, Any]] = []
    bar = tqdm(range(n), desc=f"eval {split}", unit="frame", disable=not progress, dynamic_ncols=True)
    with contextlib.ExitStack() as stack, torch.no_grad():
        # Images go to a temporary folder that replaces out_dir only once every frame is done.
        tmp_dir = stack.enter_context(
            output_folder(out_dir, IMAGES_KIND, option="--images", overwrite=overwrite,
                          writes=("*.png", IMAGES_MARKER))) if out_dir is not None else None
        for i in bar:
            frame = dataset.frame(split, i)
            one = poses.select(slice(i, i + 1))
            verts = posed_vertices(run.body, one, params["betas"][i : i + 1])[0]  # the frame's own shape
            gs = run.avatar(verts, one.body_pose[0].to(dev))
            image = run.render(gs, frame.camera, background)
            render = image.clamp(0.0, 1.0)
            mask = torch.tensor(frame.mask, dtype=torch.float32, device=dev)[..., None]
            target = torch.tensor(frame.image, dtype=torch.float32, device=dev) * mask + background * (1 - mask)
            row = {
                "position": i,
                "index": int(frame.index),
                "psnr": float(psnr(render, target)),
                "ssim": float(ssim(render, target)),
                "lpips": float(lpips(render, target)),
            }
            rows.append(row)
            bar.set_postfix(psnr=f"{row['psnr']:.2f}", refresh=False)
            if tmp_dir is not None:
                name = f"{split}_{i:04d}_frame{int(frame.index):05d}.png"
                Image.fromarray(side_by_side(render.cpu().numpy(), target.cpu().numpy())).save(tmp_dir / name)
        bar.close()

        mean = {k: float(np.mean([r[k] for r in rows])) for k in ("psnr", "ssim", "lpips")}
        result = {
            "protocol": {
                "run": str(Path(run_dir).resolve()),
                "iteration": run.iteration,
                "body": str(getattr(run.body, "spec", "")),
                "rectifier": run.avatar.config.rectifier,  # the design's name ("local", "paper") or False
                "data": str(spec),
                "split": split,
                "frames": n,
                "frames_in_split": total,
                "resolution": [width, height],
                "background": bg,
                "image_region": "full image (not masked); ground truth = frame composited over the background "
                                "with its mask",
                "render_clamped": True,
                "pose_refinement": fit is not None,
                "fit_poses": fit.steps if fit is not None else None,
                "fit_poses_settings": fit.protocol() if fit is not None else None,
                "poses": pose_source,
                "psnr": "20 log10(1 / RMSE) per image (peak 1), then averaged over frames",
                "ssim": "11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, data range 1, mean over the valid "
                        "region and RGB; per image, then averaged",
                "lpips": "LPIPS v0.1, AlexNet backbone, inputs mapped to [-1, 1]; per image, then averaged",
                "device": str(dev),
                "rmavatar_version": __version__,
            },
            "frames": [{**r, "psnr": _finite_or_none(r["psnr"])} for r in rows],
            "mean": {**mean, "psnr": _finite_or_none(mean["psnr"])},
        }
        if errors is not None:
            result["pose_error"] = errors
        if tmp_dir is not None:
            (tmp_dir / IMAGES_MARKER).write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    return result
