"""``rmavatar demo``: from nothing to an animated avatar in one command.

Makes the synthetic subject, trains an avatar on it, scores it on held-out frames and novel poses,
renders an animation and a turntable, exports a PLY, and writes ``DIR/metrics.json``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from rmavatar.utils import UserError, atomic_path
from rmavatar.utils.outputs import check_output_folder, mark_folder


@dataclass
class DemoConfig:
    """What the demo makes. ``iters`` training iterations at ``size`` x ``size`` pixels."""

    out: Path = Path("demo_out")  # folder the demo writes everything into (see DEMO_FILES)
    seed: int = 0  # seed of the synthetic subject, of training and of the demo's novel motion
    size: int = 256  # image side in pixels of the synthetic data and of training
    iters: int = 1000  # training iterations
    # Cap on the Gaussian count. Densification would triple the count within the run (and the step time
    # with it); the cap keeps the demo inside its CPU budget.
    max_gaussians: int = 40_000
    threads: int | None = None  # training's CPU threads; None: TrainConfig's default
    video_size: int = 384  # side in pixels of the animation and turntable videos
    animation_frames: int = 60  # frames of the novel-motion animation
    turntable_frames: int = 60  # frames of the turntable (one full turn)
    synth: dict | None = None  # SynthConfig overrides (frame counts), e.g. for a quick smoke run
    overwrite: bool = False  # write into a folder holding other files (never touching them)


def write_demo_motion(path: Path, num_frames: int, seed: int) -> Path:
    """The synthetic subject's novel motion (walking, then arm raises) as an AIST++-style motion file."""
    import numpy as np

    from rmavatar.data.synth.motion import novel_motion

    m = novel_motion(num_frames, np.random.default_rng([seed, 7]))
    poses = np.concatenate([m["global_orient"], m["body_pose"]], 1).astype(np.float32)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, poses=poses, trans=m["transl"].astype(np.float32), fps=np.float32(30.0))
    return path


DEMO_KIND = "demo"
# What the demo writes into its folder ('/': a folder it owns whole).
DEMO_FILES = ("data/", "run/", "eval_test/", "eval_novel_pose/", "motion.npz", "animation.mp4", "turntable.mp4",
              "avatar.ply", "metrics.json")


def _check_out(out: Path, overwrite: bool) -> None:
    """--out must be new, empty or an earlier demo's folder; with ``overwrite`` a folder of other files works
    too, as long as none of them has a name the demo writes (see rmavatar.utils.outputs)."""
    check_output_folder(out, DEMO_KIND, option="--out", overwrite=overwrite, writes=[f.rstrip("/") for f in DEMO_FILES])


def _step(name: str) -> float:
    """Announce a demo step; returns the start time (``time.perf_counter()``)."""
    print(f"\n== rmavatar demo: {name}", flush=True)
    return time.perf_counter()


def _synthesize_subject(cfg: DemoConfig, data: Path, progress: bool) -> float:
    """Write the synthetic subject to ``data`` unless an earlier run left it there; returns the seconds taken."""
    from rmavatar.data.synth import SynthConfig, synthesize

    t = _step(f"synthetic subject (seed {cfg.seed}, {cfg.size}x{cfg.size}) -> {data}")
    if (data / "meta.yaml").exists():
        print("   (already there, reused)")
    else:
        synthesize(data, SynthConfig(size=cfg.size, seed=cfg.seed, **(cfg.synth or {})), progress=progress)
    return time.perf_counter() - t


def _train_config(cfg: DemoConfig, data: Path):
    """The demo's ``TrainConfig``: defaults with the demo's data, size, iterations, seed, cap and threads."""
    from rmavatar.train import TrainConfig

    tcfg = TrainConfig()
    tcfg.data.path = str(data)
    tcfg.data.size = cfg.size
    tcfg.optim.iters = cfg.iters
    tcfg.seed = cfg.seed
    tcfg.density.max_gaussians = cfg.max_gaussians
    if cfg.threads:
        tcfg.threads = cfg.threads
    return tcfg


def _train_avatar(cfg: DemoConfig, data: Path, run_dir: Path, progress: bool):
    """Train into ``run_dir`` (resuming an earlier demo's run there); returns (train result, seconds).
    Raises UserError if training was interrupted."""
    from rmavatar.train import train

    t = _step(f"training {cfg.iters} iterations -> {run_dir}")
    tcfg = _train_config(cfg, data)
    result = train(tcfg, run_dir, progress=progress) if not (run_dir / "checkpoints").exists() else \
        train(None, run_dir, resume=True, progress=progress)
    seconds = time.perf_counter() - t
    if result.interrupted:
        raise UserError(f"training was interrupted; run the demo again to continue it ({run_dir})")
    return result, seconds


def _evaluate_splits(run_dir: Path, out: Path, progress: bool, timings: dict[str, float]) -> dict:
    """Score the run on the test and novel-pose splits into ``out/eval_SPLIT``; returns {split: {psnr,
    ssim, lpips, frames}} and adds ``eval_SPLIT_seconds`` to ``timings``."""
    from rmavatar.evaluate import evaluate_run

    metrics: dict = {}
    for split in ("test", "novel_pose"):
        t = _step(f"evaluating on {split} (white background, full images)")
        res = evaluate_run(run_dir, split=split, bg="white", out_dir=out / f"eval_{split}", progress=progress)
        metrics[split] = {k: res["mean"][k] for k in ("psnr", "ssim", "lpips")}
        metrics[split]["frames"] = len(res["frames"])
        timings[f"eval_{split}_seconds"] = time.perf_counter() - t
    return metrics


def _videos_and_export(cfg: DemoConfig, run_dir: Path, out: Path, progress: bool, timings: dict[str, float]) -> int:
    """Render the animation and turntable videos and export the PLY; adds their ``*_seconds`` to
    ``timings`` and returns the exported Gaussian count."""
    from rmavatar.animate.jobs import VideoOptions, animate_video, turntable_video
    from rmavatar.avatar import load_trained
    from rmavatar.body import load_motion, motion_to_sequence
    from rmavatar.export.export import export_ply

    trained = load_trained(run_dir)
    opts = VideoOptions(size=cfg.video_size, fps=30.0, progress=progress, overwrite=True)
    motion_path = write_demo_motion(out / "motion.npz", cfg.animation_frames, cfg.seed)
    t = _step(f"animation with {motion_path.name} -> animation.mp4")
    seq = motion_to_sequence(load_motion(motion_path), source=str(motion_path))
    animate_video(trained, seq, out / "animation.mp4", camera="fixed", opts=opts)
    timings["animate_seconds"] = time.perf_counter() - t
    t = _step("turntable -> turntable.mp4")
    turntable_video(trained, out / "turntable.mp4", num_frames=cfg.turntable_frames, pose="train", opts=opts)
    timings["turntable_seconds"] = time.perf_counter() - t
    t = _step("export -> avatar.ply")
    num = export_ply(trained, trained.rest_pose("tpose"), out / "avatar.ply", overwrite=True)
    timings["export_seconds"] = time.perf_counter() - t
    return num


def _run_summary(cfg: DemoConfig, result, num: int, timings: dict[str, float], t_all: float) -> dict:
    """The run-level entries of metrics.json (times, counts, protocol, file names); returns them as a dict."""
    return {
        "train_seconds": round(timings["train_seconds"], 1),
        "total_seconds": round(time.perf_counter() - t_all, 1),
        "iterations": result.iteration,
        "gaussians": num,
        "size": cfg.size,
        "seed": cfg.seed,
        "protocol": "full images on a white background, PSNR per image then averaged, SSIM 11x11 "
        "Gaussian window, LPIPS AlexNet on [-1,1] inputs, no test-time pose refinement",
        "seconds": {k: round(v, 1) for k, v in timings.items()},
        "files": {
            "data": "data", "run": "run", "animation": "animation.mp4", "turntable": "turntable.mp4",
            "ply": "avatar.ply", "eval_test": "eval_test", "eval_novel_pose": "eval_novel_pose",
        },
    }


def run_demo(cfg: DemoConfig, progress: bool = True) -> dict:
    """Run every step; returns the metrics dict also written to ``cfg.out / 'metrics.json'``."""
    out = cfg.out
    _check_out(out, cfg.overwrite)
    mark_folder(out, DEMO_KIND, DEMO_FILES)  # from here on these names are the demo's own to replace
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    data = out / "data"
    timings["synth_seconds"] = _synthesize_subject(cfg, data, progress)
    run_dir = out / "run"
    result, timings["train_seconds"] = _train_avatar(cfg, data, run_dir, progress)
    metrics = _evaluate_splits(run_dir, out, progress, timings)
    num = _videos_and_export(cfg, run_dir, out, progress, timings)
    metrics.update(_run_summary(cfg, result, num, timings, t_all))
    with atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(metrics, indent=2) + "\n")
    _print_summary(out, metrics)
    return metrics


def _print_summary(out: Path, m: dict) -> None:
    print(f"\n== rmavatar demo: done in {m['total_seconds'] / 60:.1f} min (training {m['train_seconds'] / 60:.1f} min, "
          f"{m['iterations']} iterations, {m['gaussians']} Gaussians)")
    for split in ("test", "novel_pose"):
        s = m[split]
        print(f"   {split:<11} PSNR {s['psnr']:.2f} dB   SSIM {s['ssim']:.4f}   LPIPS {s['lpips']:.4f}   "
              f"({s['frames']} frames)")
    for key, rel in m["files"].items():
        print(f"   {key:<16} {out / rel}")
    print(f"   {'metrics':<16} {out / 'metrics.json'}")
