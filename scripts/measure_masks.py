#!/usr/bin/env python
"""Capture's person masks against the true ones: the synthetic 1080p turn (bench.capture's clip, true
masks known) composited over a real lab's background (the plate a capture of real footage wrote,
DATA/background.png), then MediaPipe's masks (as capture makes them: video mode, the person about 640
pixels tall) refined three ways:

  mediapipe     MediaPipe's mask brought to the frame's size (bilinear)
  guided        snapped to the frame's colour edges by the guided filter (capture before the plate)
  plate         against the clip's own background plate (capture now; rmavatar.capture.matte)

Reported per variant, over every other frame of the turn: IoU at 0.5 with the true mask, the mean
|mask - true| within 4 px of the true edge (edge error), the mask found farther than 12 px outside the
true one (leak, as a share of the person's area), and the PSNR of the training target it makes (the
frame composited over white) against the target the true mask makes. Pictures: frames with their mask
errors (red: mask where there is no person, green: person without mask).

    python scripts/measure_masks.py DATA WORK --json benchmarks/masks_synthetic.json --picture docs/images/masks_synthetic.png

DATA: a capture of real footage (scripts/measure_real_footage.py makes one); WORK: where the synthetic
clip is made once.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

SIDE = 1080  # the synthetic turn's frames
EDGE, FAR = 4, 12  # pixels: the edge band, and how far outside a mask value counts as a leak


def composite_turn(truth: Path, background: np.ndarray):
    """The turn's frames (every other one) over ``background`` [SIDE,SIDE,3] (0..1): (frames uint8
    [T,S,S,3], true masks [T,S,S])."""
    from rmavatar.data import load_dataset

    ds = load_dataset(truth)
    frames, masks = [], []
    for split in ("train", "test"):
        for i in range(0, ds.num_frames(split), 2):
            f = ds.frame(split, i)
            m = f.mask[..., None]
            image = np.asarray(f.image) - (1 - m) + (1 - m) * background  # the render was over white
            frames.append((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
            masks.append(np.asarray(f.mask))
    return np.stack(frames), np.stack(masks)


def mediapipe_masks(frames: np.ndarray) -> np.ndarray:
    """MediaPipe's masks [T,S,S] of the frames, as capture makes them (video mode, at a working size)."""
    from rmavatar.capture.detect import Detector
    from rmavatar.capture.frames import shrink
    from rmavatar.data.io import resample

    work = round(SIDE * 640 / 900)  # the turn's person is about 900 px tall; capture scales it to 640
    out = []
    with Detector() as detect:
        for image in frames:
            det = detect(shrink(image, work, work))
            out.append(np.zeros((SIDE, SIDE), np.float32) if det is None else resample(det.mask, SIDE, SIDE))
    return np.stack(out)


def scores(mask: np.ndarray, true: np.ndarray, image: np.ndarray) -> dict:
    from scipy import ndimage

    a, b = mask > 0.5, true > 0.5
    edge = ndimage.binary_dilation(b, iterations=EDGE) & ~ndimage.binary_erosion(b, iterations=EDGE)
    far = ~ndimage.binary_dilation(b, iterations=FAR)
    colour = image / 255.0
    ours = colour * mask[..., None] + (1 - mask[..., None])
    theirs = colour * true[..., None] + (1 - true[..., None])
    return {"iou": float((a & b).sum() / (a | b).sum()), "edge_error": float(np.abs(mask - true)[edge].mean()),
            "leak": float(mask[far].sum() / b.sum()),
            "target_psnr": float(-10 * np.log10(((ours - theirs) ** 2).mean()))}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, help="a captured dataset of real footage (its background.png)")
    p.add_argument("work", type=Path, help="where the synthetic turn is made (once)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--picture", type=Path, default=None, help="PNG of two frames' mask errors per variant")
    args = p.parse_args()

    from PIL import Image

    from rmavatar.bench.capture import synthetic_clip
    from rmavatar.capture.matte import background_plate, refine_mask

    _, truth, _ = synthetic_clip(args.work, progress=False)
    with Image.open(args.data / "background.png") as im:
        plate = np.asarray(im.convert("RGB"))
    h, w = plate.shape[:2]
    square = plate[h - min(h, w):, :min(h, w)]  # the floor and what stands on it
    background = np.asarray(Image.fromarray(square).resize((SIDE, SIDE), Image.Resampling.BILINEAR)) / 255.0
    frames, true = composite_turn(truth, background)
    raw = mediapipe_masks(frames)
    clip_plate, seen = background_plate(frames, raw)
    variants = {"mediapipe": lambda k: raw[k], "guided": lambda k: refine_mask(frames[k], raw[k]),
                "plate": lambda k: refine_mask(frames[k], raw[k], clip_plate, seen)}
    result = {"frames": len(frames), "size": SIDE, "background": str(args.data / "background.png"),
              "plate_seen": round(float(seen.mean()), 4), "variants": {}}
    shown = {}
    for name, make in variants.items():
        rows = []
        for k in range(len(frames)):
            mask = make(k)
            rows.append(scores(mask, true[k], frames[k]))
            if k in (3, len(frames) // 2):
                shown.setdefault(name, []).append(mask)
        result["variants"][name] = {key: round(float(np.mean([r[key] for r in rows])), 4) for key in rows[0]}
        print(name, result["variants"][name], flush=True)
    if args.picture is not None:
        tiles = []
        for j, k in enumerate((3, len(frames) // 2)):
            row = [frames[k] / 255.0]
            for name in variants:
                e = shown[name][j] - true[k]
                row.append(np.stack([np.clip(e, 0, 1), np.clip(-e, 0, 1), np.zeros_like(e)], -1))
            tiles.append(np.concatenate(row, 1))
        picture = (np.concatenate(tiles, 0) * 255 + 0.5).astype(np.uint8)
        Image.fromarray(picture).resize((picture.shape[1] // 3, picture.shape[0] // 3),
                                        Image.Resampling.BOX).save(args.picture)
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
