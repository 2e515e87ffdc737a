"""``rmavatar body``: look at body models and motion files.

Examples::

    rmavatar body show --body anny --pose tpose --out tpose.png
    rmavatar body show --body anny:female --motion aist_demo.npz --frame 120 --out dance.png
    rmavatar body show --body smpl:models/smpl --gender male --motion walk.npz --frame 10 --out w.png
"""

from __future__ import annotations

import argparse
import math

from rmavatar.utils.outputs import add_overwrite_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    show = sub.add_parser(
        "show",
        help="render a posed body to a PNG (front and side views)",
        description="Render a body model in a pose (T-pose, A-pose, or a frame of a motion file) to a PNG: "
        "front and side views, flat-shaded, joints as red dots.",
        epilog="examples:" + __doc__.split("Examples::")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    show.add_argument("--body", default="anny", help="anny, anny:PRESET (neutral, male, female, child) or "
                      "smpl:PATH (file or folder with the three genders); default: anny")  # fmt: skip
    show.add_argument("--gender", choices=("neutral", "male", "female"), default=None,
                      help="picks the SMPL file in a folder, or the Anny preset for plain 'anny'")  # fmt: skip
    show.add_argument("--motion", help="motion file: AIST++/InstantAvatar or AMASS .npz, GART .npy")
    show.add_argument("--frame", type=int, default=None, help="frame of the motion file (default 0)")
    show.add_argument("--orient", choices=("auto", "keep", "none"), default=None,
                      help="the motion's global orientation: keep it, drop it (none), or auto: keep it but "
                      "turn the body upright when the file is y-down (camera-style, e.g. the AIST++ "
                      "demo), default auto")  # fmt: skip
    show.add_argument("--pose", choices=("tpose", "apose"), default=None,
                      help="pose when no --motion is given (default tpose)")  # fmt: skip
    show.add_argument("--views", default="front,side", help="comma-separated: front, side, back")
    show.add_argument("--size", type=int, default=512, help="pixels per view (default 512)")
    show.add_argument("--out", required=True, help="output PNG path")
    add_overwrite_argument(show)


def run(args: argparse.Namespace) -> int:
    import torch

    from rmavatar.body import load_body_model, load_motion
    from rmavatar.body.lbs import axis_angle_to_matrix, matrix_to_axis_angle
    from rmavatar.body.render import render_mesh
    from rmavatar.utils import UserError
    from rmavatar.utils.outputs import check_output_file, output_file

    # Options that would have no effect are errors, not silently ignored.
    if args.motion is None:
        given = [o for o, v in (("--frame", args.frame), ("--orient", args.orient)) if v is not None]
        if given:
            raise UserError(f"{' and '.join(given)} only appl{'ies' if len(given) == 1 else 'y'} to a frame of "
                            f"--motion: add --motion FILE or leave {'it' if len(given) == 1 else 'them'} out")
    elif args.pose is not None:
        raise UserError("--pose is the pose without --motion (a motion frame gives the pose): leave one out")
    if args.gender is not None and args.body.strip().lower().startswith("anny:"):
        raise UserError(f"--gender picks the preset of plain 'anny' (or an SMPL file); --body {args.body} names "
                        "its preset already: leave one out")
    args.frame = 0 if args.frame is None else args.frame
    args.orient = args.orient or "auto"
    args.pose = args.pose or "tpose"
    views = tuple(v.strip() for v in args.views.split(",") if v.strip())
    if not views or any(v not in ("front", "side", "back") for v in views):
        raise UserError(f"--views must list front, side or back, got {args.views!r}")
    if not 16 <= args.size <= 4096:
        raise UserError(f"--size must be in 16..4096 pixels per view, got {args.size}")
    check_output_file(args.out, option="--out", overwrite=args.overwrite, suffixes=(".png",))
    body = load_body_model(args.body, args.gender)
    global_orient = torch.zeros(1, 3)
    body_pose = torch.zeros(1, 69)
    hand_pose = None  # relaxed hands, unless the motion has finger poses
    if args.motion:
        motion = load_motion(args.motion)
        if not 0 <= args.frame < len(motion):
            raise UserError(f"--frame {args.frame} is outside {args.motion} (frames 0..{len(motion) - 1})")
        global_orient = torch.from_numpy(motion.global_orient[args.frame : args.frame + 1])
        body_pose = torch.from_numpy(motion.body_pose[args.frame : args.frame + 1])
        if motion.hand_pose is not None:
            hand_pose = torch.from_numpy(motion.hand_pose[args.frame : args.frame + 1])
        if args.orient == "none":
            global_orient = torch.zeros(1, 3)
        elif args.orient == "auto":
            R = axis_angle_to_matrix(global_orient)
            if R[0, 1, 1] < 0:  # the pelvis' up axis points down: view it rotated by pi about x
                flip = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
                global_orient = matrix_to_axis_angle(flip @ R)
        label = f"{args.motion} frame {args.frame}"
    elif args.pose == "apose":
        # SMPL shoulders are joints 16/17 (body_pose rows 15/16): arms down 45 degrees about +-z.
        body_pose = body_pose.view(1, 23, 3).clone()
        body_pose[0, 15, 2] = -math.pi / 4
        body_pose[0, 16, 2] = math.pi / 4
        body_pose = body_pose.view(1, 69)
        label = "A-pose"
    else:
        label = "T-pose"
    with torch.no_grad():
        out = body(None, global_orient, body_pose, torch.zeros(1, 3), hand_pose=hand_pose)
    image = render_mesh(out.vertices[0].numpy(), body.faces.numpy(), size=args.size, views=views,
                        points=out.joints[0].numpy())  # fmt: skip
    with output_file(args.out, option="--out", overwrite=args.overwrite, suffixes=(".png",)) as tmp:
        image.save(tmp, format="PNG")
    print(f"wrote {args.out}: {body.spec}, {label}, {out.vertices.shape[1]} vertices")
    return 0
