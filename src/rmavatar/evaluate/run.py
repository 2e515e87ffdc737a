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
from dataclasses import dataclass
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


@dataclass
class _Evaluation:
    """An evaluation's run, data and settings, once opened and checked."""

    run: Any  # the TrainedAvatar
    dataset: Any
    spec: Any  # the dataset spec evaluated on
    split: str
    total: int  # frames in the split
    n: int  # frames evaluated: the first n
    params: dict  # the split's body parameters (betas, poses, frame numbers)
    device: torch.device
    background: torch.Tensor  # [3] on the device, behind render and ground truth alike


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
    the first N frames of the split; fit: a :class:`rmavatar.evaluate.fit.PoseFitConfig` to fit every frame's pose
    to its image before scoring (the avatar and its checkpoint stay untouched), or None.

    Returns {"protocol": {...}, "frames": [{"position", "index", "psnr", "ssim", "lpips"}, ...],
    "mean": {"psnr", "ssim", "lpips"}}, and for a synthetic subject with true poses "pose_error" (the
    used poses' error, see :func:`rmavatar.body.pose_error`). A PSNR of infinity is None.
    """
    if bg not in BACKGROUNDS:
        raise UserError(f"background must be one of {', '.join(BACKGROUNDS)}, not {bg!r}")
    if size is not None and size < 32:
        raise UserError(f"size must be at least 32 pixels (LPIPS needs 32x32), got {size}")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"max_frames must be >= 1, got {max_frames}")
    if out_dir is not None:
        out_dir = Path(out_dir)
        check_images_dir(out_dir, overwrite)
    ev = _open(run_dir, data, split, bg, size, device, max_frames)
    if fit is not None and split in ev.dataset.same_instant:
        raise UserError(f"--fit-poses on split {split} would fit each pose to the very view it scores: that "
                        f"split's frames are another camera's views of the clip's instants, posed as the run "
                        f"posed those instants (from the training camera); score it without --fit-poses")
    poses, pose_source, errors = _choose_poses(ev, fit, progress)
    with contextlib.ExitStack() as stack:
        # Images go to a temporary folder that replaces out_dir only once every frame is done.
        tmp_dir = stack.enter_context(
            output_folder(out_dir, IMAGES_KIND, option="--images", overwrite=overwrite,
                          writes=("*.png", IMAGES_MARKER))) if out_dir is not None else None
        rows = _score_frames(ev, poses, tmp_dir, progress)
        result = _result(ev, run_dir, bg, fit, pose_source, rows, errors)
        if tmp_dir is not None:
            (tmp_dir / IMAGES_MARKER).write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    return result


def _open(run_dir, data, split: str, bg: str, size: int | None, device: str, max_frames: int | None) -> _Evaluation:
    """Load the run and the dataset (the run's own unless ``data``, at the run's size unless ``size``)
    and check that the split's images are large enough to score."""
    from rmavatar.avatar.trained import load_trained
    from rmavatar.data import load_dataset

    dev = resolve_device(device)
    run = load_trained(run_dir, device=dev)
    spec = data if data is not None else run.data_spec
    dataset = load_dataset(spec, size=run.size if size is None else size)
    total = dataset.num_frames(split)  # a UserError naming the splits there are when missing
    n = total if max_frames is None else min(total, max_frames)
    params = dataset.params(split)
    width, height = dataset.image_size
    if min(width, height) < 32:
        raise UserError(f"images of {width}x{height} are too small to score (LPIPS needs 32x32); pass a larger size")
    background = torch.tensor(BACKGROUNDS[bg], dtype=torch.float32, device=dev)
    return _Evaluation(run, dataset, spec, split, total, n, params, dev, background)


def _choose_poses(ev: _Evaluation, fit, progress: bool):
    """The poses of the first ``ev.n`` frames: the dataset's, or the run's refined ones on its own
    training frames; with ``fit``, smoothed (only the dataset's) and then fitted to each image.
    Returns (poses, where they come from in words, their errors against the true poses or None)."""
    from rmavatar.body import PoseSequence, pose_error, smooth_poses
    from rmavatar.data.synth import true_poses

    run, params, n = ev.run, ev.params, ev.n
    given = PoseSequence.from_params(params)
    if not run.config.get("data", {}).get("hand_pose", True):  # trained with relaxed hands: shown so
        given.hand_pose = None
    poses, pose_source = given, "the dataset's"
    from rmavatar.data.registry import same_dataset

    # The run's own data is recognised by its resolved path ('DATA/', './DATA' and 'DATA' are one dataset).
    own = run.training_poses is not None and same_dataset(ev.spec, run.data_spec)
    if own and ev.split == run.training_split:
        poses, pose_source = run.training_poses, "refined in training"
    elif own and ev.split in ev.dataset.same_instant:  # another camera's view of training instants
        where = _training_positions(ev.dataset, run.training_split, ev.split)
        if where is not None:
            poses = run.training_poses.select(torch.as_tensor(where))
            pose_source = "refined in training, of the same instants (seen by the training camera)"
    if fit is not None and fit.smooth and pose_source == "the dataset's":
        poses = smooth_poses(poses, params["index"], fit.smooth)  # over the whole split, before the first n
        pose_source += f", averaged over +-{fit.smooth} frames"
    poses = poses.select(slice(0, n))
    if fit is not None:
        from rmavatar.evaluate.fit import fit_poses

        if progress:
            print(f"fitting the poses of {n} frames ({fit.steps} steps, {fit.batch} frames at a time) ...", flush=True)
        poses = fit_poses(run.avatar, run.body, poses, params["betas"][:n] if run.body.num_betas > 0 else None,
                          ev.dataset.frames(ev.split, n), ev.background, fit)
        pose_source += ", then fitted to each test image"
    truth = true_poses(ev.dataset, ev.split)
    errors = None
    if truth is not None:
        truth = truth.select(slice(0, n))
        errors = {"given": pose_error(given.select(slice(0, n)), truth), "used": pose_error(poses, truth)}
    return poses, pose_source, errors


def _training_positions(dataset, train_split: str, split: str) -> list[int] | None:
    """For each frame of ``split``, the position in ``train_split`` of the frame taken at the same instant
    (the dataset's ``same_instant``), or None when one of them is not a training frame."""
    order = {index: k for k, index in enumerate(dataset.splits.get(train_split, []))}
    where = [order.get(i) for i in dataset.same_instant[split]]
    return None if None in where else where


@torch.no_grad()
def _score_frames(ev: _Evaluation, poses, tmp_dir: Path | None, progress: bool) -> list[dict[str, Any]]:
    """Render and score the first ``ev.n`` frames with ``poses``: one row per frame; with ``tmp_dir``,
    each frame's side-by-side image is written there."""
    from tqdm import tqdm

    rows: list[dict[str, Any]] = []
    bar = tqdm(range(ev.n), desc=f"eval {ev.split}", unit="frame", disable=not progress, dynamic_ncols=True)
    for i in bar:
        frame, render, target = _render_and_target(ev, poses, i)
        row = {"position": i, "index": int(frame.index), **_scores(render, target)}
        rows.append(row)
        bar.set_postfix(psnr=f"{row['psnr']:.2f}", refresh=False)
        if tmp_dir is not None:
            _write_side_by_side(tmp_dir / f"{ev.split}_{i:04d}_frame{int(frame.index):05d}.png", render, target)
    bar.close()
    return rows


def _render_and_target(ev: _Evaluation, poses, i: int):
    """Frame ``i``, its render (clamped to [0, 1]) and its ground truth, both over the background."""
    from rmavatar.avatar.frame import render_frame
    from rmavatar.body import posed_vertices
    from rmavatar.render import composite

    frame = ev.dataset.frame(ev.split, i)
    one = poses.select(slice(i, i + 1))
    verts = posed_vertices(ev.run.body, one, ev.params["betas"][i : i + 1])[0]  # the frame's own shape
    pose = ev.run.avatar.pose_input(one.body_pose[0], one.hand(0))
    drawn = render_frame(ev.run.avatar, verts, pose.to(ev.device), frame.camera, ev.background)
    mask = torch.tensor(frame.mask, dtype=torch.float32, device=ev.device)
    target = composite(torch.tensor(frame.image, dtype=torch.float32, device=ev.device), mask, ev.background)
    return frame, drawn.image.clamp(0.0, 1.0), target


def _scores(render: torch.Tensor, target: torch.Tensor) -> dict[str, float]:
    from rmavatar.evaluate.metrics import lpips, psnr, ssim

    return {"psnr": float(psnr(render, target)), "ssim": float(ssim(render, target)),
            "lpips": float(lpips(render, target))}


def _write_side_by_side(path: Path, render: torch.Tensor, target: torch.Tensor) -> None:
    from PIL import Image

    Image.fromarray(side_by_side(render.cpu().numpy(), target.cpu().numpy())).save(path)


def _result(ev: _Evaluation, run_dir, bg: str, fit, pose_source: str, rows: list[dict[str, Any]],
            errors: dict | None) -> dict[str, Any]:
    """The evaluation's result: its protocol, the per-frame rows and their means (JSON-ready)."""
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("psnr", "ssim", "lpips")}
    result = {
        "protocol": _protocol(ev, run_dir, bg, fit, pose_source),
        "frames": [{**r, "psnr": _finite_or_none(r["psnr"])} for r in rows],
        "mean": {**mean, "psnr": _finite_or_none(mean["psnr"])},
    }
    if errors is not None:
        result["pose_error"] = errors
    return result


def _protocol(ev: _Evaluation, run_dir, bg: str, fit, pose_source: str) -> dict[str, Any]:
    run = ev.run
    return {
        "run": str(Path(run_dir).resolve()),
        "iteration": run.iteration,
        "body": str(getattr(run.body, "spec", "")),
        "rectifier": run.avatar.config.rectifier,  # the design's name ("local", "paper") or False
        "data": str(ev.spec),
        "split": ev.split,
        "frames": ev.n,
        "frames_in_split": ev.total,
        "resolution": list(ev.dataset.image_size),
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
        "device": str(ev.device),
        "rmavatar_version": __version__,
    }
