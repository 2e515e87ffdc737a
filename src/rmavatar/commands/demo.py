"""``rmavatar demo``: from nothing to an animated avatar in one command (see :mod:`rmavatar.demo`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rmavatar.utils import UserError

EXAMPLES = """\
examples:
  rmavatar demo                          # everything into ./demo_out (about 10 minutes on 2 CPU cores)
  rmavatar demo --out /tmp/d --seed 3    # another synthetic subject
  rmavatar demo --size 128 --iters 600   # a quicker, rougher run

The folder then holds data/ (the synthetic dataset), run/ (the trained avatar: rmavatar eval|animate|
export|view RUN work on it), eval_test/ and eval_novel_pose/ (render | ground truth | error images),
animation.mp4, turntable.mp4, avatar.ply and metrics.json.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EXAMPLES
    from rmavatar.demo import DemoConfig

    d = DemoConfig()
    parser.add_argument("--out", type=Path, default=d.out, help=f"output folder (default {d.out})")
    parser.add_argument("--seed", type=int, default=d.seed, help="picks the synthetic subject and training seed")
    parser.add_argument("--size", type=int, default=d.size, help=f"image size in pixels (default {d.size})")
    parser.add_argument("--iters", type=int, default=d.iters, help=f"training iterations (default {d.iters})")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: all cores)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder that holds other files (they are kept; none may have a name "
                             "the demo writes)")


def run(args: argparse.Namespace) -> int:
    if args.size < 32:
        raise UserError(f"--size must be at least 32 pixels (LPIPS needs it), got {args.size}")
    if args.iters < 1:
        raise UserError(f"--iters must be positive, got {args.iters}")
    if args.size > 4096:
        raise UserError(f"--size must be at most 4096 pixels, got {args.size}")
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    from rmavatar.demo import DemoConfig, run_demo

    cfg = DemoConfig(out=args.out, seed=args.seed, size=args.size, iters=args.iters, threads=args.threads,
                     overwrite=args.overwrite)
    run_demo(cfg, progress=not args.quiet)
    return 0
