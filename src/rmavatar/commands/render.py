"""``rmavatar render``: render a Gaussian scene to a PNG, or a trained avatar's turntable to a video.

Scene sources (pick one): ``--random N`` (a structured synthetic figure of N Gaussians) or
``--ply FILE`` (a standard 3DGS PLY). Add a source by adding an option and a loader below.
Avatar mode: ``rmavatar render RUN --turntable --out turn.mp4``.
"""

from __future__ import annotations

import argparse
import math


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--random", type=int, metavar="N", help="render a synthetic figure made of N Gaussians")
    src.add_argument("--ply", metavar="FILE", help="render a standard 3DGS PLY file")
    src.add_argument("run", nargs="?", metavar="RUN", help="a trained run (with --turntable: a 360-degree video)")
    parser.add_argument("--out", required=True, metavar="PNG", help="output image (PNG)")
    parser.add_argument("--size", type=int, default=512, help="image width and height in pixels (default 512)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of --random (default 0)")
    parser.add_argument("--azimuth", type=float, default=20.0, help="camera turn about the vertical, degrees (default 20)")
    parser.add_argument("--background", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("R", "G", "B"),
                        help="background colour in 0..1 (default white)")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "gsplat"), help="rasterizer backend")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output rmavatar cannot prove it wrote (files it did not write "
                             "are never deleted)")
    parser.epilog = "Examples:\n  rmavatar render --random 20000 --out figure.png\n  rmavatar render --ply point_cloud.ply --out splat.png --size 768"
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    _turntable_arguments(parser)


def _frame_camera(means, size: int, azimuth: float):
    """A camera orbiting the scene's median point at a distance that frames its central 90%."""

    import torch

    from rmavatar.render.scenes import orbit_camera

    centre = means.median(dim=0).values
    spread = (means - centre).norm(dim=-1).quantile(0.9).item() if len(means) > 1 else 1.0
    spread = max(spread, 1e-3)
    distance = 2.2 * spread
    viewmat, K = orbit_camera(size, azimuth, distance)
    # orbit_camera frames 1.8 m at its distance; rescale the focal length to frame 2*spread instead.
    K[0, 0] = K[1, 1] = 0.9 * size * distance / (2 * spread)
    shift = torch.eye(4)
    shift[:3, 3] = -centre
    return viewmat @ shift, K


def run(args: argparse.Namespace) -> int:
    import imageio.v3 as iio
    import torch

    from rmavatar.render import rasterize
    from rmavatar.render.scenes import figure_scene, orbit_camera
    from rmavatar.utils import UserError

    from rmavatar.utils.outputs import check_output_file, output_file

    if args.size <= 0 or args.size > 8192:
        raise UserError(f"--size must be 1..8192, got {args.size}")
    if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in args.background):
        raise UserError(f"--background values must be in 0..1, got {tuple(args.background)}")
    if args.run is not None:
        return _run_turntable(args)
    check_output_file(args.out, option="--out", overwrite=args.overwrite, suffixes=(".png",))
    if args.random is not None:
        if args.random < 1:
            raise UserError(f"--random needs N >= 1 Gaussians, got {args.random}")
        scene = figure_scene(args.random, seed=args.seed, sh_degree=3)
        scene["sh_degree"] = 3
        viewmat, K = orbit_camera(args.size, args.azimuth)
    else:
        from rmavatar.export.ply import read_ply

        ply = read_ply(args.ply)
        scene = {"means": ply.means, "quats": ply.quats, "scales": ply.scales, "opacities": ply.opacities,
                 "colors": ply.sh, "sh_degree": ply.sh_degree}
        viewmat, K = _frame_camera(scene["means"], args.size, args.azimuth)
    device = "cuda" if args.backend != "cpu" and torch.cuda.is_available() else "cpu"
    to = {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in scene.items()}
    with torch.no_grad():
        image, alpha, info = rasterize(
            to["means"], to["quats"], to["scales"], to["opacities"], to["colors"],
            viewmat.to(device), K.to(device), args.size, args.size,
            background=torch.tensor(args.background, device=device), sh_degree=scene["sh_degree"],
            backend=args.backend,
        )
    pixels = (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
    with output_file(args.out, option="--out", overwrite=args.overwrite, suffixes=(".png",)) as tmp:
        iio.imwrite(tmp, pixels)
    print(f"wrote {args.out} ({args.size}x{args.size}, {int(info['visible'].sum())} of {len(scene['means'])} "
          f"Gaussians visible, backend {info['backend']})")
    return 0


def _turntable_arguments(parser: argparse.ArgumentParser) -> None:
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


def _run_turntable(args: argparse.Namespace) -> int:
    from rmavatar.animate.jobs import VideoOptions, turntable_video
    from rmavatar.animate.video import check_output
    from rmavatar.avatar import load_trained
    from rmavatar.utils import UserError

    if not args.turntable:
        raise UserError("rendering a trained run needs --turntable (e.g. rmavatar render RUN --turntable --out turn.mp4)")
    if args.frames < 1:
        raise UserError(f"--frames must be >= 1, got {args.frames}")
    if args.fps <= 0:
        raise UserError(f"--fps must be positive, got {args.fps}")
    background = tuple(float(v) for v in args.background)
    opts = VideoOptions(size=args.size, fov_deg=args.fov, background=background, fps=args.fps,
                        overwrite=args.overwrite).validate()
    check_output(args.out, args.overwrite)  # before any slow work
    trained = load_trained(args.run)
    n = turntable_video(trained, args.out, num_frames=args.frames, pose=args.pose, opts=opts,
                        elevation_deg=args.elevation)
    print(f"wrote a {n}-frame turntable of {args.run} to {args.out}")
    return 0
