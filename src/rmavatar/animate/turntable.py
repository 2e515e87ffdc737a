"""The avatar mode of ``rmavatar render``: ``rmavatar render RUN --turntable --out turn.mp4``.

``rmavatar.render.cli`` adds these options and hands over to :func:`run_turntable` when RUN is given.
"""

from __future__ import annotations

import argparse


def add_turntable_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the avatar mode (``--out``, ``--size``, ``--background`` are the render command's)."""
    group = parser.add_argument_group("avatar mode (rmavatar render RUN --turntable --out turn.mp4)")
    group.add_argument("--turntable", action="store_true",
                       help="a 360-degree orbit around the trained avatar of RUN: --out is an .mp4 or a folder/ "
                            "for PNG frames")
    group.add_argument("--frames", type=int, default=90, metavar="N", help="turntable frames (default 90)")
    group.add_argument("--fps", type=float, default=30.0, help="turntable frame rate (default 30)")
    group.add_argument("--pose", choices=("tpose", "apose", "train"), default="tpose",
                       help="the avatar's pose: tpose (the canonical zero pose, default), apose (arms lowered 45 "
                            "degrees) or train (the median pose of the training frames, e.g. their A-pose)")
    group.add_argument("--elevation", type=float, default=0.0, help="camera height angle in degrees (default 0)")
    group.add_argument("--fov", type=float, default=30.0, help="vertical field of view in degrees (default 30)")
    parser.epilog = (parser.epilog or "") + (
        "\n  rmavatar render runs/me --turntable --out turn.mp4 --size 512 --frames 120"
    )


def run_turntable(args: argparse.Namespace) -> int:
    from rmavatar.animate.drive import Poser
    from rmavatar.animate.jobs import VideoOptions, turntable_video
    from rmavatar.animate.video import check_output
    from rmavatar.train import load_run
    from rmavatar.utils import UserError

    if not args.turntable:
        raise UserError("rendering a trained run needs --turntable (e.g. rmavatar render RUN --turntable --out turn.mp4)")
    if args.frames < 1:
        raise UserError(f"--frames must be >= 1, got {args.frames}")
    if args.fps <= 0:
        raise UserError(f"--fps must be positive, got {args.fps}")
    background = tuple(float(v) for v in args.background)
    if not all(0.0 <= v <= 1.0 for v in background):
        raise UserError(f"--background values must be in 0..1, got {background}")
    check_output(args.out)  # before any slow work
    run = load_run(args.run)
    opts = VideoOptions(size=args.size, fov_deg=args.fov, background=background, fps=args.fps)
    n = turntable_video(Poser.from_run(run), args.out, num_frames=args.frames, pose=args.pose, opts=opts,
                        elevation_deg=args.elevation)
    print(f"wrote a {n}-frame turntable of {args.run} to {args.out}")
    return 0
