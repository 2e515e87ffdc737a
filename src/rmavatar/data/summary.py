"""What a dataset holds, for people to check: a JSON-ready summary and a contact sheet of frames with the
posed body drawn over them (``rmavatar inspect``)."""

from __future__ import annotations

import numpy as np

from rmavatar.body import PoseSequence, posed_vertices


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
        if "hand_pose" in p:  # finger poses: how far they bend, and how often a capture saw each hand
            hands = {"hand_pose_abs_max_deg": round(float(np.degrees(np.abs(p["hand_pose"]).max())), 2)}
            if "hand_found" in p:
                hands["hand_found_share"] = p["hand_found"].mean(0).round(3).tolist()
            out["poses"][s]["hands"] = hands
    return out


def _frame_vertices(body, frame) -> np.ndarray:
    """The body posed by a Frame's parameters -> vertices [V,3] (numpy); betas padded to the body's count."""
    nb = int(getattr(body, "num_betas", 0))
    betas = None
    if nb > 0:
        betas = np.zeros((1, nb), np.float32)
        betas[0, : min(nb, 10)] = frame.betas[:nb]
    hands = None if frame.hand_pose is None else frame.hand_pose[None]
    poses = PoseSequence.from_arrays(frame.global_orient[None], frame.body_pose[None], frame.transl[None], hands)
    return posed_vertices(body, poses, betas)[0].cpu().numpy()


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
            uv = f.camera.project(_frame_vertices(body, f))
            keep = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            for u, v in uv[keep][:: max(1, int(keep.sum()) // 4000)]:
                draw.point((x0 + float(u), y0 + 14 + float(v)), fill=(255, 40, 40))
            draw.text((x0 + 2, y0 + 1), f"{split} #{f.index}", fill=(0, 0, 0))
    return np.asarray(sheet)
