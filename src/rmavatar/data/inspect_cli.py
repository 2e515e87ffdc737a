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
    parser.add_argument("--frames", type=int, default=4, help="frames per split on the --overlay sheet")
    parser.add_argument("--check", action="store_true",
                        help="read every frame's image and mask (finds unreadable or missized files)")


def _stats(a: np.ndarray) -> dict:
    a = np.asarray(a, np.float64)
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
        "pose_source": "estimated" if ds.poses_estimated else "given",
        "image_size": list(ds.image_size),
        "source_size": list(ds.source_size),
        "splits": {s: {"frames": len(idx), "first": idx[0], "last": idx[-1]} for s, idx in ds.splits.items()},
        "camera": {
            "fx": round(float(cam.K[0, 0]), 3), "fy": round(float(cam.K[1, 1]), 3),
            "cx": round(float(cam.K[0, 2]), 3), "cy": round(float(cam.K[1, 2]), 3),
            "position": cam.position.astype(np.float64).round(4).tolist(),
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
            "betas_mean": p["betas"].astype(np.float64).mean(0).round(4).tolist(),
            "distinct_betas": int(len(np.unique(p["betas"].round(6), axis=0))),
        }
    return out


def _print(summary: dict) -> None:
    w, h = summary["image_size"]
    sw, sh = summary["source_size"]
    print(f"{summary['kind']}: {summary['name']}  ({summary['path']})")
    extra = f" (source {sw}x{sh})" if (sw, sh) != (w, h) else ""
    print(f"  gender {summary['gender']}, body {summary['body']}, fps {summary['fps']}, image {w}x{h}{extra}, "
          f"poses {summary['pose_source']}")
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


def posed_vertices(body, frame) -> np.ndarray:
    """The body posed by a Frame's parameters -> vertices [V,3] (numpy)."""
    import torch

    t = lambda a: torch.as_tensor(np.asarray(a, np.float32))[None]  # noqa: E731
    nb = int(getattr(body, "num_betas", 0))
    betas = None
    if nb > 0:
        full = np.zeros(nb, np.float32)
        full[: min(nb, 10)] = frame.betas[:nb]
        betas = t(full)
    with torch.no_grad():
        out = body(betas, t(frame.global_orient), t(frame.body_pose), t(frame.transl))
    return out.vertices[0].detach().cpu().numpy()


def overlay_sheet(ds, body, per_split: int = 4) -> np.ndarray:
    """Evenly spaced frames of every split (a row each) with the posed body's vertices drawn where the
    frame's camera projects them; outside the mask the image is dimmed. Returns [H,W,3] uint8."""
    from PIL import Image, ImageDraw

    w, h = ds.image_size
    splits = list(ds.splits)
    sheet = Image.new("RGB", (per_split * w, len(splits) * (h + 14)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for row, split in enumerate(splits):
        n = ds.num_frames(split)
        for col, i in enumerate(sorted(set(np.linspace(0, n - 1, min(per_split, n)).round().astype(int)))):
            f = ds.frame(split, int(i))
            tile = f.image * (0.3 + 0.7 * f.mask[..., None])
            x0, y0 = col * w, row * (h + 14)
            sheet.paste(Image.fromarray((tile * 255).round().astype(np.uint8)), (x0, y0 + 14))
            uv = f.camera.project(posed_vertices(body, f))
            keep = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            for u, v in uv[keep][:: max(1, int(keep.sum()) // 4000)]:
                draw.point((x0 + float(u), y0 + 14 + float(v)), fill=(255, 40, 40))
            draw.text((x0 + 2, y0 + 1), f"{split} #{f.index}", fill=(0, 0, 0))
    return np.asarray(sheet)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from rmavatar.data import load_dataset
    from rmavatar.data.dataset import detect_kind, parse_spec
    from rmavatar.utils import atomic_path

    kind, path, _ = parse_spec(args.data)
    kind = kind or (detect_kind(path) if path.is_dir() else None)
    options = {"body": args.body} if args.body and kind == "zju" else {}
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
    else:
        _print(summary)
    if args.json and args.json != "-":
        with atomic_path(args.json) as tmp:
            tmp.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"summary written to {args.json}")
    if args.overlay:
        from PIL import Image

        from rmavatar.body import load_body_model

        spec = args.body or ds.body or "anny"
        body = load_body_model(spec, gender=ds.gender)
        small = load_dataset(args.data, size=args.size or 256, cache_mb=64, **options)
        sheet = overlay_sheet(small, body, per_split=max(1, args.frames))
        with atomic_path(args.overlay) as tmp:
            Image.fromarray(sheet).save(tmp)
        if args.json != "-":
            print(f"overlay ({spec}) written to {args.overlay}")
    return 0
