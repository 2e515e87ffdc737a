"""LPIPS on the person's window (``loss.lpips_region: person``) against the whole frame (``frame``):
the loss's CPU time and the quality of avatars trained each way (docs/train.md, "LPIPS on the person").

    PYTHONPATH=src python scripts/measure_lpips_crop.py WORK [--json benchmarks/lpips_crop.json]
        [--timing-sizes 256,512] [--size 256] [--iters 400] [--max-gaussians 25000] [--seeds 0,1,2]
        [--jobs 2] [--skip-timing] [--skip-quality]

Timing: one synthetic subject (``rmavatar synth``, 512 px, 100 training frames, 1 sample per pixel),
read at each of ``--timing-sizes``; the run's window from every training frame's mask as training makes
it; then the loss forward and backward on training frame 0 (its target over white, a stand-in render,
the paper's weights, the target's LPIPS features cached as training keeps them), whole frame and window
alternately, one CPU thread, medians after a warm-up; also the LPIPS term alone.

Quality: per seed a synthetic subject (``rmavatar synth --size SIZE --seed SEED``: 100 training, 30 test,
30 novel-pose frames), trained with each region (``rmavatar train --iters --size --seed --threads 1``,
both regions of a seed side by side, ``--jobs`` trainings at a time), then ``rmavatar eval`` on test and
novel_pose (full images over white). Writes the JSON and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REGIONS = ("frame", "person")
SPLITS = ("test", "novel_pose")
METRICS = ("psnr", "ssim", "lpips")


def rmavatar(*args: str, log: Path | None = None) -> float:
    """Run ``rmavatar ARGS`` with this interpreter (one torch / numba thread); its wall seconds."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    started = time.perf_counter()
    with open(log, "w") if log else open(os.devnull, "w") as out:
        subprocess.run([sys.executable, "-m", "rmavatar", *args], check=True, env=env, stdout=out,
                       stderr=subprocess.STDOUT)
    return time.perf_counter() - started


# ------------------------------------------------------------------------------------------------ timing
def time_losses(data: Path, size: int, repeats: int, warmup: int = 5) -> dict:
    """Medians (ms) of the loss forward + backward on one frame at ``size``, whole frame vs window."""
    import numpy as np
    import torch

    from rmavatar.data import load_dataset
    from rmavatar.render.composite import composite
    from rmavatar.train.frames import lpips_window_size, mask_box, place_window
    from rmavatar.train.losses import LossConfig, lpips_units, total_loss

    torch.set_num_threads(1)
    ds = load_dataset(str(data), size=size)
    n = ds.num_frames("train")
    boxes = [mask_box(ds.frame("train", i).mask) for i in range(n)]
    h, w = lpips_window_size(boxes, size, size)
    r0, c0 = place_window(boxes[0], (h, w), size, size)
    window = (torch.arange(r0, r0 + h), torch.arange(c0, c0 + w))
    frame = ds.frame("train", 0)
    target = composite(torch.from_numpy(np.array(frame.image)), torch.from_numpy(np.array(frame.mask)),
                       torch.ones(3))
    gen = torch.Generator().manual_seed(0)
    render0 = target + 0.05 * torch.randn(target.shape, generator=gen)  # a stand-in render: same cost
    units = {"frame": lpips_units(target), "person": lpips_units(target, window)}
    windows = {"frame": None, "person": window}
    out: dict = {"image": [size, size], "window": [h, w], "window_pixels": round(h * w / size**2, 3)}
    for name, cfg in (("loss", LossConfig()),
                      ("lpips_term", LossConfig(rgb=0.0, ssim=0.0, lpips=1.0, pos=0.0, scaling=0.0, offset=0.0))):
        times: dict = {r: [] for r in REGIONS}
        for k in range(warmup + repeats):
            for region in REGIONS if k % 2 else REGIONS[::-1]:  # alternated, so drift hits both alike
                render = render0.clone().requires_grad_(True)
                started = time.perf_counter()
                loss, _ = total_loss(render, target, None, cfg, lpips_units=units[region],
                                     lpips_window=windows[region])
                loss.backward()
                if k >= warmup:
                    times[region].append(time.perf_counter() - started)
        med = {r: statistics.median(t) * 1e3 for r, t in times.items()}
        out[name] = {"frame_ms": round(med["frame"], 2), "person_ms": round(med["person"], 2),
                     "person_over_frame": round(med["person"] / med["frame"], 3)}
    return out


# ------------------------------------------------------------------------------------------------ quality
def train_and_score(work: Path, data: Path, seed: int, region: str, size: int, iters: int,
                    max_gaussians: int) -> dict:
    run, config = work / f"run-s{seed}-{region}", work / f"{region}.yaml"
    config.write_text(f"loss:\n  lpips_region: {region}\ndensity:\n  max_gaussians: {max_gaussians}\n")
    seconds = rmavatar("train", str(data), "--out", str(run), "--iters", str(iters), "--size", str(size),
                       "--seed", str(seed), "--threads", "1", "--config", str(config),
                       "--checkpoint-every", str(iters), log=work / f"train-s{seed}-{region}.log")
    out: dict = {"train_seconds": round(seconds, 1)}
    for split in SPLITS:
        result = work / f"eval-s{seed}-{region}-{split}.json"
        rmavatar("eval", str(run), "--json", str(result), "--split", split, "--no-images", "--quiet",
                 "--device", "cpu")
        out[split] = {m: json.loads(result.read_text())["mean"][m] for m in METRICS}
    return out


def quality(work: Path, size: int, iters: int, max_gaussians: int, seeds: list[int], jobs: int) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    subjects = {s: work / f"synth-s{s}-{size}" for s in seeds}
    with ThreadPoolExecutor(jobs) as pool:
        list(pool.map(lambda s: rmavatar("synth", str(subjects[s]), "--size", str(size), "--seed", str(s),
                                         "--quiet"), seeds))
        tasks = {(s, r): pool.submit(train_and_score, work, subjects[s], s, r, size, iters, max_gaussians)
                 for s in seeds for r in REGIONS}
        runs = {r: {str(s): tasks[s, r].result() for s in seeds} for r in REGIONS}
    mean = {r: {"train_seconds": round(statistics.mean(v["train_seconds"] for v in runs[r].values()), 1),
                **{split: {m: statistics.mean(v[split][m] for v in runs[r].values()) for m in METRICS}
                   for split in SPLITS}} for r in REGIONS}
    return {"size": size, "iterations": iters, "max_gaussians": max_gaussians, "seeds": seeds,
            "subject": "rmavatar synth --size SIZE --seed SEED (100 train, 30 test, 30 novel_pose frames)",
            "protocol": "rmavatar train --threads 1, both regions of a seed at the same time; rmavatar eval: "
                        "full images over white, PSNR / SSIM / LPIPS means over the split",
            "runs": runs, "mean": mean}


def table(q: dict) -> str:
    rows = ["| region | seed | train s | test PSNR | test SSIM | test LPIPS | novel PSNR | novel SSIM | novel LPIPS |",
            "|---|---|---|---|---|---|---|---|---|"]
    for region in REGIONS:
        for seed, v in [*q["runs"][region].items(), ("mean", q["mean"][region])]:
            cells = [f"{v[s]['psnr']:.2f} | {v[s]['ssim']:.4f} | {v[s]['lpips']:.4f}" for s in SPLITS]
            rows.append(f"| {region} | {seed} | {v['train_seconds']:.0f} | {cells[0]} | {cells[1]} |")
    return "\n".join(rows)


def main(argv: list[str]) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("work", type=Path, help="folder for the subjects and runs (outside the repository)")
    p.add_argument("--json", type=Path, default=Path("benchmarks/lpips_crop.json"))
    p.add_argument("--timing-sizes", default="256,512")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--iters", type=int, default=400)
    p.add_argument("--max-gaussians", type=int, default=25000)
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--skip-timing", action="store_true")
    p.add_argument("--skip-quality", action="store_true")
    p.add_argument("--note", default="", help="what code was measured (stored in the JSON)")
    args = p.parse_args(argv)
    started = time.perf_counter()
    out: dict = {"benchmark": "lpips_crop", "note": args.note,
                 "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_start": os.getloadavg()}}
    if not args.skip_timing:
        sizes = [int(s) for s in args.timing_sizes.split(",")]
        data = args.work / "timing-subject"
        rmavatar("synth", str(data), "--size", str(max(sizes)), "--train", "100", "--test", "1", "--novel-pose",
                 "1", "--ss", "1", "--quiet")
        out["timing"] = {"protocol": "loss forward + backward on training frame 0, 1 CPU thread, medians of "
                                     "alternated repeats after 5 warm-up each; LPIPS features of the target cached",
                         **{str(s): time_losses(data, s, repeats=30 if s <= 256 else 12) for s in sizes}}
        print(json.dumps(out["timing"], indent=1), flush=True)
    if not args.skip_quality:
        out["quality"] = quality(args.work / "quality", args.size, args.iters, args.max_gaussians,
                                 [int(s) for s in args.seeds.split(",")], args.jobs)
        print(table(out["quality"]))
    out["machine"]["load_end"] = os.getloadavg()
    out["wall_seconds"] = round(time.perf_counter() - started, 1)
    args.json.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.json} ({out['wall_seconds']:.0f} s)")


if __name__ == "__main__":
    main(sys.argv[1:])
