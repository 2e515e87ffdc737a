"""``rmavatar bench speed``: how fast rmavatar is on this machine, as times and as ratios to reference paths.

Three measurements, each timed (median of repeats after warm-up) next to a reference path timed in the
same run, so that the ratio stays comparable on a busy or different machine:

1. rasterizer: forward+backward of the CPU kernels on an avatar-like scene (``bench raster``'s scene)
   vs the dense pure-PyTorch float64 reference (``render/reference.py``). The reference is O(N H W) in
   memory, so it runs on a small configuration; the fast kernels are timed on that same configuration
   in float64 too (the like-for-like ratio), and the per Gaussian-pixel ratio to the large
   configuration is reported as well.
2. training step: the trainer's full step (``bench step``'s machinery: all losses, rectifier, Adam) vs
   the same step with the rectifier run as a plain autograd MLP that concatenates its inputs
   (``Rectifier.reference_forward``: same layers, same weights), each with its per-stage breakdown,
   measured in the order ours, reference, reference, ours.
3. rendering: frames per second of a posed avatar (body forward, mesh-embedded Gaussians, rectifier,
   rasterizer; no autograd) at each render size, vs the same pipeline with the dense reference
   rasterizer at a size where it fits (the fast pipeline is timed there too: that ratio).

Every ratio is ``reference time / rmavatar time``: above 1 means rmavatar is faster.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path


def _ratio(reference_s: float, ours_s: float) -> float:
    return reference_s / ours_s


# ---------------------------------------------------------------------------------------------- rasterizer
def bench_rasterizer(n: int, size: int, ref_n: int, ref_size: int, repeats: int, warmup: int) -> dict:
    """Forward+backward seconds of the CPU kernels at (n, size) in float32, and of the dense reference vs
    the kernels at (ref_n, ref_size), both in float64 (see ``bench raster`` for the scene)."""
    import torch

    from rmavatar.bench.raster import _bench_one
    from rmavatar.render import rasterize
    from rmavatar.render.reference import reference_rasterize

    opts = argparse.Namespace(sh_degree=3, device="cpu", disc_scale=1.5, repeats=repeats, warmup=warmup)
    ref_opts = argparse.Namespace(**{**vars(opts), "repeats": min(repeats, 3), "warmup": min(warmup, 1)})
    no_sync = lambda: None  # noqa: E731

    def fast(*a, **kw):
        return rasterize(*a, backend="cpu", **kw)

    def keep(m: dict) -> dict:
        return {k: m[k] for k in ("forward_s", "forward_backward_s", "forward_backward_cpu_s")}

    ours = keep(_bench_one(n, size, opts, no_sync, fast, memory=False))
    ref = keep(_bench_one(ref_n, ref_size, ref_opts, no_sync, reference_rasterize, dtype=torch.float64,
                          memory=False))
    ours_small = keep(_bench_one(ref_n, ref_size, ref_opts, no_sync, fast, dtype=torch.float64, memory=False))
    per_gp_ref = ref["forward_backward_s"] / (ref_n * ref_size**2)
    per_gp_ours = ours["forward_backward_s"] / (n * size**2)
    return {
        "scene": "bench raster's figure_scene: surface discs on a 1.8 m figure, SH degree 3, white background",
        "rmavatar": {"n": n, "size": size, "dtype": "float32", "backend": "cpu", **ours},
        "reference": {"n": ref_n, "size": ref_size, "dtype": "float64", "path": "render.reference "
                      "(dense: every pixel x every Gaussian, autograd)", **ref},
        "rmavatar_at_reference_config": {"n": ref_n, "size": ref_size, "dtype": "float64", **ours_small},
        "time_s": ours["forward_backward_s"],
        "ratio": _ratio(ref["forward_backward_s"], ours_small["forward_backward_s"]),
        "ratio_note": "dense reference / CPU kernels, forward+backward, same scene, same config, both float64",
        "ratio_per_gaussian_pixel": per_gp_ref / per_gp_ours,
        "ratio_per_gaussian_pixel_note": "reference seconds per Gaussian-pixel at its config / kernels' at "
                                         f"{n}x{size} float32 (tiling makes the kernels' cost grow far slower "
                                         "than N*H*W, so this grows with the size)",
    }


# ------------------------------------------------------------------------------------------- training step
def _naive_rectifier(trainer) -> None:
    """Run the trainer's rectifier as a plain autograd MLP on concatenated inputs (same weights)."""
    rect = trainer.avatar.rectifier
    if rect is not None:
        rect.forward = rect.reference_forward


def _mean_rounds(rounds: list[dict]) -> dict:
    """Step and per-stage wall seconds averaged over rounds of ``bench step``'s measurement."""
    mean = statistics.fmean
    return {
        "step_s": mean(r["step_median_s"] for r in rounds),
        "step_cpu_s": mean(r["step_median_cpu_s"] for r in rounds),
        "stages_s": {k: mean(r["stages"][k]["wall_s"] for r in rounds) for k in rounds[0]["stages"]},
        "other_s": mean(r["other"]["wall_s"] for r in rounds),
        "gaussians": rounds[0]["gaussians"],
        "size": rounds[0]["size"],
        "rounds": rounds,
    }


def bench_training_step(data: str, size: int, steps: int, warmup: int, threads: int,
                        gaussians: int | None) -> dict:
    """``bench step``'s measurement for the fused rectifier and for the plain autograd one.

    Measured in the order ours, reference, reference, ours and averaged per variant, so that load that
    rises or falls during the run weighs on both alike (the two differ by ~10% of a step, less than
    the load's effect on one median).
    """
    from rmavatar.bench.step import measure

    rounds: dict[str, list[dict]] = {"rmavatar": [], "reference": []}
    for name in ("rmavatar", "reference", "reference", "rmavatar"):
        prepare = _naive_rectifier if name == "reference" else None
        rounds[name].append(measure(data, size, steps, warmup, threads, "cpu", gaussians, rectifier=True,
                                    prepare=prepare))
    ours, ref = _mean_rounds(rounds["rmavatar"]), _mean_rounds(rounds["reference"])
    return {
        "rmavatar": ours,
        "reference": {"path": "the same step with Rectifier.reference_forward: nn.Linear + ReLU under "
                              "autograd on the concatenated [N,105] and [N,164] inputs", **ref},
        "time_s": ours["step_s"],
        "ratio": _ratio(ref["step_s"], ours["step_s"]),
        "ratio_note": "reference step / rmavatar step (median wall seconds, mean of 2 rounds each, "
                      "measured ours-reference-reference-ours)",
        "rectifier_stage_ratio": _ratio(ref["stages_s"]["rectifier"], ours["stages_s"]["rectifier"]),
    }


# ----------------------------------------------------------------------------------------------- rendering
def _trained(data: str, run: str | None, gaussians: int | None):
    """The avatar to render: a trained run's, or a freshly initialised one on the dataset's body."""
    from rmavatar.avatar import TrainedAvatar, load_trained
    from rmavatar.avatar.run import training_betas

    if run is not None:
        return load_trained(run), "trained run " + str(run)
    from rmavatar.data import load_dataset
    from rmavatar.train.config import TrainConfig
    from rmavatar.train.trainer import load_body

    cfg = TrainConfig()
    if gaussians:
        cfg.model.placement, cfg.model.num_gaussians = "area", gaussians
    dataset = load_dataset(data)
    body, info = load_body(cfg, dataset, None, data)
    spec = info["spec"]
    avatar = cfg.model.build(body, seed=cfg.seed).eval()
    betas = training_betas(dataset.params("train")) if body.num_betas > 0 else None
    desc = f"freshly initialised (untrained) avatar on {spec}, {avatar.num_gaussians} Gaussians"
    return TrainedAvatar(avatar, body, betas, iteration=0, data_spec=data, size=None, config={}), desc


def bench_rendering(trained, data: str, sizes: list[int], ref_size: int, repeats: int, warmup: int) -> dict:
    """Frames per second of pose -> image for the training poses of ``data``, each frame in front of a
    camera framing the body (as ``rmavatar animate`` shoots it)."""
    import torch

    from rmavatar.animate.camera import intrinsics, preset_viewmat
    from rmavatar.animate.jobs import VideoOptions, frame_the_body
    from rmavatar.animate.motion import recenter_motion
    from rmavatar.bench.timing import Clock
    from rmavatar.body import PoseSequence
    from rmavatar.data import load_dataset
    from rmavatar.render import rasterize
    from rmavatar.render.reference import reference_rasterize

    params = load_dataset(data).params("train")
    seq = PoseSequence.from_params(params)
    seq = recenter_motion(seq, trained.root_rest())
    center, distance = frame_the_body(trained.vertices(seq), VideoOptions())
    view = preset_viewmat("front", center, distance)

    def fps(raster, size, reps, warm):
        """Median frame time at ``size`` and the medians of its three stages."""
        K = intrinsics(size, size, VideoOptions().fov_deg)
        bg = torch.ones(3)
        stages = {name: Clock() for name in ("body_forward", "gaussians", "rasterize")}
        frame_clock = Clock()
        for k in range(warm + reps):
            one = seq.select(slice(k % len(seq), k % len(seq) + 1))
            timed = k >= warm
            with torch.no_grad(), (frame_clock if timed else nullcontext()):
                with stages["body_forward"] if timed else nullcontext():
                    vertices = trained.vertices(one)[0]
                with stages["gaussians"] if timed else nullcontext():  # mesh embedding + rectifier
                    gs = trained.gaussians(vertices, one.body_pose[0], one.hand(0))
                with stages["rasterize"] if timed else nullcontext():
                    raster(gs.means, gs.quats, gs.scales, gs.opacities, gs.colors(view), view, K, size, size,
                           background=bg)
        t = frame_clock.result()
        return {"size": size, "frame_s": t["wall_s"], "frame_cpu_s": t["cpu_s"], "fps": 1.0 / t["wall_s"],
                "stages_s": {name: c.result()["wall_s"] for name, c in stages.items()}}

    def fast(*a, **kw):
        return rasterize(*a, backend="cpu", **kw)

    rows = [fps(fast, s, repeats, warmup) for s in sizes]
    ref_reps, ref_warm = min(repeats, 3), min(warmup, 1)
    ref = fps(reference_rasterize, ref_size, ref_reps, ref_warm)
    ours_small = fps(fast, ref_size, repeats, warmup)
    return {
        "pipeline": "body forward (1 frame) + mesh-embedded Gaussians + rectifier + rasterize, no autograd, "
                    "front camera framing the body, cycling through the training poses",
        "rmavatar": rows,
        "reference": {"path": "the same pipeline with render.reference (dense, float64)", **ref},
        "rmavatar_at_reference_size": ours_small,
        "time_s": rows[0]["frame_s"],
        "ratio": _ratio(ref["frame_s"], ours_small["frame_s"]),
        "ratio_note": f"frame time with the dense reference rasterizer / with the CPU kernels, both at "
                      f"{ref_size}x{ref_size} with all Gaussians",
    }


# ---------------------------------------------------------------------------------------------------- run
def _check(args) -> tuple[int, int]:
    from rmavatar.bench.raster import _parse_config
    from rmavatar.utils import UserError
    from rmavatar.utils.outputs import check_output_file

    for name in ("size", "gaussians", "repeats", "steps", "threads", "render_reference_size"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.avatar_gaussians is not None and args.avatar_gaussians < 1:
        raise UserError(f"--avatar-gaussians must be >= 1, got {args.avatar_gaussians}")
    if args.warmup < 0:
        raise UserError(f"--warmup must be >= 0, got {args.warmup}")
    if any(s < 1 for s in args.render_sizes):
        raise UserError(f"--render-sizes must all be >= 1, got {args.render_sizes}")
    if args.run is not None and not Path(args.run).is_dir():
        raise UserError(f"--run {args.run}: no such run folder")
    if args.json:  # fail now, not after minutes of measuring, if the result cannot be written
        check_output_file(args.json, option="--json", overwrite=getattr(args, "overwrite", False))
    ref_n, ref_size = _parse_config(args.raster_reference, "--raster-reference")
    if ref_n < 1:
        raise UserError(f"--raster-reference needs at least one Gaussian, got {args.raster_reference!r}")
    return ref_n, ref_size


def _print(report: dict) -> None:
    r, s, v = report["rasterizer"], report["training_step"], report["rendering"]
    rr, ref = r["rmavatar"], r["reference"]
    print()
    print(f"{'measurement':<44} {'rmavatar':>12} {'reference':>12} {'ratio':>8}")
    print(f"{'rasterizer fwd+bwd ' + str(rr['n']) + ' @' + str(rr['size']) + ' (f32)':<44} "
          f"{rr['forward_backward_s'] * 1e3:>9.1f} ms {'':>12} {'':>8}")
    print(f"{'  same config as reference ' + str(ref['n']) + ' @' + str(ref['size']) + ' (f64)':<44} "
          f"{r['rmavatar_at_reference_config']['forward_backward_s'] * 1e3:>9.1f} ms "
          f"{ref['forward_backward_s'] * 1e3:>9.1f} ms {r['ratio']:>7.1f}x")
    print(f"{'  per Gaussian-pixel':<44} {'':>12} {'':>12} {r['ratio_per_gaussian_pixel']:>7.0f}x")
    so, sr = s["rmavatar"], s["reference"]
    print(f"{'training step ' + str(so['gaussians']) + ' @' + str(so['size']):<44} "
          f"{so['step_s'] * 1e3:>9.1f} ms {sr['step_s'] * 1e3:>9.1f} ms {s['ratio']:>7.2f}x")
    for k, a in so["stages_s"].items():
        b = sr["stages_s"][k]
        print(f"{'  ' + k:<44} {a * 1e3:>9.1f} ms {b * 1e3:>9.1f} ms {b / a:>7.2f}x")
    print(f"{'  other (data, guards, statistics)':<44} {so['other_s'] * 1e3:>9.1f} ms "
          f"{sr['other_s'] * 1e3:>9.1f} ms")
    for row in v["rmavatar"]:
        st = row["stages_s"]
        print(f"{'render ' + str(row['size']) + 'x' + str(row['size']) + ' (no grad)':<44} "
              f"{row['fps']:>8.1f} fps {'':>12} {'':>8}   body {st['body_forward'] * 1e3:.0f} ms, "
              f"Gaussians+rectifier {st['gaussians'] * 1e3:.0f} ms, rasterize {st['rasterize'] * 1e3:.0f} ms")
    vr, vs = v["reference"], v["rmavatar_at_reference_size"]
    print(f"{'  same size as reference ' + str(vr['size']) + 'x' + str(vr['size']):<44} "
          f"{vs['fps']:>8.1f} fps {vr['fps']:>8.2f} fps {v['ratio']:>7.1f}x")
    m = report["machine"]
    print(f"\nratio = reference time / rmavatar time.  {m['cpu_count']} CPUs, torch {m['torch']} "
          f"({m['torch_threads']} threads), numba {m['numba']}; load average "
          f"{m['load_average_start'][0]:.2f} at start, {m['load_average_end'][0]:.2f} at end "
          f"(1 min); {report['total_s']:.0f} s in all")


def run(args: argparse.Namespace) -> int:
    ref_n, ref_size = _check(args)

    from rmavatar.bench.step import synthetic_subject
    from rmavatar.bench.timing import machine_info
    from rmavatar.utils.device import set_threads
    from rmavatar.utils.outputs import write_json

    t_start = time.perf_counter()
    load_start = list(os.getloadavg())
    set_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or synthetic_subject(Path(tmp) / "synth", args.size)
        print(f"rasterizer: {args.gaussians} Gaussians at {args.size}x{args.size} vs dense reference "
              f"{args.raster_reference} ...", flush=True)
        raster = bench_rasterizer(args.gaussians, args.size, ref_n, ref_size, args.repeats, args.warmup)
        print(f"training step at {args.size}x{args.size}: fused vs plain autograd rectifier ...", flush=True)
        step = bench_training_step(data, args.size, args.steps, min(args.warmup, args.steps), args.threads,
                                   args.avatar_gaussians)
        set_threads(args.threads)
        print(f"rendering at {', '.join(map(str, args.render_sizes))} vs dense reference at "
              f"{args.render_reference_size} ...", flush=True)
        trained, avatar_desc = _trained(data, args.run, args.avatar_gaussians)
        render = bench_rendering(trained, data, args.render_sizes, args.render_reference_size, args.repeats,
                                 args.warmup)
        render["avatar"] = avatar_desc
        render["gaussians"] = int(trained.avatar.num_gaussians)
    machine = machine_info()
    machine["load_average_start"] = load_start
    machine["load_average_end"] = machine.pop("load_average")
    report = {
        "benchmark": "speed",
        "ratio_definition": "reference time / rmavatar time, measured in the same run (> 1: rmavatar faster)",
        "timing": f"median wall seconds of {args.repeats} runs after {args.warmup} warm-up runs "
                  f"(training steps: {args.steps} per round, 2 rounds per variant); dense references: at most 3 runs after 1 warm-up",
        "data": args.data or "synthetic subject (rmavatar synth, seed 0, 8 training frames)",
        "rasterizer": raster,
        "training_step": step,
        "rendering": render,
        "machine": machine,
        "total_s": time.perf_counter() - t_start,
    }
    ratios = [raster["ratio"], raster["ratio_per_gaussian_pixel"], step["ratio"], step["rectifier_stage_ratio"],
              render["ratio"]]
    if not all(math.isfinite(x) and x > 0 for x in ratios):
        raise RuntimeError(f"a speed ratio is not a positive finite number: {ratios}")
    _print(report)
    if args.json:
        write_json(args.json, report, overwrite=args.overwrite)
        print(f"wrote {args.json}")
    return 0
