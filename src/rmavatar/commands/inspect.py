"""``rmavatar inspect DATA``: what a dataset holds (kind, splits, image size, camera, pose ranges)."""

from __future__ import annotations

import argparse
import json

from rmavatar.utils.outputs import add_overwrite_argument

DESCRIPTION = """\
Summarise a dataset: its kind (native, peoplesnapshot, zju), name, gender/body, frames per split, image
size, camera intrinsics and position, and the range of its SMPL-format parameters per split.
DATA is a folder; the kind is detected from its layout, or named as KIND:PATH. ZJU-MoCap options go
after a '?': zju:PATH?camera=3&mask=cihp.

examples:
  rmavatar inspect data/people_snapshot/male-3-casual
  rmavatar inspect zju:data/CoreView_377?camera=0 --json summary.json
  rmavatar inspect out/synth --check        # also reads every image and mask
  rmavatar inspect data/me --overlay me.png  # frames with the posed body projected on them
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("data", metavar="DATA", help="dataset folder, or KIND:PATH")
    parser.add_argument("--json", metavar="OUT", help="also write the summary as JSON to OUT ('-' for stdout only)")
    parser.add_argument("--size", type=int, default=None,
                        help="report intrinsics for images resized to this longer side")
    parser.add_argument("--body", default=None,
                        help="body model for --overlay (default: the dataset's preset, else anny) and, for "
                             "ZJU, the body whose rest pelvis converts Rh/Th (use the one you train with, "
                             "e.g. smpl:PATH)")
    parser.add_argument("--overlay", metavar="PNG", default=None,
                        help="write a contact sheet: a few frames per split with the posed body's vertices "
                             "projected by the frame's camera (checks that poses, cameras and masks agree)")
    parser.add_argument("--frames", type=int, default=None,
                        help="frames per split on the --overlay sheet (default 4)")
    parser.add_argument("--check", action="store_true",
                        help="also read every frame's image and mask: unreadable or missized files, masks "
                             "that are all empty or saved 0/1 (cameras and poses are always checked)")
    add_overwrite_argument(parser)


def _print(summary: dict) -> None:
    w, h = summary["image_size"]
    sw, sh = summary["source_size"]
    print(f"{summary['kind']}: {summary['name']}  ({summary['path']})")
    extra = f" (source {sw}x{sh})" if (sw, sh) != (w, h) else ""
    print(f"  gender {summary['gender']}, body {summary['body']}, fps {summary['fps']}, image {w}x{h}{extra}, "
          f"poses {summary['pose_source']}")
    video = summary.get("video_frames")
    for s, v in summary["splits"].items():
        if video is not None:
            vf = video["splits"][s]
            print(f"  {s:<11} {v['frames']:>5} frames  (dataset frames {v['first']}..{v['last']} = video frames "
                  f"{vf['first']}..{vf['last']})")
        else:
            which = "dataset" if summary["kind"] == "native" else "source"
            print(f"  {s:<11} {v['frames']:>5} frames  ({which} frames {v['first']}..{v['last']})")
    if video is not None:
        print(f"  frames      video frames are the 0-based frame numbers in {video['source']} of the dataset's "
              f"frames (meta.yaml extra.source_frames), the numbers on contact_sheet.png and in capture.npz's "
              f"source_index")
    c = summary["camera"]
    print(f"  camera      fx {c['fx']} fy {c['fy']} cx {c['cx']} cy {c['cy']}, centre {c['position']} m, "
          f"{c['distinct_cameras']} distinct camera(s)")
    for s, p in summary["poses"].items():
        t = p["transl"]
        g = p["global_orient_deg"]
        print(f"  {s:<11} transl min {t['min']} max {t['max']} m")
        print(f"  {'':<11} global_orient min {g['min']} max {g['max']} deg; body_pose |max| "
              f"{p['body_pose_abs_max_deg']} deg, |mean| {p['body_pose_abs_mean_deg']} deg; "
              f"{p['distinct_betas']} distinct betas")
        hands = p.get("hands")
        if hands is not None:
            found = hands.get("hand_found_share")
            seen = "" if found is None else f"; left hand found in {found[0]:.0%} of frames, right {found[1]:.0%}"
            print(f"  {'':<11} finger poses: |max| {hands['hand_pose_abs_max_deg']} deg{seen}")


def _video_frames(ds) -> dict | None:
    """For a dataset ``rmavatar capture`` wrote: which frame of the video each dataset frame is (meta.yaml's
    extra.source_frames, the video's 0-based frame numbers), per split; None for other datasets."""
    from rmavatar.data.native import read_meta

    doc = read_meta(ds.root)
    frames = doc["extra"].get("source_frames")
    if not isinstance(frames, list) or len(frames) != doc["num_frames"]:
        return None
    return {
        "source": doc["extra"].get("source", "the video"),
        "numbering": "0-based frame number in the video (a folder of images: in its sorted file list)",
        "frames": frames,
        "splits": {s: {"first": frames[idx[0]], "last": frames[idx[-1]], "frames": [frames[i] for i in idx]}
                   for s, idx in ds.splits.items()},
    }


def run(args: argparse.Namespace) -> int:
    from rmavatar.data import load_dataset
    from rmavatar.data.registry import detect_kind, parse_spec
    from rmavatar.data.summary import overlay_sheet, summarize
    from rmavatar.data.checks import check_dataset
    from rmavatar.utils import UserError
    from rmavatar.utils.outputs import check_output_file, output_file, write_json

    # Options that would have no effect are errors, not silently ignored.
    if not args.overlay and args.frames is not None:
        raise UserError("--frames only sets the frames per split of the --overlay sheet: add --overlay PNG or "
                        "leave it out")
    if args.overwrite and not args.overlay and args.json in (None, "-"):
        raise UserError("--overwrite only applies to --json FILE and --overlay PNG: leave it out")
    args.frames = 4 if args.frames is None else args.frames
    if args.frames < 1:
        raise UserError(f"--frames must be >= 1, got {args.frames}")
    if args.size is not None and not 1 <= args.size <= 8192:
        raise UserError(f"--size must be in 1..8192 pixels, got {args.size}")
    if args.json and args.json != "-":
        check_output_file(args.json, option="--json", overwrite=args.overwrite)
    if args.overlay:
        check_output_file(args.overlay, option="--overlay", overwrite=args.overwrite, suffixes=(".png",))
    kind, path, _ = parse_spec(args.data)
    kind = kind or (detect_kind(path) if path.is_dir() else None)
    if args.body and not args.overlay and kind != "zju":
        raise UserError(f"--body only matters with --overlay (or for a ZJU-MoCap dataset, which {args.data} is "
                        "not): add --overlay PNG or leave it out")
    options = {"body": args.body} if args.body and kind == "zju" else {}
    ds = load_dataset(args.data, size=args.size, cache_mb=64, **options)
    summary = summarize(ds)
    if ds.kind == "native":
        video = _video_frames(ds)
        if video is not None:
            summary["video_frames"] = video
    if args.check:
        summary["checked"] = check_dataset(ds, progress=True)
    if args.json == "-":
        print(json.dumps(summary, indent=2))
    else:
        _print(summary)
    if args.json and args.json != "-":
        write_json(args.json, summary, overwrite=args.overwrite)
        print(f"summary written to {args.json}")
    if args.overlay:
        from PIL import Image

        spec = args.body or ds.body or "anny"
        body = ds.body_model(spec)
        small = load_dataset(args.data, size=args.size or 256, cache_mb=64, **options)
        sheet = overlay_sheet(small, body, per_split=max(1, args.frames))
        with output_file(args.overlay, option="--overlay", overwrite=args.overwrite, suffixes=(".png",)) as tmp:
            Image.fromarray(sheet).save(tmp)
        if args.json != "-":
            print(f"overlay ({spec}) written to {args.overlay}")
    return 0
