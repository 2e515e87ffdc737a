"""``rmavatar view``: look at a trained avatar in the browser, optionally playing a motion."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Open an interactive 3D viewer of a trained avatar in the browser (viser's Gaussian-splat "
        "renderer). With --motion, a timeline slider, a play checkbox and a speed slider drive the avatar; "
        "camera buttons jump to front, side and back views. Stop with Ctrl-C.\n"
        "The browser shows the degree-0 (view-independent) colour of each Gaussian."
    )
    parser.epilog = (
        "examples:\n"
        "  rmavatar view runs/me                      # then open http://localhost:8080\n"
        "  rmavatar view runs/me --motion aist_demo.npz --port 8081\n"
        "  rmavatar view runs/me --host 0.0.0.0       # reachable from other machines"
    )
    parser.add_argument("run", metavar="RUN", help="a training run folder (holds checkpoints/last.pt)")
    parser.add_argument("--motion", metavar="FILE", default=None, help="motion file to play (.npz or .npy)")
    parser.add_argument("--frames", metavar="A:B", default=None, help="motion frames to use (python slice rules)")
    parser.add_argument("--pose", choices=("tpose", "apose", "train"), default=None,
                        help="pose shown without --motion: tpose (default), apose, or train (the median "
                             "training pose)")
    parser.add_argument("--port", type=int, default=8080,
                        help="port to serve on (default 8080; when taken, the next free port is used)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0 for all)")


def _check_host(host: str) -> None:
    """UserError unless this machine can listen on ``host`` (else the server retries ports for ever)."""
    import socket

    from rmavatar.utils import UserError

    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as sock:
            sock.bind(addr)
    except (OSError, UnicodeError) as exc:
        raise UserError(f"--host {host}: cannot listen on this address ({getattr(exc, 'strerror', None) or exc}); "
                        "use 127.0.0.1, 0.0.0.0 or an address of this machine") from None


def run(args: argparse.Namespace) -> int:
    import time

    from rmavatar.animate.motion import parse_frame_range
    from rmavatar.avatar import load_trained
    from rmavatar.body import motion_to_sequence
    from rmavatar.utils import UserError
    from rmavatar.viewer.app import avatar_viewer

    # Options that would have no effect are errors, not silently ignored.
    if args.motion is None and args.frames is not None:
        raise UserError("--frames selects frames of --motion: add --motion FILE or leave it out")
    if args.motion is not None and args.pose is not None:
        raise UserError("--pose is the pose shown without --motion: leave one out")
    args.pose = args.pose or "tpose"
    if not 0 <= args.port <= 65535:
        raise UserError(f"--port must be in 0..65535, got {args.port}")
    _check_host(args.host)
    seq, fps = None, 30.0
    if args.motion is not None:
        from rmavatar.body import load_motion

        motion = load_motion(args.motion)
        seq = motion_to_sequence(motion, source=str(args.motion))
        seq = seq.select(parse_frame_range(args.frames, len(seq)))
        fps = motion.fps or 30.0
    trained = load_trained(args.run)
    try:
        viewer = avatar_viewer(trained, seq, fps=fps, host=args.host, port=args.port, rest=args.pose)
    except OSError as exc:
        raise UserError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
    print(f"viewer running at http://{'localhost' if args.host in ('127.0.0.1', '0.0.0.0') else args.host}:"
          f"{viewer.port}  (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    finally:
        viewer.close()
