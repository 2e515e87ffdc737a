"""Refit the body offsets of a captured dataset (``rmavatar capture`` / ``rmavatar bench capture --work``)
with other ShapeFitConfig settings, and report the silhouette IoU of the body with the dataset's masks
(at most 512 px on the longer side, as ``rmavatar bench capture``): the preset's, and each setting's.

    PYTHONPATH=src python scripts/measure_shape_fit.py DATA [--set min_offset=-0.03 --set silhouette=20 ...]
        [--set ...] [--truth TRUTH] [--json OUT]

Each ``--set`` is one run (comma-separated KEY=VALUE pairs of ShapeFitConfig; none: the defaults). The
poses held are the dataset's (smpl.npz), the masks its masks/ brought to the capture's fit size, as the
capture's own fit sees them. With --truth (the synthetic dataset that ``rmavatar bench capture`` renders
its 1920x1080 clip from, ``synth1080_truth`` in its --work) also the IoU with the true masks. Per run:
the IoU over all frames and over the frames the fit did not see, the worst frame's change, the offsets'
mean (over the vertices that may move) and extremes (mm), and seconds.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch
import yaml


def mask_observations(data: Path):
    """The capture's mask observations of a dataset: (Observations with no landmarks, params [T,...])."""
    from rmavatar.capture.fit import Observations, mask_maps
    from rmavatar.capture.pipeline import FIT_SIDE
    from rmavatar.data.dataset import target_size
    from rmavatar.data.io import read_mask, resample

    meta = yaml.safe_load((data / "meta.yaml").read_text())
    w, h = int(meta["width"]), int(meta["height"])
    K = np.load(data / "cameras.npz")["K"]
    params = dict(np.load(data / "smpl.npz"))
    T = len(params["global_orient"])
    small = target_size(w, h, min(FIT_SIDE, max(w, h)))
    full = [read_mask(data / "masks" / f"{i:05d}.png") > 0.5 for i in range(T)]
    masks = [resample(m.astype(np.float32), *small) > 0.5 for m in full]
    heights = [np.ptp(np.nonzero(m.any(1))[0]) + 1 for m in full]
    outside, outline, weight = mask_maps(masks, w)
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32))  # noqa: E731
    obs = Observations(keypoints=torch.zeros(T, 0, 2), visibility=torch.zeros(T, 0), world=torch.zeros(T, 0, 3),
                       outside=t(outside), K=t(K if K.ndim == 2 else K[0]), size=(w, h), gaps=torch.ones(T - 1),
                       height_px=float(np.median(heights)), outline=t(outline), outline_weight=t(weight))
    return obs, params, meta["body"]


def true_masks(data: Path, truth: Path, shape: tuple[int, int]):
    """The synthetic truth's masks in the IoU's frame: (masks [N,h,w'] bool, the columns x0:x1 they fill)."""
    from rmavatar.bench.capture import SYNTH_SIDE, SYNTH_WIDTH
    from rmavatar.data.io import read_mask, resample

    h, w = shape
    pad = round((SYNTH_WIDTH - SYNTH_SIDE) / 2 * w / SYNTH_WIDTH)
    source = np.load(data / "capture.npz")["source_index"]
    masks = [resample(read_mask(truth / "masks" / f"{int(s):05d}.png"), w - 2 * pad, h) > 0.5 for s in source]
    return np.stack(masks), pad, w - pad


def parse(text: str) -> dict:
    """"KEY=VALUE,..." -> ShapeFitConfig overrides (its field annotations are strings: "int", "float")."""
    from rmavatar.capture.shape import ShapeFitConfig

    kinds = {f.name: f.type for f in fields(ShapeFitConfig)}
    out = {}
    for pair in filter(None, text.split(",")):
        key, _, value = pair.partition("=")
        out[key] = int(value) if kinds[key] == "int" else float(value)
    return out


def main() -> None:
    from rmavatar.bench.capture import body_silhouettes, captured_masks, iou
    from rmavatar.body import load_body_model
    from rmavatar.capture.shape import ShapeFitConfig, fit_body_offsets

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path)
    ap.add_argument("--set", action="append", default=None, metavar="KEY=VALUE,...")
    ap.add_argument("--truth", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    obs, params, spec = mask_observations(args.data)
    body = load_body_model(spec)
    preset, masks = body_silhouettes(args.data, offsets=False), captured_masks(args.data) > 0.5
    before = iou(preset, masks)
    truth = true_masks(args.data, args.truth, masks.shape[1:]) if args.truth else None
    true_iou = (lambda s: round(float(iou(s[:, :, truth[1]:truth[2]], truth[0]).mean()), 4)) if truth else None
    report = {"data": str(args.data), "preset": {"iou": round(float(before.mean()), 4)}, "runs": []}
    if truth:
        report["preset"]["iou_true_masks"] = true_iou(preset)
    print(json.dumps(report["preset"]), flush=True)
    for text in args.set or [""]:
        overrides = parse(text)
        r = fit_body_offsets(body, params, obs, ShapeFitConfig(**overrides))
        fitted = body_silhouettes(args.data, offsets=r.offsets)
        after = iou(fitted, masks)
        unseen = np.setdiff1d(np.arange(len(after)), r.frames)
        run = {"set": overrides, "iou": round(float(after.mean()), 4),
               "iou_unseen_frames": round(float(after[unseen].mean()), 4) if len(unseen) else None,
               "worst_frame_change": round(float((after - before).min()), 4),
               **{k: v for k, v in r.summary().items() if k != "losses"}}
        if truth:
            run["iou_true_masks"] = true_iou(fitted)
        report["runs"].append(run)
        print(json.dumps(run), flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
