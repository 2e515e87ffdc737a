"""``rmavatar inspect DATA``: what a dataset holds (kind, splits, image size, camera, pose ranges)."""

from __future__ import annotations

import argparse
import json

import numpy as np

DESCRIPTION = """\
Summarise a dataset: its kind (native, peoplesnapshot, zju), name, gender/body, frames per split, image
size, camera intrinsics and position, and the range of its SMPL-format parameters per split.
DATA is a folder; the kind is detected from its layout, or named as KIND:PATH. ZJU-MoCap options go
after a '?': zju:PATH?camera=3&mask=cihp.

examples:
  rmavatar inspect data/people_snapshot/male-3-casual
  rmavatar inspect zju:data/CoreView_377?camera=0 --json summary.json
  rmavatar inspect out/synth --check        # also reads every image and mask
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("data", metavar="DATA", help="dataset folder, or KIND:PATH")
    parser.add_argument("--json", metavar="OUT", help="also write the summary as JSON to OUT ('-' for stdout only)")
    parser.add_argument("--size", type=int, default=None,
                        help="report intrinsics for images resized to this longer side")
    parser.add_argument("--body", default=None,
                        help="ZJU only: the body whose rest pelvis converts Rh/Th (default anny; use the "
                             "body you train with, e.g. smpl:PATH)")
    parser.add_argument("--check", action="store_true",
                        help="read every frame's image and mask (finds unreadable or missized files)")


def _stats(a: np.ndarray) -> dict:
    return {"min": a.min(0).round(4).tolist(), "max": a.max(0).round(4).tolist(),
            "mean": a.mean(0).round(4).tolist()}


def summarize(ds) -> dict:
    """A JSON-ready summary of a Dataset."""
    cam = ds.camera(next(iter(ds.splits)), 0)
    cams = [ds.camera(s, i) for s in ds.splits for i in range(ds.num_frames(s))]
    distinct = len({(c.K.tobytes(), c.viewmat.tobytes()) for c in cams})
    out = {
        "kind": ds.kind,
        "name": ds.name,
        "path": str(ds.root),
        "gender": ds.gender,
        "body": ds.body,
        "fps": ds.fps,
        "image_size": list(ds.image_size),
        "source_size": list(ds.source_size),
        "splits": {s: {"frames": len(idx), "first": idx[0], "last": idx[-1]} for s, idx in ds.splits.items()},
        "camera": {
            "fx": round(float(cam.K[0, 0]), 3), "fy": round(float(cam.K[1, 1]), 3),
            "cx": round(float(cam.K[0, 2]), 3), "cy": round(float(cam.K[1, 2]), 3),
            "position": cam.position.round(4).tolist(),
            "distinct_cameras": distinct,
        },
        "poses": {},
    }
    for s in ds.splits:
        p = ds.params(s)
        bp = np.abs(p["body_pose"])
        out["poses"][s] = {
            "global_orient_deg": _stats(np.degrees(p["global_orient"])),
            "transl": _stats(p["transl"]),
            "body_pose_abs_max_deg": round(float(np.degrees(bp.max())), 2),
            "body_pose_abs_mean_deg": round(float(np.degrees(bp.mean())), 2),
            "betas_mean": p["betas"].mean(0).round(4).tolist(),
            "distinct_betas": int(len(np.unique(p["betas"].round(6), axis=0))),
        }
    return out


def _print(summary: dict) -> None:
    w, h = summary["image_size"]
    sw, sh = summary["source_size"]
    print(f"{summary['kind']}: {summary['name']}  ({summary['path']})")
    extra = f" (source {sw}x{sh})" if (sw, sh) != (w, h) else ""
    print(f"  gender {summary['gender']}, body {summary['body']}, fps {summary['fps']}, image {w}x{h}{extra}")
    for s, v in summary["splits"].items():
        print(f"  {s:<11} {v['frames']:>5} frames  (source frames {v['first']}..{v['last']})")
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


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from rmavatar.data import load_dataset
    from rmavatar.utils import atomic_path

    from rmavatar.data.dataset import detect_kind, parse_spec
    from rmavatar.utils import UserError

    options = {}
    if args.body:
        kind, path, _ = parse_spec(args.data)
        if (kind or (detect_kind(path) if path.is_dir() else None)) != "zju":
            raise UserError("--body applies to ZJU-MoCap data only (other kinds store SMPL-style transl)")
        options["body"] = args.body
    ds = load_dataset(args.data, size=args.size, cache_mb=64, **options)
    summary = summarize(ds)
    if args.check:
        total = sum(ds.num_frames(s) for s in ds.splits)
        with tqdm(total=total, desc="checking frames", unit="frame") as bar:
            for s in ds.splits:
                for i in range(ds.num_frames(s)):
                    ds.frame(s, i)
                    bar.update(1)
        summary["checked"] = True
    if args.json == "-":
        print(json.dumps(summary, indent=2))
        return 0
    _print(summary)
    if args.json:
        with atomic_path(args.json) as tmp:
            tmp.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"summary written to {args.json}")
    return 0
