"""Where a late training step's time goes: wall time, GPU kernel time, kernel launches and host syncs.

Runs the trainer's own ``step()`` on DATA at SIZE (the default config, as ``rmavatar train`` does), from
the first iteration with every SH band on (``late_iteration``), then 10 more steps under
``torch.profiler``. A step whose GPU kernel time is far below its wall time is launch- or sync-bound.

    python scripts/gpu_profile.py DATA --size 512 --device cuda --json profile.json

Numbers (per step): wall_ms (synced, unprofiled), gpu_kernel_ms (sum of the kernels' device time),
gpu_kernels (kernels run on the device, those replayed inside CUDA graphs included), kernel_launches
(cudaLaunchKernel calls from the host), graph_launches, host_syncs (rmavatar.bench.counting's count of
the operations that make the host wait), sync_api_calls (cuda*Synchronize / blocking copies seen by the
profiler, the script's own closing sync excluded). On the CPU only wall_ms, host_syncs and the CPU table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from rmavatar.bench.step import count_step_ops, late_iteration
from rmavatar.data.registry import normalize_spec
from rmavatar.train.config import TrainConfig
from rmavatar.train.trainer import Trainer

LAUNCH_APIS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")
GRAPH_APIS = ("cudaGraphLaunch", "cuGraphLaunch")
SYNC_APIS = ("cudaDeviceSynchronize", "cudaStreamSynchronize", "cudaEventSynchronize", "cudaMemcpy")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", help="dataset (as for rmavatar train), e.g. a folder made by rmavatar synth")
    p.add_argument("--size", type=int, default=512, help="image size (default 512)")
    p.add_argument("--device", default="cuda", help="torch device (default cuda)")
    p.add_argument("--warmup", type=int, default=10, help="untimed steps first (default 10)")
    p.add_argument("--steps", type=int, default=30, help="timed steps, unprofiled (default 30)")
    p.add_argument("--profiled", type=int, default=10, help="steps under the profiler (default 10)")
    p.add_argument("--count-steps", type=int, default=10,
                   help="steps under the host-sync counter (default 10; 0 = skip)")
    p.add_argument("--json", help="also write the numbers and the top kernels to this JSON file")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    cfg = TrainConfig()
    cfg.data.path, cfg.data.size, cfg.device = normalize_spec(args.data), args.size, args.device
    cfg.log.tensorboard = False
    cuda = torch.device(args.device).type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    res: dict = {"size": args.size, "device": args.device}
    with tempfile.TemporaryDirectory() as run:
        tr = Trainer(cfg, Path(run), progress=False)
        tr.setup()
        tr.iteration = late_iteration(cfg)

        def one() -> None:
            tr.step()
            tr.iteration += 1

        for _ in range(args.warmup):
            one()
        sync()
        t0 = time.perf_counter()
        for _ in range(args.steps):
            one()
        sync()
        res["wall_ms"] = 1e3 * (time.perf_counter() - t0) / args.steps
        if args.count_steps > 0:
            counts = count_step_ops(one, args.count_steps)
            res["host_syncs"] = counts.get("syncs_per_step")
            res["ops"] = counts.get("ops_per_step")
            res["syncs_by_op"] = counts.get("syncs_by_op")
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        with profile(activities=acts) as prof:
            for _ in range(args.profiled):
                one()
            sync()
        events = prof.key_averages()
        n = args.profiled
        if cuda:
            dev = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
            kernels = [e for e in dev if not e.key.startswith(("Memcpy", "Memset"))]
            res["gpu_kernel_ms"] = sum(e.self_device_time_total for e in dev) / 1e3 / n
            res["gpu_kernels"] = sum(e.count for e in kernels) / n
            res["kernel_launches"] = sum(e.count for e in events if e.key in LAUNCH_APIS) / n
            res["graph_launches"] = sum(e.count for e in events if e.key in GRAPH_APIS) / n
            res["sync_api_calls"] = (sum(e.count for e in events if e.key in SYNC_APIS) - 1) / n
            res["gpu_busy_fraction"] = res["gpu_kernel_ms"] / res["wall_ms"]
            res["max_memory_allocated_mib"] = torch.cuda.max_memory_allocated() / 2**20
            res["gpu"] = torch.cuda.get_device_name()
            top = sorted(dev, key=lambda e: -e.self_device_time_total)[:25]
            res["top_kernels"] = [{"name": e.key[:120], "ms_per_step": e.self_device_time_total / 1e3 / n,
                                   "calls_per_step": e.count / n} for e in top]
            print(events.table(sort_by="self_cuda_time_total", row_limit=25, max_name_column_width=70))
        print(events.table(sort_by="self_cpu_time_total", row_limit=20, max_name_column_width=70))
        res["gaussians"] = int(tr.avatar.num_gaussians)
        res["cuda_graphs"] = bool(getattr(getattr(tr, "graphs", None), "enabled", False))
    print(json.dumps({k: v for k, v in res.items() if k != "top_kernels"}, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
