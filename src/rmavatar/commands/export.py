"""``rmavatar export``: write a trained avatar as a standard 3D Gaussian Splatting PLY."""

from __future__ import annotations

import argparse

from rmavatar.utils.outputs import add_overwrite_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Export a trained avatar as a standard 3DGS PLY (world-space positions, log-scales and rotations, "
        "opacity logits, SH colours) that stock 3DGS viewers open. The avatar stands in its canonical "
        "pose (zero pose: T-pose), an A-pose, its training pose, or frame K of a motion file, with the rectifier "
        "applied."
    )
    parser.epilog = (
        "examples:\n"
        "  rmavatar export runs/me --ply me.ply\n"
        "  rmavatar export runs/me --ply me_dance40.ply --motion aist_demo.npz --frame 40\n"
        "The motion frame is used as is (its own translation and orientation), not re-centred."
    )
    parser.add_argument("run", metavar="RUN", help="a training run folder (holds checkpoints/last.pt)")
    parser.add_argument("--ply", required=True, metavar="OUT.ply", help="output PLY file")
    parser.add_argument("--motion", metavar="FILE", default=None, help="pose the avatar with a frame of this motion")
    parser.add_argument("--frame", type=int, default=0, metavar="K",
                        help="frame of --motion (default 0; negative counts from the end)")
    parser.add_argument("--pose", choices=("tpose", "apose", "train"), default="tpose",
                        help="pose when no --motion is given: tpose (the zero pose, default), apose (arms down "
                             "45 degrees) or train (the median pose of the training frames)")
    add_overwrite_argument(parser)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from rmavatar.avatar import load_trained
    from rmavatar.export.export import check_ply_output, export_ply, pose_for_export

    out = check_ply_output(Path(args.ply), args.overwrite)
    trained = load_trained(args.run)
    n = export_ply(trained, pose_for_export(trained, args.motion, args.frame, args.pose), out,
                   overwrite=args.overwrite)
    print(f"wrote {n} Gaussians to {out}")
    return 0
