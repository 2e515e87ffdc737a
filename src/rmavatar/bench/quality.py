"""``rmavatar bench quality``: the full model and the paper's three ablations, trained the same way.

On one fixed synthetic subject (or a dataset you name), each variant is trained for the same number of
iterations with the same seed, then scored on ``test`` (novel frames of the training motion) and
``novel_pose`` (a motion never seen in training): PSNR / SSIM / LPIPS on full images over a white
background, plus wall time, iterations per second and the final Gaussian count.

Variants (paper §4.4): ``full``; ``no_rectifier`` ("w/o GauRec": Gaussians fixed to their faces);
``no_offset_loss``; ``no_scaling_loss``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from rmavatar.utils import UserError
from rmavatar.utils.outputs import output_file

VARIANTS = ("full", "no_rectifier", "no_offset_loss", "no_scaling_loss")  # rmavatar.train.config.ABLATIONS
SPLITS = ("test", "novel_pose")


def variant_config(variant: str, data: str, size: int, iters: int, seed: int, max_gaussians: int,
                   threads: int, device: str):
    """The TrainConfig of one variant: the paper's defaults with one switch flipped."""
    from rmavatar.train.config import ABLATIONS, TrainConfig, apply_overrides

    if variant not in ABLATIONS:
        raise UserError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")
    cfg = apply_overrides(TrainConfig(), ABLATIONS[variant])
    cfg.data.path = data
    cfg.data.size = size
    cfg.optim.iters = iters
    cfg.seed = seed
    cfg.threads = threads
    cfg.device = device
    cfg.density.max_gaussians = max_gaussians
    return cfg


def run_quality(work: Path, variants: list[str], data: str | None, size: int, iters: int, seed: int,
                max_gaussians: int, threads: int, device: str, progress: bool = True) -> dict:
    """Train and score every variant under ``work``; returns the result dict (also what --json writes)."""
    from rmavatar.bench.timing import machine_info
    from rmavatar.data.synth import SynthConfig, synthesize
    from rmavatar.evaluate import evaluate_run
    from rmavatar.train import train

    work.mkdir(parents=True, exist_ok=True)
    if data is None:
        data_dir = work / f"synth-seed{seed}-{size}"
        if not (data_dir / "meta.yaml").exists():
            synthesize(data_dir, SynthConfig(size=size, seed=seed), progress=progress)
        data = str(data_dir)
    load_start = os.getloadavg()
    rows = {}
    for variant in variants:
        run_dir = work / f"run-{variant}"
        cfg = variant_config(variant, data, size, iters, seed, max_gaussians, threads, device)
        print(f"\n== bench quality: {variant} ({iters} iterations at {size}px) -> {run_dir}", flush=True)
        start = time.perf_counter()
        if (run_dir / "checkpoints" / "last.pt").exists():
            result = train(None, run_dir, resume=True, progress=progress)
        else:
            result = train(cfg, run_dir, progress=progress)
        seconds = time.perf_counter() - start
        row = {"iterations": result.iteration, "train_seconds": round(seconds, 1),
               "iters_per_second": round(result.iteration / seconds, 3) if seconds > 0 else None,
               "gaussians": result.history[-1]["gaussians"] if result.history else None}
        for split in SPLITS:
            res = evaluate_run(run_dir, split=split, bg="white", size=size, progress=progress)
            row[split] = {k: res["mean"][k] for k in ("psnr", "ssim", "lpips")}
        rows[variant] = row
    return {
        "benchmark": "quality",
        "data": data,
        "size": size,
        "iterations": iters,
        "seed": seed,
        "max_gaussians": max_gaussians,
        "protocol": "full images, white background, PSNR per image then averaged, SSIM 11x11 Gaussian "
        "window (sigma 1.5), LPIPS AlexNet v0.1 on [-1,1] inputs, no test-time pose refinement",
        "machine": {**machine_info(), "device": device, "load_start": load_start, "load_end": os.getloadavg()},
        "variants": rows,
    }


def format_table(result: dict) -> str:
    """A Markdown table of the result (the one BENCHMARKS.md shows)."""
    lines = ["| variant | test PSNR | test SSIM | test LPIPS | novel-pose PSNR | novel-pose SSIM | "
             "novel-pose LPIPS | train s | it/s | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in result["variants"].items():
        t, n = r["test"], r["novel_pose"]
        lines.append(f"| {name} | {t['psnr']:.2f} | {t['ssim']:.4f} | {t['lpips']:.4f} | {n['psnr']:.2f} | "
                     f"{n['ssim']:.4f} | {n['lpips']:.4f} | {r['train_seconds']:.0f} | "
                     f"{r['iters_per_second']:.2f} | {r['gaussians']} |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    # --json was checked by the bench command before anything ran (rmavatar.utils.outputs)
    result = run_quality(args.work, args.variants, args.data, args.size, args.iters, args.seed,
                         args.max_gaussians, args.threads, args.device, progress=not args.quiet)
    table = format_table(result)
    print("\n" + table)
    if args.json:
        with output_file(args.json, option="--json", overwrite=args.overwrite) as tmp:
            tmp.write_text(json.dumps(result, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return 0
