"""``rmavatar render``: render a Gaussian scene or a trained avatar to a PNG, or an avatar's turntable to a video.

Sources (pick one): ``--random N`` (a structured synthetic figure of N Gaussians), ``--ply FILE`` (a
standard 3DGS PLY, in either world convention, see :mod:`rmavatar.export.ply`) or ``RUN`` (a trained
run: a still of the avatar, or with ``--turntable`` a 360-degree video). Add a source by adding an
option and a loader below.

``--ply`` and ``RUN`` draw the same picture of the same Gaussians: both work in rmavatar's y-up world
(``read_ply`` brings a y-down file up) and are framed by :func:`rmavatar.animate.camera.frame_camera`, which only looks at the
Gaussians' positions; so ``render --ply`` of an exported avatar matches ``render RUN`` of its pose.
"""

from __future__ import annotations

import argparse
import math

DEFAULT_AZIMUTH = 20.0
DEFAULT_ELEVATION = 0.0
DEFAULT_FOV = 30.0
DEFAULT_POSE = "tpose"
DEFAULT_FRAMES = 90
DEFAULT_FPS = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Render a synthetic figure (--random), a standard 3DGS PLY (--ply) or a trained avatar (RUN) to a PNG, "
        "or a trained avatar's 360-degree turntable (RUN --turntable) to a video. --ply and RUN show the "
        "avatar upright and framed alike: render --ply of an exported avatar matches render RUN of the "
        "same pose."
    )
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--random", type=int, metavar="N", help="render a synthetic figure made of N Gaussians")
    src.add_argument("--ply", metavar="FILE",
                     help="render a standard 3DGS PLY file (y down as 3DGS files are, or y up when its header "
                          "says 'comment rmavatar up y', as rmavatar export --up y writes)")
    src.add_argument("run", nargs="?", metavar="RUN",
                     help="a trained run: a still of its avatar (--pose, --azimuth, --elevation), or with "
                          "--turntable a 360-degree video")
    parser.add_argument("--out", required=True, metavar="OUT",
                        help="output image (PNG); with --turntable an .mp4 or a folder/ for PNG frames")
    parser.add_argument("--size", type=int, default=512, help="image width and height in pixels (default 512)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of --random (default 0)")
    parser.add_argument("--azimuth", type=float, default=None, metavar="DEG",
                        help=f"camera turn about the vertical axis in degrees (default {DEFAULT_AZIMUTH:g}); "
                             "RUN and --ply: 0 looks at the avatar's front, positive turns towards its left; "
                             "not with --turntable (it goes all the way round)")
    parser.add_argument("--elevation", type=float, default=None, metavar="DEG",
                        help=f"camera height angle in degrees, -90..90 exclusive (default {DEFAULT_ELEVATION:g}; "
                             "RUN and --ply)")
    parser.add_argument("--fov", type=float, default=None, metavar="DEG",
                        help=f"vertical field of view in degrees (default {DEFAULT_FOV:g}; RUN and --ply)")
    parser.add_argument("--background", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("R", "G", "B"),
                        help="background colour in 0..1 (default white)")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "gsplat"),
                        help="rasterizer backend of the PNG (default auto: gsplat on a CUDA GPU, else cpu)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output rmavatar cannot prove it wrote (files it did not write "
                             "are never deleted)")
    group = parser.add_argument_group("trained avatar (RUN)")
    group.add_argument("--pose", choices=("tpose", "apose", "train"), default=None,
                       help="the avatar's pose: tpose (the canonical zero pose, default), apose (arms lowered 45 "
                            "degrees) or train (the median pose of the training frames, e.g. their A-pose)")
    group.add_argument("--turntable", action="store_true",
                       help="a 360-degree orbit around the avatar instead of a still: --out is an .mp4 or a "
                            "folder/ for PNG frames")
    group.add_argument("--frames", type=int, default=None, metavar="N",
                       help=f"turntable frames (default {DEFAULT_FRAMES})")
    group.add_argument("--fps", type=float, default=None, help=f"turntable frame rate (default {DEFAULT_FPS:g})")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        "examples:\n"
        "  rmavatar render runs/me --out still.png                          # the avatar in its T-pose\n"
        "  rmavatar render runs/me --out side.png --pose apose --azimuth 90 --elevation 10\n"
        "  rmavatar render runs/me --turntable --out turn.mp4 --size 512 --frames 120\n"
        "  rmavatar render --ply avatar.ply --out splat.png                 # what rmavatar export wrote\n"
        "  rmavatar render --ply point_cloud.ply --out splat.png --size 768  # any 3DGS PLY\n"
        "  rmavatar render --random 20000 --out figure.png"
    )


def run(args: argparse.Namespace) -> int:
    import imageio.v3 as iio
    import torch

    from rmavatar.render import render_gaussians
    from rmavatar.render.gaussians import GaussianSet
    from rmavatar.render.scenes import figure_scene, orbit_camera
    from rmavatar.utils import UserError
    from rmavatar.utils.outputs import check_output_file, output_file

    _check_arguments(args)
    if args.turntable:
        return _run_turntable(args)
    check_output_file(args.out, option="--out", overwrite=args.overwrite, suffixes=(".png",))
    azimuth = DEFAULT_AZIMUTH if args.azimuth is None else args.azimuth
    if args.random is not None:
        if args.random < 1:
            raise UserError(f"--random needs N >= 1 Gaussians, got {args.random}")
        scene = figure_scene(args.random, seed=args.seed, sh_degree=3)
        gs = GaussianSet(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"], 3)
        viewmat, K = orbit_camera(args.size, azimuth)  # the figure is built y down, for this camera
        what = f"{args.random} Gaussians"
    else:
        if args.ply is not None:
            from rmavatar.export.ply import read_ply

            gs = read_ply(args.ply)  # in the y-up world, whichever convention the file is in
            what = str(args.ply)
        else:
            from rmavatar.avatar import load_trained

            trained = load_trained(args.run)
            pose = args.pose or DEFAULT_POSE
            gs = trained.pose(trained.rest_pose(pose), 0)
            what = f"the avatar of {args.run} in its {pose}"
        elevation = DEFAULT_ELEVATION if args.elevation is None else args.elevation
        fov = DEFAULT_FOV if args.fov is None else args.fov
        from rmavatar.animate.camera import frame_camera

        viewmat, K = frame_camera(gs.means, args.size, azimuth, elevation, fov)
    device = "cuda" if args.backend != "cpu" and torch.cuda.is_available() else "cpu"
    gs = GaussianSet(gs.means.to(device), gs.quats.to(device), gs.scales.to(device), gs.opacities.to(device),
                     gs.sh.to(device), gs.sh_degree, None if gs.frames is None else gs.frames.to(device))
    with torch.no_grad():
        image, _, info = render_gaussians(gs, viewmat, K, args.size, args.size,
                                          background=torch.tensor(args.background), backend=args.backend)
    pixels = (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
    with output_file(args.out, option="--out", overwrite=args.overwrite, suffixes=(".png",)) as tmp:
        iio.imwrite(tmp, pixels)
    print(f"wrote {args.out} ({args.size}x{args.size}, {what}: {int(info['visible'].sum())} of {len(gs)} "
          f"Gaussians visible, backend {info['backend']})")
    return 0


def _check_arguments(args: argparse.Namespace) -> None:
    """UserError, naming the option, for values or combinations no render can use (before any slow work)."""
    from rmavatar.utils import UserError

    if args.size <= 0 or args.size > 8192:
        raise UserError(f"--size must be 1..8192, got {args.size}")
    if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in args.background):
        raise UserError(f"--background values must be in 0..1, got {tuple(args.background)}")
    if args.azimuth is not None and not math.isfinite(args.azimuth):
        raise UserError(f"--azimuth must be a finite number of degrees, got {args.azimuth}")
    if args.elevation is not None and not (math.isfinite(args.elevation) and -90.0 < args.elevation < 90.0):
        raise UserError(f"--elevation must be between -90 and 90 degrees (exclusive), got {args.elevation}")
    if args.fov is not None and not (math.isfinite(args.fov) and 0.0 < args.fov < 180.0):
        raise UserError(f"--fov must be between 0 and 180 degrees (exclusive), got {args.fov}")
    source = "--random" if args.random is not None else "--ply" if args.ply is not None else None
    if source is not None:
        given = [name for name, value in (("--pose", args.pose), ("--frames", args.frames), ("--fps", args.fps))
                 if value is not None] + (["--turntable"] if args.turntable else [])
        if source == "--random":
            given += [name for name, value in (("--elevation", args.elevation), ("--fov", args.fov))
                      if value is not None]
        if given:
            raise UserError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to a trained RUN, "
                            f"not to {source} (e.g. rmavatar render RUN --out still.png --pose apose)")
    elif args.turntable:
        if args.azimuth is not None:
            raise UserError("--azimuth sets the camera of a still; a --turntable goes all the way round "
                            "(leave --azimuth out)")
    else:
        given = [name for name, value in (("--frames", args.frames), ("--fps", args.fps)) if value is not None]
        if given:
            raise UserError(f"{' and '.join(given)} {'is' if len(given) == 1 else 'are'} for --turntable videos "
                            "(rmavatar render RUN --turntable --out turn.mp4); without it RUN renders a still PNG")


def _run_turntable(args: argparse.Namespace) -> int:
    from rmavatar.animate.jobs import VideoOptions, turntable_video
    from rmavatar.animate.video import check_output
    from rmavatar.avatar import load_trained
    from rmavatar.utils import UserError

    frames = DEFAULT_FRAMES if args.frames is None else args.frames
    fps = DEFAULT_FPS if args.fps is None else args.fps
    if frames < 1:
        raise UserError(f"--frames must be >= 1, got {frames}")
    if fps <= 0:
        raise UserError(f"--fps must be positive, got {fps}")
    background = tuple(float(v) for v in args.background)
    opts = VideoOptions(size=args.size, fov_deg=DEFAULT_FOV if args.fov is None else args.fov,
                        background=background, fps=fps, overwrite=args.overwrite).validate()
    check_output(args.out, args.overwrite)  # before any slow work
    trained = load_trained(args.run)
    n = turntable_video(trained, args.out, num_frames=frames, pose=args.pose or DEFAULT_POSE, opts=opts,
                        elevation_deg=DEFAULT_ELEVATION if args.elevation is None else args.elevation)
    print(f"wrote a {n}-frame turntable of {args.run} to {args.out}")
    return 0
