"""``rmavatar bench raster``: speed and memory of the rasterizer on an avatar-like scene.

For each (N Gaussians, image size): forward and forward+backward wall time (median over repeats
after warm-up), peak resident-memory growth during one forward+backward, Gaussians per second.
The dense float64 reference is timed on a small configuration it fits, next to the fast backend on
the same configuration, and reported as a ratio.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import threading
import time

DEFAULT_CONFIGS = ("10000x256", "10000x512", "50000x256", "50000x512")
REFERENCE_CONFIG = "1000x64"


def _parse_config(text: str, option: str = "--configs") -> tuple[int, int]:
    from rmavatar.utils import UserError

    try:
        n, size = text.lower().split("x")
        n, size = int(n), int(size)
        if n < 1 or not 1 <= size <= 8192:
            raise ValueError
        return n, size
    except ValueError:
        raise UserError(f"{option}: {text!r} is not NxSIZE (N >= 1 Gaussians x SIZE 1..8192 pixels), "
                        "e.g. 10000x256") from None


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class _PeakRSS:
    """Polls this process's resident set size in a thread; ``peak - start`` is the growth."""

    def __init__(self, interval: float = 0.001):
        self.interval = interval

    def __enter__(self):
        self.start = self.peak = _rss_bytes()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()
        return self

    def _poll(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss_bytes())
            time.sleep(self.interval)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())


def _measure(fn_forward, repeats: int, warmup: int, sync, memory: bool) -> dict:
    """fn_forward() -> (image, alpha, params); times forward and forward+backward."""
    import torch

    weights = {}

    def fwd_bwd():
        image, alpha, params = fn_forward()
        if "w" not in weights:
            g = torch.Generator().manual_seed(0)
            weights["w"] = torch.rand(image.shape, generator=g, dtype=image.dtype).to(image.device)
        loss = (image * weights["w"]).sum() + alpha.sum()
        loss.backward()
        for p in params:
            p.grad = None
        sync()

    def fwd():
        fn_forward()
        sync()

    def timed(f):
        for _ in range(warmup):
            f()
        wall, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            f()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        return wall, cpu

    t_f, c_f = timed(fwd)
    t_fb, c_fb = timed(fwd_bwd)
    out = {
        "forward_s": statistics.median(t_f),
        "forward_backward_s": statistics.median(t_fb),
        "forward_s_min": min(t_f),
        "forward_backward_s_min": min(t_fb),
        # CPU seconds of this process summed over its threads: less sensitive to other load.
        "forward_cpu_s": statistics.median(c_f),
        "forward_backward_cpu_s": statistics.median(c_fb),
    }
    if memory:
        _release_free_memory()
        with _PeakRSS() as mem:
            fwd_bwd()
        out["peak_rss_growth_mb"] = (mem.peak - mem.start) / 2**20
    return out


def _release_free_memory() -> None:
    """Hand freed heap pages back to the OS (glibc), so RSS growth counts the next call's memory."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _scene(n: int, size: int, sh_degree: int, device: str, disc_scale: float):
    import torch

    from rmavatar.render.scenes import figure_scene, orbit_camera

    sc = figure_scene(n, seed=0, sh_degree=sh_degree, disc_scale=disc_scale)
    params = {k: v.to(device).requires_grad_(True) for k, v in sc.items()}
    viewmat, K = orbit_camera(size)
    bg = torch.ones(3, device=device, requires_grad=True)
    return params, viewmat.to(device), K.to(device), bg


def _bench_one(n, size, args, sync, rasterize_fn, dtype=None, memory=True) -> dict:
    params, viewmat, K, bg = _scene(n, size, args.sh_degree, args.device, args.disc_scale)
    if dtype is not None:
        params = {k: v.detach().to(dtype).requires_grad_(True) for k, v in params.items()}
        viewmat, K, bg = viewmat.to(dtype), K.to(dtype), bg.detach().to(dtype).requires_grad_(True)
    plist = list(params.values()) + [bg]

    def forward():
        image, alpha, _ = rasterize_fn(params["means"], params["quats"], params["scales"], params["opacities"],
                                       params["colors"], viewmat, K, size, size, background=bg,
                                       sh_degree=args.sh_degree)
        return image, alpha, plist

    return _measure(forward, args.repeats, args.warmup, sync, memory)


def _scene_stats(n, size, args) -> dict:
    import torch

    from rmavatar.render import rasterize

    params, viewmat, K, bg = _scene(n, size, args.sh_degree, "cpu", args.disc_scale)
    with torch.no_grad():
        image, alpha, info = rasterize(params["means"], params["quats"], params["scales"], params["opacities"],
                                       params["colors"], viewmat, K, size, size, sh_degree=args.sh_degree,
                                       backend="cpu")
    vis = info["visible"]
    return {
        "visible": int(vis.sum()),
        "mean_radius_px": float(info["radii"][vis].float().mean()) if vis.any() else 0.0,
        "covered_fraction": float((alpha > 0.5).float().mean()),
    }


def _check_args(args: argparse.Namespace) -> list[tuple[int, int]]:
    """Check the options and apply ``--threads`` to torch and numba; returns the (N, size) configs."""
    import torch

    from rmavatar.utils import UserError

    configs = [_parse_config(c) for c in args.configs]
    if args.repeats < 1 or args.warmup < 0:
        raise UserError("--repeats must be >= 1 and --warmup >= 0")
    if not 0 <= args.sh_degree <= 3:
        raise UserError(f"--sh-degree must be 0..3, got {args.sh_degree}")
    if not (math.isfinite(args.disc_scale) and args.disc_scale > 0):
        raise UserError(f"--disc-scale must be a number > 0, got {args.disc_scale}")
    try:
        torch.device(args.device)
    except RuntimeError:
        raise UserError(f"--device {args.device}: not a torch device (use cpu, cuda or cuda:N)") from None
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {args.device}: no CUDA device is available")
    from rmavatar.render._numba import numba

    if args.threads is not None:
        if not 1 <= args.threads <= numba.config.NUMBA_NUM_THREADS:
            raise UserError(f"--threads must be 1..{numba.config.NUMBA_NUM_THREADS}")
        torch.set_num_threads(args.threads)
        numba.set_num_threads(args.threads)
    return configs


def _bench_configs(configs: list[tuple[int, int]], args: argparse.Namespace, sync, fast) -> list[dict]:
    """Time ``fast`` on each (N, size) config, printing a line each; returns one result row per config."""
    results = []
    for n, size in configs:
        row = {"n": n, "size": size, **_bench_one(n, size, args, sync, fast)}
        row["gaussians_per_s_forward_backward"] = n / row["forward_backward_s"]
        row["gaussians_per_s_forward"] = n / row["forward_s"]
        row.update(_scene_stats(n, size, args))
        results.append(row)
        print(
            f"N={n:>6} {size}x{size}: forward {row['forward_s'] * 1e3:7.1f} ms, forward+backward "
            f"{row['forward_backward_s'] * 1e3:7.1f} ms (CPU {row['forward_backward_cpu_s'] * 1e3:.0f} ms), "
            f"peak RSS +{row['peak_rss_growth_mb']:.0f} MB, "
            f"{row['gaussians_per_s_forward_backward'] / 1e3:.0f}k Gaussians/s (fwd+bwd)",
            flush=True,
        )
    return results


def _bench_reference(args: argparse.Namespace, sync, fast) -> dict:
    """Time the dense float64 reference and ``fast`` on REFERENCE_CONFIG, printing the speed-up; returns
    both timings and the speed-ups."""
    import torch

    from rmavatar.render.reference import reference_rasterize

    n, size = _parse_config(REFERENCE_CONFIG)
    ref_args = argparse.Namespace(**{**vars(args), "repeats": min(args.repeats, 3), "warmup": 1})
    ref = _bench_one(n, size, ref_args, sync, reference_rasterize, dtype=torch.float64)
    ours = _bench_one(n, size, ref_args, sync, fast, dtype=torch.float64)
    reference = {
        "n": n, "size": size, "dtype": "float64 (both)",
        "reference": ref, "fast": ours,
        "speedup_forward": ref["forward_s"] / ours["forward_s"],
        "speedup_forward_backward": ref["forward_backward_s"] / ours["forward_backward_s"],
    }
    print(
        f"dense reference N={n} {size}x{size}: forward+backward {ref['forward_backward_s'] * 1e3:.0f} ms "
        f"(+{ref['peak_rss_growth_mb']:.0f} MB) vs {ours['forward_backward_s'] * 1e3:.1f} ms: "
        f"{reference['speedup_forward_backward']:.0f}x faster",
        flush=True,
    )
    return reference


def _report(args: argparse.Namespace, results: list[dict], reference: dict | None, load_before) -> dict:
    """The JSON report: settings, scene and method descriptions, machine, results; returns it."""
    import torch

    from rmavatar.render._numba import numba

    return {
        "benchmark": "raster",
        "backend": args.backend,
        "device": args.device,
        "scene": f"figure_scene: surface discs (sigma = {args.disc_scale} x point spacing) on a 1.8 m "
                 f"figure, 3 m away, SH degree {args.sh_degree}, white background, "
                 "loss = sum(w * image) + sum(alpha)",
        "timing": f"median of {args.repeats} runs after {args.warmup} warm-up runs, wall clock",
        "memory": "peak_rss_growth_mb: growth of the process's resident set during one forward+backward "
                  "after a warm-up and malloc_trim, polled every 1 ms from /proc/self/statm",
        "machine": {
            "cpus": os.cpu_count(), "platform": platform.platform(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(), "numba": numba.__version__,
            "numba_threads": numba.get_num_threads(),
            "loadavg_before": load_before, "loadavg_after": os.getloadavg(),
        },
        "results": results,
        "reference": reference,
    }


def run(args: argparse.Namespace) -> int:
    import numpy as np  # noqa: F401  (imported before torch threads start, as in real use)
    import torch

    from rmavatar.render import rasterize
    from rmavatar.utils.outputs import write_json

    configs = _check_args(args)
    cuda = args.device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)

    def fast(*a, **kw):
        return rasterize(*a, backend=args.backend, **kw)

    load_before = os.getloadavg()
    results = _bench_configs(configs, args, sync, fast)
    reference = None
    if not args.no_reference and not cuda:
        reference = _bench_reference(args, sync, fast)
    report = _report(args, results, reference, load_before)
    if args.json:
        write_json(args.json, report, overwrite=args.overwrite)
        print(f"wrote {args.json}")
    return 0
