"""``rmavatar bench quality``: the full model, the paper's three ablations and our variants, trained the same way.

On a synthetic subject per seed (or a dataset you name), each variant is trained for the same number of
iterations with the same seed, then scored on ``test`` (novel frames of the training motion) and
``novel_pose`` (a motion never seen in training): PSNR / SSIM / LPIPS on full images over a white
background, plus wall time, iterations per second and the final Gaussian count. With several seeds
(``--seeds 0,1,2``: three subjects, each trained with its own seed) every variant gets the mean and the
sample standard deviation over the seeds, so a difference can be told from subject-to-subject noise.

Variants (paper §4.4): ``full``; ``no_rectifier`` ("w/o GauRec": Gaussians fixed to their faces);
``no_offset_loss``; ``no_scaling_loss``. Ours: ``local_rectifier`` (``model.rectifier: local``).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import statistics
import time
from pathlib import Path

from rmavatar.utils import UserError
from rmavatar.utils.outputs import write_json

# rmavatar.train.config.ABLATIONS
VARIANTS = ("full", "no_rectifier", "no_offset_loss", "no_scaling_loss", "local_rectifier")
SPLITS = ("test", "novel_pose")
METRICS = ("psnr", "ssim", "lpips")


def parse_seeds(text: str) -> list[int]:
    """``"0"`` or ``"0,1,2"`` -> [0, 1, 2] (distinct whole numbers); the --seed/--seeds argument type."""
    try:
        seeds = [int(part) for part in str(text).split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a seed or a comma-separated list of seeds, got {text!r}") from None
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"seeds must be distinct, got {text!r}")
    return seeds


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


def run_quality(work: Path, variants: list[str], data: str | None, size: int, iters: int, seeds: int | list[int],
                max_gaussians: int, threads: int, device: str, progress: bool = True) -> dict:
    """Train and score every variant for every seed under ``work`` (``work/seedS/run-VARIANT``; the
    synthetic subject of seed S in ``work/synth-seedS-SIZE`` unless ``data`` names a dataset); returns
    the result dict (also what --json writes): ``runs`` seed -> variant -> row, ``variants`` variant ->
    mean and standard deviation over the seeds (:func:`aggregate`)."""
    from rmavatar.bench.timing import machine_info

    seeds = [seeds] if isinstance(seeds, int) else list(seeds)
    if not seeds:
        raise UserError("bench quality needs at least one seed")
    work.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    runs, datasets = {}, {}
    for seed in seeds:
        datasets[str(seed)], runs[str(seed)] = _run_seed(work, variants, data, size, iters, seed, max_gaussians,
                                                        threads, device, progress)
    return {
        "benchmark": "quality",
        "data": datasets,
        "size": size,
        "iterations": iters,
        "seeds": seeds,
        "max_gaussians": max_gaussians,
        "protocol": "full images, white background, PSNR per image then averaged, SSIM 11x11 Gaussian "
        "window (sigma 1.5), LPIPS AlexNet v0.1 on [-1,1] inputs, no test-time pose refinement; across "
        "seeds: mean and sample standard deviation (n - 1)",
        "machine": {**machine_info(), "device": device, "load_start": load_start, "load_end": os.getloadavg()},
        "variants": aggregate(runs),
        "runs": runs,
    }


def _run_seed(work: Path, variants: list[str], data: str | None, size: int, iters: int, seed: int,
              max_gaussians: int, threads: int, device: str, progress: bool) -> tuple[str, dict]:
    """One seed's dataset spec and its rows, variant -> row."""
    from rmavatar.data.synth import SynthConfig, synthesize
    from rmavatar.evaluate import evaluate_run
    from rmavatar.train import train

    if data is None:
        data_dir = work / f"synth-seed{seed}-{size}"
        if not (data_dir / "meta.yaml").exists():
            synthesize(data_dir, SynthConfig(size=size, seed=seed), progress=progress)
        data = str(data_dir)
    rows = {}
    for variant in variants:
        run_dir = work / f"seed{seed}" / f"run-{variant}"
        cfg = variant_config(variant, data, size, iters, seed, max_gaussians, threads, device)
        print(f"\n== bench quality: {variant}, seed {seed} ({iters} iterations at {size}px) -> {run_dir}",
              flush=True)
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
            row[split] = {k: res["mean"][k] for k in METRICS}
        rows[variant] = row
    return data, rows


def _mean_std(values: list[float]) -> dict:
    """Mean and sample standard deviation (None for a single value, where it is undefined)."""
    return {"mean": statistics.fmean(values), "std": statistics.stdev(values) if len(values) > 1 else None}


def aggregate(runs: dict) -> dict:
    """Per-seed rows (seed -> variant -> row) -> variant -> {"seeds": n, SPLIT: {METRIC: {"mean", "std"}},
    "train_seconds" / "iters_per_second" / "gaussians": {"mean", "std"}}, over the seeds that ran it."""
    out: dict = {}
    for variant in dict.fromkeys(v for rows in runs.values() for v in rows):
        rows = [seed_rows[variant] for seed_rows in runs.values() if variant in seed_rows]
        agg: dict = {"seeds": len(rows)}
        for split in SPLITS:
            agg[split] = {m: _mean_std([float(r[split][m]) for r in rows]) for m in METRICS}
        for key in ("train_seconds", "iters_per_second", "gaussians"):
            values = [float(r[key]) for r in rows if r.get(key) is not None]
            agg[key] = _mean_std(values) if values else None
        out[variant] = agg
    return out


def _cell(stat: dict | None, digits: int) -> str:
    if stat is None:
        return "-"
    if stat["std"] is None or math.isnan(stat["std"]):
        return f"{stat['mean']:.{digits}f}"
    return f"{stat['mean']:.{digits}f} ± {stat['std']:.{digits}f}"


def format_table(result: dict) -> str:
    """A Markdown table of the result (the one BENCHMARKS.md shows): mean ± sample standard deviation
    over the seeds (the mean alone for one seed)."""
    seeds = result.get("seeds", [])
    lines = [f"seeds: {', '.join(str(s) for s in seeds)} (mean ± standard deviation over {len(seeds)})"
             if len(seeds) > 1 else f"seed: {seeds[0]}", "",
             "| variant | test PSNR | test SSIM | test LPIPS | novel-pose PSNR | novel-pose SSIM | "
             "novel-pose LPIPS | train s | it/s | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in result["variants"].items():
        t, n = r["test"], r["novel_pose"]
        lines.append(f"| {name} | {_cell(t['psnr'], 2)} | {_cell(t['ssim'], 4)} | {_cell(t['lpips'], 4)} | "
                     f"{_cell(n['psnr'], 2)} | {_cell(n['ssim'], 4)} | {_cell(n['lpips'], 4)} | "
                     f"{_cell(r['train_seconds'], 0)} | {_cell(r['iters_per_second'], 2)} | "
                     f"{_cell(r['gaussians'], 0)} |")
    return "\n".join(lines)


WORK_KIND = "bench-quality-work"  # the kind of --work's .rmavatar marker (rmavatar.utils.outputs)
_WORK_ENTRY = re.compile(r"^(synth-seed\d+-\d+|seed\d+)(/|$)")


def check_work(work: Path, seeds: list[int], size: int, with_synth: bool) -> None:
    """UserError unless ``work`` is new, empty or a --work folder of bench quality (its marker, or only
    what bench quality writes there when it had none); then marks it with what this run writes. A folder
    of the user's is never written into: its runs would be resumed and trained further."""
    from rmavatar.utils import check_writable_folder, outputs

    if os.path.lexists(work) and not work.is_dir():
        raise UserError(f"--work {work} exists and is not a folder")
    check_writable_folder(work / outputs.MARKER, f"--work {work}", create=True)
    foreign = outputs.foreign_files(work, WORK_KIND)
    if foreign and outputs.read_marker(work) is None:  # a --work folder of a bench quality without markers
        foreign = [e for e in foreign if not _WORK_ENTRY.match(e)]
    if foreign:
        raise UserError(f"--work {work} holds files that bench quality did not write there "
                        f"({outputs.some_of(foreign)}): refusing to "
                        "write into it; choose a new or empty folder")
    names = [f"seed{s}/" for s in seeds] + ([f"synth-seed{s}-{size}/" for s in seeds] if with_synth else [])
    work.mkdir(parents=True, exist_ok=True)
    outputs.mark_folder(work, WORK_KIND, names)


def run(args: argparse.Namespace) -> int:
    # --json was checked by the bench command before anything ran (rmavatar.utils.outputs)
    check_work(Path(args.work), list(args.seeds), args.size, args.data is None)
    result = run_quality(args.work, args.variants, args.data, args.size, args.iters, args.seeds,
                         args.max_gaussians, args.threads, args.device, progress=not args.quiet)
    table = format_table(result)
    print("\n" + table)
    if args.json:
        write_json(args.json, result, overwrite=args.overwrite)
        print(f"\nwrote {args.json}")
    return 0
