"""``rmavatar bench step``: time of one training iteration, and where it goes.

The full step is the trainer's own ``step()`` (target fetch, avatar, rasterizer, all losses, backward,
NaN guards, Adam, density statistics; on CUDA the posing and the losses replayed as CUDA graphs), timed as the median over repeats after warm-up, on a small
synthetic subject (``rmavatar synth``) at the chosen size, or on a dataset you name. Density control
is left out (it runs once per few hundred steps; its cost is reported separately, once).

The breakdown times each stage alone on the same inputs (median of repeats):
body forward (one frame; training caches all frames' posed bodies up front, so a step pays 0),
mesh embedding (the per-Gaussian transform from the frame's face table, cached as in a step; fwd+bwd),
rectifier MLP (fwd+bwd), rasterizer forward and backward, losses (L1 + SSIM + LPIPS + regularisers, fwd+bwd), optimiser
(Adam step + zero_grad). "other" = full step minus the stages.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

from rmavatar.bench.timing import Clock, median_time, timed


def late_iteration(cfg) -> int:
    """The first iteration of a ``cfg`` run with every SH band on and the encoding window fully open."""
    iters, m = cfg.optim.iters, cfg.model
    sh = m.sh_degree * max(1, round(m.sh_every_frac * iters))
    window = math.ceil(m.c2f_end * iters) if m.coarse_to_fine else 0
    return min(iters - 1, max(sh, window))


def _stages(trainer, repeats: int, sync) -> dict:
    """Each stage of a step timed alone on frame 0's inputs (seconds, medians)."""
    import torch

    from rmavatar.render import rasterize
    from rmavatar.train.losses import total_loss
    from rmavatar.train.frames import background_color

    av, cfg, dev = trainer.avatar, trainer.cfg, trainer.device
    i = 0
    params = trainer.dataset.params(cfg.data.split)
    one = {k: torch.as_tensor(params[k][:1], dtype=torch.float32, device=dev)
           for k in ("betas", "global_orient", "body_pose", "transl")}
    verts, pose, table = trainer.frame_body(i, trainer.iteration)
    verts = verts.detach()  # the stages are timed again and again: not through a refined pose's graph
    bg = background_color(cfg.background, trainer.bg_generator, dev)
    target = trainer.frames.target(i, bg)  # what a step uses: the cached target, face table, LPIPS features
    units, window = trainer.frames.lpips_units(i, bg), trainer.frames.lpips_window(i)
    out = {}

    with torch.no_grad():
        out["body_forward"] = median_time(lambda: trainer.body(**one), repeats, sync)

    def embed():
        mu, r, s = av.posed(verts, table)
        (mu.sum() + r.sum() + s.sum()).backward()

    out["mesh_embedding"] = median_time(embed, repeats, sync)
    if av.rectifier is not None:
        with torch.no_grad():
            mu0 = av.posed(verts, table)[0]

        def rect():
            d_mu, d_s, d_r = av.rectifier(mu0, pose)
            (d_mu.sum() + d_s.sum() + d_r.sum()).backward()

        out["rectifier"] = median_time(rect, repeats, sync)
    with torch.no_grad():
        gs, extras = av.forward_with_extras(verts, pose, table=table)
    cam = trainer.frames.cameras[i]
    colors = gs.colors(cam.viewmat)
    leaves = [t.detach().clone().requires_grad_(True) for t in (gs.means, gs.quats, gs.scales, gs.opacities, colors)]

    def raster_fwd():
        with torch.no_grad():
            rasterize(*leaves, cam.viewmat, cam.K, cam.width, cam.height, background=bg)

    out["rasterizer_forward"] = median_time(raster_fwd, repeats, sync)
    grad_img = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0)).to(dev)
    clock = Clock(sync)
    for _ in range(repeats):
        image, alpha, _ = rasterize(*leaves, cam.viewmat, cam.K, cam.width, cam.height, background=bg)
        with clock:
            image.backward(grad_img)
    out["rasterizer_backward"] = clock.result()
    img_leaf = image.detach().clone().requires_grad_(True)
    alpha_leaf = alpha.detach().clone().requires_grad_(True)
    mask = trainer.frames.mask(i) if cfg.loss.mask else None
    offsets = None if extras.offsets is None else tuple(o.detach().clone().requires_grad_(True) for o in extras.offsets)
    extras_leaf = type(extras)(local_means=av.means, local_log_scales=av.log_scales, offsets=offsets)

    def losses():
        loss, _ = total_loss(img_leaf, target, extras_leaf, cfg.loss, lpips_units=units, lpips_window=window,
                             alpha=alpha_leaf, mask=mask)
        loss.backward()

    out["losses"] = median_time(losses, repeats, sync)

    def optim():
        for p in (q for g in trainer.optimizer.param_groups for q in g["params"]):
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        trainer.optimizer.step()
        trainer.optimizer.zero_grad(set_to_none=True)

    out["optimizer"] = median_time(optim, repeats, sync)
    av.zero_grad(set_to_none=True)
    return out


def _config(data: str, size: int, device: str, threads: int, rectifier, gaussians: int, refine_poses: bool,
            cuda_graphs: bool = True, capacity: bool | None = None):
    """The TrainConfig the benchmark's steps run with (``capacity``: density.capacity)."""
    from rmavatar.train.config import TrainConfig
    from rmavatar.data.registry import normalize_spec

    cfg = TrainConfig()
    cfg.threads = threads
    cfg.data.path = normalize_spec(data)
    cfg.data.size = size
    cfg.device = device
    cfg.cuda_graphs = cuda_graphs
    cfg.density.capacity = capacity
    cfg.model.rectifier = "paper" if rectifier else False  # the design every measurement here was taken with
    if refine_poses:  # every timed step past the warm-up: the body posed with gradients (a first pass's)
        cfg.poses.refine, cfg.poses.warmup, cfg.poses.first_pass = True, 0.0, 0.0
    if gaussians:
        cfg.model.placement, cfg.model.num_gaussians = "area", gaussians
    cfg.log.tensorboard = False
    return cfg


def count_step_ops(one_step, steps: int) -> dict:
    """Tensor operations and host syncs per training step (``bench.counting``), averaged over ``steps``
    further steps (none of them a logging or density-control step: ``Trainer.step`` does not log)."""
    from rmavatar.bench.counting import OpCounter

    with OpCounter() as counter:
        for _ in range(steps):
            one_step()
    return {"steps": steps, **counter.summary(steps)}


def count_graphed_ops(trainer) -> dict:
    """Tensor operations per step inside the two pieces a CUDA step replays as graphs (``StepGraphs``):
    posing (``pose_frame``) and the losses (``total_loss``), each forward and backward, counted on frame
    0's inputs. On a GPU these launch as two graph replays each (forward, backward); the rest of a step's
    operations launch one by one."""
    import torch

    from rmavatar.avatar.frame import pose_frame
    from rmavatar.bench.counting import OpCounter
    from rmavatar.render import rasterize
    from rmavatar.train.frames import background_color
    from rmavatar.train.losses import total_loss

    av, cfg, i = trainer.avatar, trainer.cfg, 0
    vertices, body_pose, table = trainer.frame_body(i, trainer.iteration)
    cam = trainer.frames.cameras[i]
    bg = background_color(cfg.background, trainer.bg_generator, trainer.device)
    target, units = trainer.frames.target(i, bg), trainer.frames.lpips_units(i, bg)
    window = trainer.frames.lpips_window(i)
    params = [p for p in av.parameters() if p.requires_grad]
    with OpCounter() as posing:
        gs, extras, colors = pose_frame(av, vertices.detach(), body_pose.detach(), cam.viewmat, table=table)
        outs = (gs.means, gs.quats, gs.scales, gs.opacities, colors, *(extras.offsets or ()))
        torch.autograd.grad(outs, params, [torch.ones_like(o) for o in outs], allow_unused=True)
    with torch.no_grad():
        image, alpha, _ = rasterize(*(t.detach() for t in outs[:5]), cam.viewmat, cam.K, cam.width, cam.height,
                                    background=bg, check=False)
    image.requires_grad_(True)
    alpha.requires_grad_(True)
    mask = trainer.frames.mask(i) if cfg.loss.mask else None
    offsets = None if extras.offsets is None else tuple(o.detach().requires_grad_(True) for o in extras.offsets)
    with OpCounter() as losses:
        loss, _ = total_loss(image, target, type(extras)(av.means, av.log_scales, offsets, extras.row_weights), cfg.loss,
                             lpips_units=units, lpips_window=window, alpha=alpha, mask=mask)
        loss.backward()
    av.zero_grad(set_to_none=True)
    return {"posing": posing.ops, "losses": losses.ops}


def device_info(device) -> dict:
    """The torch device as text and, on CUDA, the GPU's name."""
    import torch

    dev = torch.device(device)
    info = {"device": str(dev)}
    if dev.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(dev)
    return info


def measure(data: str, size: int, steps: int, warmup: int, threads: int, device: str,
            gaussians: int | None, rectifier: bool, prepare=None, count_steps: int = 20,
            refine_poses: bool = False, cuda_graphs: bool = True, capacity: bool | None = None) -> dict:
    """Time ``steps`` training steps (after ``warmup``) and each stage alone; see the module docstring.

    ``prepare(trainer)``, when given, runs after the trainer's setup and before any step (``bench speed``
    uses it to swap in a reference implementation). ``count_steps`` more steps are run under an
    operation counter (0: none).
    """
    import torch

    from rmavatar.train.trainer import Trainer

    cfg = _config(data, size, device, threads, rectifier, gaussians, refine_poses, cuda_graphs, capacity)
    with tempfile.TemporaryDirectory() as run:
        trainer = Trainer(cfg, Path(run), progress=False)
        t0 = time.perf_counter()
        trainer.setup()
        setup_s = time.perf_counter() - t0
        if prepare is not None:
            prepare(trainer)
        sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
        clock, counts = _timed_steps(trainer, steps, warmup, count_steps, sync)
        graphs = {"used": trainer.graphs.enabled, "captures": trainer.graphs.captures,
                  "capture_s": trainer.graphs.capture_s, "off_reason": trainer.graphs.off_reason,
                  "failures": [list(f) for f in trainer.graphs.failures]}
        n = trainer.avatar.num_gaussians
        rows = None if trainer.avatar.live_rows is None else trainer.avatar.capacity
        stages = _stages(trainer, max(3, steps // 2), sync)
        # One density-control pass (densify + prune) with the statistics gathered so far.
        t0 = time.perf_counter()
        trainer.density.densify_and_prune()
        sync()
        density_s = time.perf_counter() - t0
        device_fields = device_info(trainer.device)
    step, step_cpu = statistics.median(clock.wall), statistics.median(clock.cpu)
    in_step = {k: v for k, v in stages.items() if k != "body_forward"}
    return {
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "size": size,
        "gaussians": n,
        "capacity": rows,  # rows of the capacity buffers the Gaussians live in (None: not in buffers)
        **device_fields,
        "threads": threads,
        "rectifier": rectifier,
        "refine_poses": refine_poses,
        "cuda_graphs": graphs,
        "step_median_s": step,
        "step_min_s": min(clock.wall),
        "step_max_s": max(clock.wall),
        "step_median_cpu_s": step_cpu,
        "iterations_per_s": 1.0 / step,
        "stages": stages,
        "other": {"wall_s": step - sum(v["wall_s"] for v in in_step.values()),
                  "cpu_s": step_cpu - sum(v["cpu_s"] for v in in_step.values())},
        "body_forward_in_step_s": 0.0,
        "density_control_once_s": density_s,
        "counts": counts,
        "setup_s": setup_s,
        "target_s": 0.3,
    }


def _timed_steps(trainer, steps: int, warmup: int, count_steps: int, sync) -> tuple:
    """(a Clock of ``steps`` of ``trainer``'s steps after ``warmup``, the operation counts of ``count_steps``
    more or None). The steps are late ones: every SH band on and the coarse-to-fine window open."""
    import torch

    # trainer.step() sets the avatar's progress from trainer.iteration, so that is what has to move
    # (setting the avatar's progress here would be undone by the first step, which then timed an early,
    # cheaper one).
    trainer.iteration = late_iteration(trainer.cfg)
    oks = []  # each step's device-side flag, read once at the end: no sync, no operation per step

    def one_step():
        oks.append(trainer.step()["ok"])
        trainer.iteration += 1

    clock = timed(one_step, steps, sync, warmup)
    counts = count_step_ops(one_step, count_steps) if count_steps > 0 else None
    if counts is not None:
        counts["in_cuda_graphs"] = count_graphed_ops(trainer)
    skipped = int((~torch.stack(oks)).sum())
    if skipped:
        raise RuntimeError(f"{skipped} benchmark step(s) were skipped (non-finite loss)")
    return clock, counts


def synthetic_subject(folder: Path, size: int) -> str:
    """Make the small synthetic subject the speed benchmarks train on (8 training frames); its path."""
    from rmavatar.data.synth import SynthConfig, synthesize

    print(f"making a synthetic subject at {size}x{size} ...", flush=True)
    synthesize(str(folder), SynthConfig(size=size, seed=0, train=8, test=1, novel_pose=1, ss=1), progress=False)
    return str(folder)


def run(args: argparse.Namespace) -> int:
    from rmavatar.utils import UserError

    if args.steps < 1 or args.warmup < 0:
        raise UserError("--steps must be >= 1 and --warmup >= 0")
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = synthetic_subject(Path(tmp) / "synth", args.size)
        res = measure(data, args.size, args.steps, args.warmup, args.threads, args.device, args.gaussians,
                      not args.no_rectifier, count_steps=args.count_steps, refine_poses=args.refine_poses,
                      cuda_graphs=not args.no_cuda_graphs,
                      capacity={"auto": None, "on": True, "off": False}[args.capacity])
    res["machine"] = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                      "cpu_count": os.cpu_count(), "load_average": list(os.getloadavg())}
    gpu = f" ({res['gpu']})" if "gpu" in res else ""
    rows = f" (in buffers of {res['capacity']} rows)" if res["capacity"] else ""
    print(f"training step at {res['size']}x{res['size']}, {res['gaussians']} Gaussians{rows}, {res['device']}{gpu}, "
          f"{res['threads']} threads:")
    print(f"  median {res['step_median_s']:.3f} s wall, {res['step_median_cpu_s']:.3f} s CPU (min {res['step_min_s']:.3f}, "
          f"max {res['step_max_s']:.3f}; target <= {res['target_s']} s)  {res['iterations_per_s']:.2f} it/s")
    g = res["cuda_graphs"]
    how = (f"replayed as CUDA graphs ({g['captures']} captured in {g['capture_s']:.2f} s)" if g["used"]
           else f"eager ({g['off_reason']})")
    print(f"  posing and losses {how}; the stages below are each run eagerly")
    print(f"  {'stage':<22} {'wall s':>8} {'CPU s':>8}")
    for k, v in [*res["stages"].items(), ("other", res["other"])]:
        note = "  (cached up front: 0 per step)" if k == "body_forward" else ""
        note = "  (data, guards, density statistics, overhead)" if k == "other" else note
        print(f"  {k:<22} {v['wall_s']:8.4f} {v['cpu_s']:8.4f}{note}")
    print(f"  density control pass   {res['density_control_once_s']:.3f} s (once per interval)")
    c = res["counts"]
    if c:
        print(f"  per step (mean of {c['steps']} steps): {c['ops_per_step']:.0f} tensor operations launched from Python (a graph replay counts none), "
              f"{c['syncs_per_step']:.2f} host syncs ({c['views_per_step']:.0f} views not counted)")
        if not res["cuda_graphs"]["used"]:
            g = c["in_cuda_graphs"]
            print(f"  of these, in the pieces a CUDA step replays as graphs: posing {g['posing']}, losses "
                  f"{g['losses']} (forward + backward); about {c['ops_per_step'] - g['posing'] - g['losses']:.0f} "
                  "launch one by one")
        if c["syncs_by_op"]:
            print(f"  syncs by operation ({c['steps']} steps): "
                  + ", ".join(f"{k} {v}" for k, v in c["syncs_by_op"].items()))
    print(f"  machine load average   {', '.join(f'{x:.1f}' for x in res['machine']['load_average'])}")
    if args.json:
        from rmavatar.utils.outputs import write_json

        write_json(args.json, res, overwrite=args.overwrite)
        print(f"wrote {args.json}")
    return 0
