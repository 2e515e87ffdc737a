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
        "applied. The file is y down (the 3DGS / COLMAP convention), so the avatar stands upright in "
        "SuperSplat and other 3DGS viewers; --up y writes it y up instead."
    )
    parser.epilog = (
        "examples:\n"
        "  rmavatar export runs/me --ply me.ply\n"
        "  rmavatar export runs/me --ply me_dance40.ply --motion aist_demo.npz --frame 40\n"
        "  rmavatar export runs/me --ply me_yup.ply --up y      # for tools that want y up\n"
        "The motion frame is used as is (its own translation and orientation), not re-centred.\n"
        "rmavatar render --ply reads both conventions (the header's 'comment rmavatar up' line says which)."
    )
    parser.add_argument("run", metavar="RUN", help="a training run folder (holds checkpoints/last.pt)")
    parser.add_argument("--ply", required=True, metavar="OUT.ply", help="output PLY file")
    parser.add_argument("--motion", metavar="FILE", default=None, help="pose the avatar with a frame of this motion")
    parser.add_argument("--frame", type=int, default=None, metavar="K",
                        help="frame of --motion (default 0; negative counts from the end)")
    parser.add_argument("--pose", choices=("tpose", "apose", "train"), default=None,
                        help="pose when no --motion is given: tpose (the zero pose, default), apose (arms down "
                             "45 degrees) or train (the median pose of the training frames)")
    parser.add_argument("--up", type=up_axis, default="-y", metavar="{-y,y}",
                        help="the file's world convention: -y (default; y down and the avatar facing -z, "
                             "the 3DGS / COLMAP / OpenCV convention that SuperSplat, PlayCanvas' "
                             "splat-transform viewer and other stock 3DGS viewers expect) or y (y up, facing "
                             "+z: rmavatar's and SMPL's world, for tools that want y up); write -y as --up=-y")
    add_overwrite_argument(parser)


def up_axis(text: str) -> str:
    """argparse type of ``--up``: "-y" or "y", anything else refused with the choices explained."""
    if text not in ("-y", "y"):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a world convention rmavatar writes: -y (y down, the 3DGS / COLMAP convention "
            "stock viewers expect; the default) or y (y up)")
    return text


def run(args: argparse.Namespace) -> int:
    from rmavatar.avatar import load_trained
    from rmavatar.export.export import check_ply_output, export_ply, pose_for_export
    from rmavatar.utils import UserError

    # Options that would have no effect are errors, not silently ignored.
    if args.motion is None and args.frame is not None:
        raise UserError("--frame picks a frame of --motion: add --motion FILE or leave it out")
    if args.motion is not None and args.pose is not None:
        raise UserError("--pose is the pose without --motion (a motion frame gives the pose): leave one out")
    args.frame = 0 if args.frame is None else args.frame
    args.pose = args.pose or "tpose"
    out = check_ply_output(args.ply, args.overwrite)  # the string as given: 'a.ply/' is refused
    trained = load_trained(args.run)
    n = export_ply(trained, pose_for_export(trained, args.motion, args.frame, args.pose), out,
                   overwrite=args.overwrite, up=args.up)
    print(f"wrote {n} Gaussians to {out} ({'y down, the 3DGS convention' if args.up == '-y' else 'y up'})")
    return 0
