"""``rmavatar animate``: drive a trained avatar with a motion file and write a video."""

from __future__ import annotations

import argparse

from rmavatar.utils.outputs import add_overwrite_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Drive a trained avatar with a motion file (AIST++ / InstantAvatar .npz, AMASS .npz, GART .npy, "
        "anything 'rmavatar.body.load_motion' reads) and render it to an MP4 or PNG frames.\n"
        "The motion is turned upright (y-up, z-up and camera-frame motions all work), faces the camera in "
        "its first frame, and its root travel is removed so the person stays in view; the pose-dependent "
        "rectifier is applied. The avatar keeps its own body shape (the motion's betas are ignored). AMASS "
        "SMPL-H / SMPL-X motions pose the fingers too; motions without finger poses leave the hands relaxed."
    )
    parser.epilog = (
        "examples:\n"
        "  rmavatar animate runs/me --motion aist_demo.npz --out dance.mp4\n"
        "  rmavatar animate runs/me --motion walk.npz --out walk.mp4 --camera orbit --fps 30 --size 720\n"
        "  rmavatar animate runs/me --motion walk.npz --out frames/ --frames 0:60   # PNG frames"
    )
    parser.add_argument("run", metavar="RUN", help="a training run folder (holds checkpoints/last.pt)")
    parser.add_argument("--motion", required=True, metavar="FILE", help="motion file (.npz or .npy)")
    parser.add_argument("--out", required=True, metavar="OUT",
                        help="an .mp4 file (H.264, yuv420p), or a folder (ending in '/') for PNG frames")
    parser.add_argument("--camera", choices=("fixed", "orbit"), default="fixed",
                        help="fixed: in front of the body; orbit: one turn around it over the clip (default fixed)")
    parser.add_argument("--fps", type=float, default=None,
                        help="output frame rate; with a motion of known rate a lower FPS takes every k-th frame "
                             "so the motion keeps its speed (default: the motion's rate, else 30)")
    parser.add_argument("--size", type=int, default=512, help="image height (and width) in pixels, made even (default 512)")
    parser.add_argument("--frames", metavar="A:B", default=None,
                        help="motion frames to use, python slice rules (B exclusive), e.g. 0:120 or 30:")
    parser.add_argument("--bg", default="white", help="background: white (default), black, gray or R,G,B in 0..1")
    parser.add_argument("--fov", type=float, default=30.0, help="vertical field of view in degrees (default 30)")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    add_overwrite_argument(parser)


def run(args: argparse.Namespace) -> int:
    from rmavatar.animate.jobs import VideoOptions, animate_video, parse_background
    from rmavatar.animate.motion import parse_frame_range
    from rmavatar.animate.video import check_output
    from rmavatar.avatar import load_trained
    from rmavatar.body import load_motion, motion_to_sequence
    from rmavatar.utils import UserError
    from rmavatar.utils.device import resolve_device

    try:
        device = resolve_device(args.device)
    except UserError as exc:
        raise UserError(f"--device {args.device}: {exc}") from None
    background = parse_background(args.bg)
    # Every option is checked before any slow work (the fps placeholder stands for the motion's rate). A
    # given --fps is checked as given: 0 or NaN is an error, never silently replaced by a default.
    fps_given = args.fps is not None
    VideoOptions(size=args.size, fov_deg=args.fov, background=background,
                 fps=args.fps if fps_given else 30.0).validate()
    check_output(args.out, args.overwrite)
    motion = load_motion(args.motion)
    seq = motion_to_sequence(motion, source=str(args.motion))
    step = 1
    fps = args.fps if fps_given else (motion.fps or 30.0)
    if fps_given and motion.fps and args.fps < motion.fps:
        step = max(1, round(motion.fps / args.fps))
    seq = seq.select(parse_frame_range(args.frames, len(seq), step))
    trained = load_trained(args.run, device=device)
    opts = VideoOptions(size=args.size, fov_deg=args.fov, background=background, fps=fps, overwrite=args.overwrite)
    n = animate_video(trained, seq, args.out, camera=args.camera, opts=opts)
    print(f"wrote {n} frames at {fps:g} fps to {args.out}")
    return 0
