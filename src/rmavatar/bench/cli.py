"""``rmavatar bench NAME``: run one benchmark.

Each NAME maps to a module with ``add_arguments(parser)`` and ``run(args) -> int``, like a top-level
command; keep heavy imports inside ``run`` since every row's ``add_arguments`` is called.
"""

from __future__ import annotations

import argparse
import importlib

# name -> (module, one-line help). Add a row per benchmark.
BENCHMARKS: dict[str, tuple[str, str]] = {
    "raster": ("rmavatar.bench.raster", "rasterizer forward / forward+backward time, peak memory, Gaussians/s"),
    "quality": ("rmavatar.bench.quality", "full model vs the paper's ablations: PSNR/SSIM/LPIPS on test and novel_pose, time"),
    "step": ("rmavatar.bench.step", "training iteration time at 256x256 (~25k Gaussians) and its breakdown by stage"),
    "speed": ("rmavatar.bench.speed", "rasterizer, training step and rendering speed, each as time and as a ratio to a reference path"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", metavar="NAME", required=True)
    for name, (module, help_text) in BENCHMARKS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        importlib.import_module(module).add_arguments(p)


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(BENCHMARKS[args.benchmark][0]).run(args) or 0)
