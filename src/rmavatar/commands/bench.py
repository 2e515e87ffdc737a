"""``rmavatar bench NAME``: run one benchmark (the measuring code lives in :mod:`rmavatar.bench`).

Each NAME has an options builder here and a ``run(options) -> int`` in its ``rmavatar.bench`` module;
the modules import the heavy parts inside ``run``.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from rmavatar.utils.outputs import add_overwrite_argument

# name -> (module, one-line help). Add a row per benchmark.
BENCHMARKS: dict[str, tuple[str, str]] = {
    "raster": ("rmavatar.bench.raster", "rasterizer forward / forward+backward time, peak memory, Gaussians/s"),
    "quality": ("rmavatar.bench.quality", "full model vs the paper's ablations and our variants: PSNR/SSIM/LPIPS on test and novel_pose (mean and spread over --seeds), time"),
    "step": ("rmavatar.bench.step", "training iteration time at 256x256 (~25k Gaussians) and its breakdown by stage"),
    "speed": ("rmavatar.bench.speed", "rasterizer, training step and rendering speed, each as time and as a ratio to a reference path"),
    "avatar": ("rmavatar.bench.avatar", "the avatar's forward+backward (posing + rectifier): float32, bfloat16, no rectifier"),
    "render": ("rmavatar.bench.render", "frames per second of a trained avatar (posing + rectifier as one CUDA "
               "graph on a GPU) and the split by stage"),
    "capture": ("rmavatar.bench.capture", "rmavatar capture on a clip: seconds per frame by stage (decode, landmarks, "
                "masks, fit, write), frames with a person, landmarks seen, silhouette IoU of the fitted body"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", metavar="NAME", required=True)
    for name, (_, help_text) in BENCHMARKS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        _OPTIONS[name](p)
        if any("--json" in a.option_strings for a in p._actions):
            add_overwrite_argument(p)


def run(args: argparse.Namespace) -> int:
    from rmavatar.utils import UserError
    from rmavatar.utils.outputs import check_output_file

    # The options every benchmark shares, checked before any measuring.
    if getattr(args, "json", None):
        check_output_file(args.json, option="--json", overwrite=args.overwrite)
    elif getattr(args, "overwrite", False) and args.benchmark != "capture":  # capture's also covers --work
        raise UserError("--overwrite only applies to --json FILE: leave it out")
    for name in ("threads", "gaussians", "avatar_gaussians", "repeats", "steps", "iters", "warmup", "frames"):
        value = getattr(args, name, None)
        least = 0 if name in ("threads", "warmup") else 1
        if value is not None and value < least:
            raise UserError(f"--{name.replace('_', '-')} must be >= {least}, got {value}")
    if getattr(args, "size", None) is not None and not 32 <= args.size <= 8192:
        raise UserError(f"--size must be in 32..8192 pixels, got {args.size}")
    return int(importlib.import_module(BENCHMARKS[args.benchmark][0]).run(args) or 0)


def _raster_options(parser: argparse.ArgumentParser) -> None:
    from rmavatar.bench.raster import DEFAULT_CONFIGS

    parser.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")
    parser.add_argument("--configs", nargs="+", default=list(DEFAULT_CONFIGS), metavar="NxSIZE",
                        help="Gaussian count x square image size (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=7, help="timed repeats per measurement (default 7)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed runs first (default 2)")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "gsplat"),
                        help="rasterizer backend (default: auto)")
    parser.add_argument("--device", default="cpu", help="torch device of the scene (cuda for gsplat)")
    parser.add_argument("--sh-degree", type=int, default=3, help="SH degree of the colours (default 3)")
    parser.add_argument("--disc-scale", type=float, default=1.5,
                        help="Gaussian size as a multiple of the point spacing (default 1.5)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch and Numba threads (default: their defaults, one per core)")
    parser.add_argument("--no-reference", action="store_true", help="skip the dense reference comparison")
    parser.epilog = "Example: rmavatar bench raster --json bench_raster.json"


def _quality_options(parser: argparse.ArgumentParser) -> None:
    from rmavatar.bench.quality import VARIANTS, parse_seeds

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = """examples:
  rmavatar bench quality --json bench_quality.json              # CPU budget: 256px, 1000 iterations
  rmavatar bench quality --iters 50000 --size 1080 --device cuda --data peoplesnapshot:DIR --json q.json
  rmavatar bench quality --variants full no_rectifier --iters 300 --size 128
  rmavatar bench quality --seeds 0,1,2 --variants full no_rectifier local_rectifier --json q3.json
"""
    parser.add_argument("--json", metavar="FILE", help="write the results to this JSON file")
    parser.add_argument("--work", type=Path, default=Path("bench_quality_runs"),
                        help="folder for the dataset and the runs (default bench_quality_runs; reused on rerun)")
    parser.add_argument("--data", default=None, help="dataset (default: the synthetic subject of --seed)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS, metavar="V",
                        help=f"which variants (default all: {' '.join(VARIANTS)})")
    parser.add_argument("--size", type=int, default=256, help="image size (default 256)")
    parser.add_argument("--iters", type=int, default=1000, help="iterations per variant (default 1000)")
    parser.add_argument("--seeds", "--seed", dest="seeds", type=parse_seeds, default=[0], metavar="S[,S...]",
                        help="subject and training seed, or several (0,1,2: three subjects; the table then "
                             "gives mean ± standard deviation over them); default 0")
    parser.add_argument("--max-gaussians", type=int, default=40_000,
                        help="densification cap (default 40000, as the demo; 0 = none)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's choice)")
    parser.add_argument("--device", default="auto", help="auto (CUDA when available), cpu or cuda")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _step_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")
    parser.add_argument("--size", type=int, default=256, help="image size (default 256)")
    parser.add_argument("--data", metavar="DATA",
                        help="dataset to use (default: a small synthetic subject made in a temporary folder)")
    parser.add_argument("--gaussians", type=int, default=None,
                        help="Gaussian count (placement by area; default: one per binding face, ~25k for Anny)")
    parser.add_argument("--steps", type=int, default=15, help="timed training steps (default 15)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu; cuda for the GPU path)")
    parser.add_argument("--no-rectifier", action="store_true", help="time the 'w/o GauRec' model")
    parser.add_argument("--count-steps", type=int, default=20,
                        help="further steps run under an operation counter: tensor operations and host syncs "
                             "per step (default 20; 0 = skip)")
    parser.add_argument("--refine-poses", action="store_true",
                        help="time steps with pose refinement (the body posed with gradients every step)")
    parser.add_argument("--no-cuda-graphs", action="store_true",
                        help="on CUDA, run the step eagerly (the reference for the replayed CUDA graphs)")
    parser.add_argument("--capacity", choices=("auto", "on", "off"), default="auto",
                        help="keep the Gaussians in fixed-size buffers (density.capacity; auto, the default: "
                             "where the step replays as CUDA graphs)")
    parser.epilog = "Example: rmavatar bench step --json bench_step.json"


def _speed_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")
    parser.add_argument("--size", type=int, default=256,
                        help="image size of the rasterizer and training-step measurements (default 256)")
    parser.add_argument("--gaussians", type=int, default=25_000,
                        help="Gaussian count of the rasterizer scene (default 25000)")
    parser.add_argument("--avatar-gaussians", type=int, default=None,
                        help="Gaussian count of the avatar in the training step and rendering, placed by area "
                             "(at least one per binding face; default: one per binding face, 24864 for Anny)")
    parser.add_argument("--render-sizes", type=int, nargs="+", default=[256, 512], metavar="SIZE",
                        help="image sizes of the rendering throughput (default: 256 512)")
    parser.add_argument("--raster-reference", default="1000x64", metavar="NxSIZE",
                        help="configuration of the dense reference rasterizer (default 1000x64)")
    parser.add_argument("--render-reference-size", type=int, default=32,
                        help="image size of the dense-reference rendering pipeline, with all Gaussians "
                             "(default 32)")
    parser.add_argument("--repeats", type=int, default=9, help="timed repeats per measurement (default 9)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed runs first (default 3)")
    parser.add_argument("--steps", type=int, default=15, help="timed training steps per variant (default 15)")
    parser.add_argument("--threads", type=int, default=2, help="torch and Numba threads (default 2)")
    parser.add_argument("--data", metavar="DATA",
                        help="dataset for the training step and the avatar's poses (default: a small "
                             "synthetic subject made in a temporary folder)")
    parser.add_argument("--run", metavar="RUN",
                        help="render this trained run's avatar (default: a freshly initialised avatar)")
    parser.epilog = "Example: rmavatar bench speed --json bench_speed.json"


def _avatar_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gaussians", type=int, default=25_000, help="Gaussian count (default 25000)")
    parser.add_argument("--repeats", type=int, default=20, help="timed repeats (default 20)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch's default)")
    parser.add_argument("--body", default="anny", help="body model spec: anny, anny:PRESET or smpl:PATH (default anny)")
    parser.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")


def _render_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", metavar="RUN", help="a trained run folder (rmavatar train --out)")
    parser.add_argument("--size", type=int, default=1080, help="square image size in pixels (default 1080)")
    parser.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda, cuda:N")
    parser.add_argument("--frames", type=int, default=60, help="timed frames per path (default 60)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed frames first (default 5)")
    parser.add_argument("--motion", metavar="FILE", help="poses to cycle through (default: the run's training poses)")
    parser.add_argument("--no-cuda-graphs", action="store_true",
                        help="on CUDA, pose eagerly (the reference for the replayed CUDA graph)")
    parser.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")


def _capture_options(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = """examples:
  rmavatar bench capture --json capture_synth1080.json       # a synthetic 1920x1080 turn with true poses
  rmavatar bench capture me.mp4 --size 512 --frames 100 --json capture_me.json
"""
    parser.add_argument("input", metavar="INPUT", nargs="?", default=None,
                        help="a video or a folder of frames of one person (default: a synthetic 1920x1080 clip "
                             "of the default subject turning, made in --work, whose true poses are known)")
    parser.add_argument("--size", type=int, default=None,
                        help="longer side of the frames captured, as rmavatar capture --size (default: the clip's)")
    parser.add_argument("--fps", type=float, default=None, metavar="N",
                        help="keep at most N frames per second, as rmavatar capture")
    parser.add_argument("--frames", type=int, default=None, metavar="N",
                        help="use only the first N frames (after --fps; default: all)")
    parser.add_argument("--still", action="store_true",
                        help="capture with --still (the person holds one pose; always on for the synthetic turn)")
    parser.add_argument("--fov", type=float, default=None, metavar="DEGREES",
                        help="the camera's horizontal field of view (default: the synthetic clip's true one, "
                             "else rmavatar capture's default)")
    parser.add_argument("--device", default="auto", help="where the fit runs: auto, cpu, cuda")
    parser.add_argument("--work", metavar="DIR", default=None,
                        help="keep the synthetic clip and the captured dataset here and reuse the clip "
                             "(default: a temporary folder, removed at the end)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--json", metavar="FILE", help="also write the results to this JSON file")


_OPTIONS = {"raster": _raster_options, "quality": _quality_options, "step": _step_options, "speed": _speed_options,
            "avatar": _avatar_options, "render": _render_options, "capture": _capture_options}
