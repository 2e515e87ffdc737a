"""The ``rmavatar`` command line.

Each sub-command lives next to the code it drives, in a module with ``add_arguments(parser)`` and
``run(args) -> int``. Only the chosen command's module is imported, so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from rmavatar import __version__
from rmavatar.utils import UserError

# name -> (module, one-line help). Add a row when a command lands.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("rmavatar.demo", "from nothing to an animated avatar: synthetic subject, training, metrics, videos, PLY"),
    "body": ("rmavatar.body.cli", "look at body models (Anny, SMPL) posed by motion files: body show"),
    "inspect": ("rmavatar.data.inspect_cli", "summarise a dataset: kind, frames per split, image size, camera, pose ranges"),
    "animate": ("rmavatar.animate.cli", "drive a trained avatar with a motion file (AIST++, AMASS, GART) into an MP4 or PNG frames"),
    "export": ("rmavatar.export.cli", "write a trained avatar as a standard 3DGS PLY (canonical pose or a motion frame)"),
    "view": ("rmavatar.viewer.cli", "interactive browser viewer (viser) of an avatar, with motion playback and camera presets"),
    "eval": ("rmavatar.evaluate.cli", "score a trained run on a dataset split: PSNR, SSIM, LPIPS per frame and mean, protocol in the JSON"),
    "train": ("rmavatar.train.cli", "fit an avatar to a dataset's training frames (checkpoints, resume, previews)"),
    "render": ("rmavatar.render.cli", "render a Gaussian scene (synthetic figure or 3DGS PLY) to a PNG"),
    "bench": ("rmavatar.bench.cli", "benchmarks: bench raster (rasterizer speed and memory)"),
    "synth": ("rmavatar.data.synth.cli", "render the synthetic clothed subject (turning in an A-pose, novel poses) into a native dataset"),
    "capture": ("rmavatar.commands.capture", "your own video of one person -> a dataset with estimated poses (MediaPipe + body fit, offline)"),
}


def _build_parser(argv: list[str]) -> tuple[argparse.ArgumentParser, dict]:
    parser = argparse.ArgumentParser(
        prog="rmavatar",
        description="Photorealistic, animatable 3D human avatars from a monocular video "
        "(RMAvatar: Gaussians embedded in a posed body mesh, rectified by a pose-conditioned MLP).",
        epilog="Run 'rmavatar COMMAND --help' for a command's options.",
    )
    parser.add_argument("--version", action="version", version=f"rmavatar {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = next((a for a in argv if not a.startswith("-")), None)
    modules = {}
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            modules[name] = mod
    return parser, modules


def main(argv: list[str] | None = None) -> int:
    # Before torch loads: idle OpenMP threads that spin steal the CPU from Numba kernels and the
    # other process on a small machine (a 10x slowdown measured on 2 busy cores).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, modules = _build_parser(argv)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    try:
        return int(modules[args.command].run(args) or 0)
    except UserError as exc:
        print(f"rmavatar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rmavatar {args.command}: interrupted", file=sys.stderr)
        return 130
