"""The ``rmavatar`` command line: the argparse front ends of the library, one module per command.

Each module here has ``add_arguments(parser)`` and ``run(args) -> int`` and turns options into calls of
the library (``rmavatar.train``, ``rmavatar.evaluate``, ...). Only the chosen command's module is
imported, and those modules import the library inside ``run``, so ``--help`` stays fast.
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
    "demo": ("rmavatar.commands.demo", "from nothing to an animated avatar: synthetic subject, training, metrics, videos, PLY"),
    "body": ("rmavatar.commands.body", "look at body models (Anny, SMPL) posed by motion files: body show"),
    "inspect": ("rmavatar.commands.inspect", "summarise a dataset: kind, frames per split, image size, camera, pose ranges"),
    "animate": ("rmavatar.commands.animate", "drive a trained avatar with a motion file (AIST++, AMASS, GART) into an MP4 or PNG frames"),
    "export": ("rmavatar.commands.export", "write a trained avatar as a standard 3DGS PLY (canonical pose or a motion frame)"),
    "view": ("rmavatar.commands.view", "interactive browser viewer (viser) of an avatar, with motion playback and camera presets"),
    "eval": ("rmavatar.commands.eval", "score a trained run on a dataset split: PSNR, SSIM, LPIPS per frame and mean, protocol in the JSON"),
    "train": ("rmavatar.commands.train", "fit an avatar to a dataset's training frames (checkpoints, resume, previews)"),
    "render": ("rmavatar.commands.render", "render a Gaussian scene (synthetic figure or 3DGS PLY) to a PNG, or a trained avatar's turntable video"),
    "bench": ("rmavatar.commands.bench", "benchmarks: raster, step, speed, quality, avatar, render, capture (times, ratios to references, metrics)"),
    "synth": ("rmavatar.commands.synth", "render the synthetic clothed subject (turning in an A-pose, novel poses) into a native dataset"),
    "capture": ("rmavatar.commands.capture", "your own video of one person -> a dataset with estimated poses (MediaPipe + body fit, offline)"),
    "batch": ("rmavatar.commands.batch", "train and evaluate many avatars from a JOBS.yaml on a Ray cluster or this machine; results tables"),
    "reproduce": ("rmavatar.commands.reproduce", "reproduce the paper's tables (PeopleSnapshot, ZJU-MoCap, ablations) as one batch"),
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
    # Set here, once, before any command loads torch (the environment wins): idle OpenMP threads that
    # spin steal the CPU from Numba kernels and other processes on a small machine. Measured on 2 busy
    # cores: a training step at 64x64 took 1.9 s instead of 0.5 s under load 8, and a viewer frame's
    # avatar evaluation 1.2 s instead of 0.12 s.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, modules = _build_parser(argv)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    from rmavatar.utils import outputs

    outputs.command_name = f"rmavatar {args.command}"
    try:
        return int(modules[args.command].run(args) or 0)
    except UserError as exc:
        print(f"rmavatar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"rmavatar {args.command}: interrupted", file=sys.stderr)
        return 130
