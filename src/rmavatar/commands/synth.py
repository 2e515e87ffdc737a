"""``rmavatar synth OUT``: render the synthetic clothed subject into a native dataset folder."""

from __future__ import annotations

import argparse

from rmavatar.utils.outputs import add_overwrite_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Render a synthetic clothed person (the Anny body in a loose striped tunic whose hem swings and "
        "folds with the pose, trousers, shoes, hair, a painted face) turning round in an A-pose in front "
        "of a static camera, like PeopleSnapshot. Writes a native dataset (train / val / test / "
        "novel_pose [/ novel_view] splits) plus OUT/contact_sheet.png. Deterministic for a seed."
    )
    parser.epilog = "Example: rmavatar synth data/synth0 --size 256 --seed 0   (see docs/synth.md)"
    parser.add_argument("out", help="output folder (written atomically; an earlier synth dataset there is replaced, "
                        "anything else is refused)")
    parser.add_argument("--size", type=int, default=256, help="image width and height in pixels (default 256)")
    parser.add_argument("--seed", type=int, default=0, help="picks the outfit colours, motion details, noise")
    parser.add_argument("--preset", default="neutral", choices=("neutral", "male", "female", "child"),
                        help="Anny body preset (default neutral)")
    parser.add_argument("--train", type=int, default=100, help="training frames (default 100)")
    parser.add_argument("--test", type=int, default=30,
                        help="test frames: the contiguous tail of the turn, as in PeopleSnapshot (default 30)")
    parser.add_argument("--novel-pose", type=int, default=30,
                        help="frames of a different motion (walking, arm raises) from the same camera (default 30)")
    parser.add_argument("--novel-views", type=int, default=0, metavar="N",
                        help="extra cameras that render the test poses, split 'novel_view' (default 0)")
    parser.add_argument("--turns", type=float, default=1.75,
                        help="full turns over the train+test frames (default 1.75)")
    parser.add_argument("--pose-noise", type=float, default=0.0, metavar="DEG",
                        help="tracker-like noise (degrees, per axis) on the stored poses; images are unaffected")
    parser.add_argument("--ss", type=int, default=3, help="supersampling: samples per pixel side (default 3)")
    parser.add_argument("--hand-motion", action="store_true",
                        help="the fingers move (open, fist, pointing, spread) and their poses are stored as "
                             "hand_pose; without it the hands stay relaxed")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite_argument(parser)


def run(args: argparse.Namespace) -> int:
    from rmavatar.data.synth import SynthConfig, synthesize

    cfg = SynthConfig(size=args.size, seed=args.seed, preset=args.preset, train=args.train, test=args.test,
                      novel_pose=args.novel_pose, novel_views=args.novel_views, turns=args.turns,
                      pose_noise=args.pose_noise, ss=args.ss, hand_motion=args.hand_motion)  # fmt: skip
    summary = synthesize(args.out, cfg, progress=not args.quiet, overwrite=args.overwrite)
    frames = ", ".join(f"{k} {v}" for k, v in summary["frames"].items())
    print(f"wrote {summary['out']} ({frames}) in {summary['seconds']:.1f} s")
    print(f"contact sheet: {summary['out']}/contact_sheet.png")
    return 0
