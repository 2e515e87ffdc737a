"""``rmavatar capture INPUT --out DATA``: your own video -> a dataset ``rmavatar train`` reads."""

from __future__ import annotations

import argparse

from rmavatar.utils.outputs import add_overwrite_argument

DESCRIPTION = """\
Turn a video of one person (or a folder of its frames) into a native dataset with estimated poses,
offline: MediaPipe finds the person's mask and landmarks in every frame, the body (Anny by default)
is fitted to all frames at once (Anny's shape, too, to the person's outline), and DATA gets the
frames, masks, camera, SMPL-format poses and body offsets, a train split and a held-out test tail, and
contact_sheet.png: the fitted body drawn over frames of the clip. Look at it before training.

Record: one person, the whole body in view, a static camera (on a tripod or propped up), turning
slowly on the spot in an A-pose (arms lowered, away from the body), 20-60 seconds.

examples:
  rmavatar capture me.mp4 --out data/me                      # a phone video, default camera
  rmavatar capture me.mov --out data/me --fov 65 --fps 10    # known field of view, 10 frames/s
  rmavatar capture me.mp4 --out data/me --still              # a turn in a held A-pose
  rmavatar capture frames/ --out data/me --focal 1400 --size 1080
  rmavatar capture me.mp4 --out data/me --body smpl:models/smpl/SMPL_NEUTRAL.pkl
  rmavatar capture videos/cam04.mp4 --out data/lab --calibration Calib.toml --novel-view videos/cam03.mp4
then:
  rmavatar inspect data/me --overlay check.png
  rmavatar train data/me --out runs/me
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("input", metavar="INPUT",
                        help="a video file (mp4, mov, avi, webm, mkv) or a folder of images (sorted by name)")
    parser.add_argument("--out", required=True, metavar="DATA",
                        help="the dataset folder to write (new, empty, or an earlier capture dataset, which is replaced)")
    camera = parser.add_mutually_exclusive_group()
    camera.add_argument("--fov", type=float, metavar="DEGREES",
                        help="the camera's horizontal field of view (across the frame's width)")
    camera.add_argument("--focal", type=float, metavar="PIXELS",
                        help="the focal length in pixels of the frames written (after --size)")
    camera.add_argument("--calibration", metavar="FILE",
                        help="a calibration of the camera (and of others filming the same clip): a TOML file as "
                             "Pose2Sim and Anipose write it (OpenCV's model) or a Qualisys .qca.txt; its "
                             "intrinsics replace --fov / --focal (lens distortion is not applied)")
    parser.add_argument("--camera", metavar="NAME",
                        help="with --calibration: the input's camera in it (default: the camera named like the "
                             "video, e.g. cam04 for cam04.mp4)")
    parser.add_argument("--novel-view", action="append", default=[], metavar="VIDEO[@CAMERA]",
                        help="with --calibration: a synchronised video of the same clip by another calibrated "
                             "camera (named like the video, or @CAMERA); its frames at the training instants "
                             "become the split novel_view, real ground truth for views the avatar never saw "
                             "(rmavatar eval --split novel_view). Repeatable")
    parser.add_argument("--body", default="anny", metavar="SPEC",
                        help="body to fit: anny (default: the neutral preset), anny:PRESET (neutral, male, "
                             "female, child) or smpl:PATH (SMPL betas are fitted too)")
    parser.add_argument("--fps", type=float, default=None, metavar="N",
                        help="keep at most N frames per second (default: every frame)")
    parser.add_argument("--size", type=int, default=None, metavar="S",
                        help="longer side of the frames written, in pixels (default: the video's)")
    parser.add_argument("--test-fraction", type=float, default=0.2, metavar="F",
                        help="the end of the clip held out as the test split (default 0.2)")
    parser.add_argument("--val-every", type=int, default=0, metavar="K",
                        help="of the frames before the test tail, hold out every K-th as the split val "
                             "(frames between training frames; default 0: none)")
    parser.add_argument("--still", action="store_true",
                        help="the person holds one pose and turns on the spot (the recommended turn in an "
                             "A-pose): every frame's pose and up direction are pulled towards the clip's mean, "
                             "and the mask's outline, seen from every side, weighs more against the "
                             "landmarks; this removes most of the pose error; wrong for walking, dancing or "
                             "gestures")
    # (ShapeFitConfig's bounds, written out: importing it here would import torch for every command's --help)
    parser.add_argument("--no-shape", action="store_true",
                        help="keep the Anny body's preset shape: by default its surface is moved outwards along "
                             "its normals (at most 10 cm, the head 3 cm, the hands not at all) to fit the person's "
                             "outline in the masks, so that an avatar starts on the clothed person, not inside; "
                             "SMPL bodies fit their betas either way")
    parser.add_argument("--iters", type=int, default=None, metavar="N",
                        help="fitting iterations (default 400, after 100 to start)")
    parser.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    add_overwrite_argument(parser)


def run(args: argparse.Namespace) -> int:
    from rmavatar.capture import CaptureConfig, capture
    from rmavatar.capture.fit import BodyFitConfig
    from rmavatar.utils import UserError

    if not 0 < args.test_fraction < 1:  # (CaptureConfig says "the test fraction"; here the option is named)
        raise UserError(f"--test-fraction must lie between 0 and 1 (exclusive), got {args.test_fraction:g}")
    fit = BodyFitConfig().still() if args.still else BodyFitConfig()
    if args.iters is not None:
        if args.iters < 1:
            raise UserError(f"--iters must be >= 1, got {args.iters}")
        fit.iters = args.iters
    cfg = CaptureConfig(body=args.body, fov=args.fov, focal=args.focal, fps=args.fps, size=args.size,
                        test_fraction=args.test_fraction, device=args.device, fit=fit, val_every=args.val_every,
                        calibration=args.calibration, camera=args.camera, novel_views=args.novel_view)
    if args.no_shape:
        cfg.shape = None
    s = capture(args.input, args.out, cfg, progress=not args.quiet, overwrite=args.overwrite)
    dropped = len(s["no_person"]) + len(s["other_person"])
    held = "".join(f" + {s['frames'][k]} {k}" for k in ("val", "novel_view") if k in s["frames"])
    print(f"wrote {s['out']}: {s['frames']['train']} train + {s['frames']['test']} test{held} frames of "
          f"{s['camera']['width']}x{s['camera']['height']} (fx {s['camera']['fx']:.1f} px), body {s['body']}")
    for name, view in (s.get("novel_views") or {}).items():
        print(f"novel view {name}: {view['frames']} frames, {view['offset']:+d} video frames from the main one's "
              f"instants (synchronised by the landmarks); the fitted body covers its masks with IoU "
              f"{view['body_iou']:.3f}")
    if dropped:
        print(f"dropped {dropped} of {s['decoded']} frames: {len(s['no_person'])} without a person "
              f"{s['no_person'][:10]}, {len(s['other_person'])} with another person {s['other_person'][:10]}")
    hands = s.get("hands")
    if hands is not None:
        print(f"hands: the left one found in {hands['left']} of {hands['frames']} frames, the right one in "
              f"{hands['right']} (finger poses in smpl.npz's hand_pose; the others held, then relaxed)")
    shape = s.get("shape")
    if shape is not None:
        print(f"shape: the body's surface moved by {shape['mean_mm']:.0f} mm on average (from {shape['min_mm']:.0f} "
              f"to {shape['max_mm']:.0f} mm) to fit the outline in {shape['frames']} frames (smpl.npz's body_offsets)")
    t = s["seconds"]
    views = f"other cameras {t['views']:.1f} s, " if t["views"] else ""
    w, h = s["detection_size"]
    print(f"{s['seconds_per_frame']:.2f} s per frame, {s['total_seconds']:.1f} s in all (decoding {t['decode']:.1f} s, "
          f"landmarks {t['landmarks']:.1f} s at {w}x{h}, masks {t['masks']:.1f} s, fitting {t['fit']:.1f} s, "
          f"shape {t['shape']:.1f} s, {views}writing {t['write']:.1f} s)")
    print(f"look at {s['out']}/contact_sheet.png, then: rmavatar train {s['out']} --out runs/NAME")
    return 0
