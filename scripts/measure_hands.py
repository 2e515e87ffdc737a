"""Hands with and without finger poses: train avatars on a synthetic subject whose fingers move and score
crops around each hand on its test frames.

    python scripts/measure_hands.py DATA OUT --iters 1000 --size 384 [--variants none,mesh,rectifier]

DATA: a dataset from ``rmavatar synth DATA --hand-motion`` (true finger poses stored). Variants:
``none`` trains with relaxed hands (the dataset's finger poses ignored, as rmavatar did before hand
poses), ``mesh`` poses the fingers of the body (and so the Gaussians bound to them) with the finger poses,
``rectifier`` does that and lets the rectifier see the finger joints too (``model.hand_pose``). Each
variant is a run OUT/<variant>; OUT/hands.json gets per variant the test split's PSNR on the whole frame
and on the hand crops (a square around each hand's 21 points from the true poses, padded by half its
size, at least 24 px), and the training time.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

VARIANTS = ("none", "mesh", "rectifier")


def train_variant(data: str, run: Path, variant: str, iters: int, size: int, threads: int) -> float:
    from rmavatar.train import TrainConfig, train

    cfg = TrainConfig()
    cfg.data.path, cfg.data.size, cfg.data.hand_pose = data, size, variant != "none"
    cfg.model.hand_pose = variant == "rectifier"
    cfg.optim.iters, cfg.threads, cfg.log.tensorboard = iters, threads, False
    start = time.perf_counter()
    if (run / "checkpoints" / "last.pt").is_file():
        train(None, run, resume=True, progress=True)
    else:
        train(cfg, run, progress=True)
    return time.perf_counter() - start


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10 * torch.log10(1.0 / ((a - b) ** 2).mean().clamp_min(1e-10)))


@torch.no_grad()
def hand_boxes(body, poses, camera, min_px: int = 24) -> list[tuple[int, int, int, int]]:
    """(x0, y0, x1, y1) of each hand of the one pose ``poses``, seen by ``camera``."""
    out = body(None, poses.global_orient, poses.body_pose, poses.transl, hand_pose=poses.hand_pose)
    points = out.hand_points[0].double().numpy().reshape(2, 21, 3)
    boxes = []
    for hand in points:
        cam = hand @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3]
        uv = (cam @ camera.K.T)[:, :2] / cam[:, 2:3]
        centre = (uv.min(0) + uv.max(0)) / 2
        half = max(min_px / 2, 0.75 * float((uv.max(0) - uv.min(0)).max()))
        x0, y0 = np.floor(centre - half).astype(int)
        x1, y1 = np.ceil(centre + half).astype(int)
        boxes.append((max(x0, 0), max(y0, 0), min(x1, camera.width), min(y1, camera.height)))
    return boxes


def score(run: Path, data: str, split: str = "test") -> dict:
    from rmavatar.avatar import load_trained
    from rmavatar.body import PoseSequence
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import true_poses
    from rmavatar.render.composite import composite

    trained = load_trained(run)
    ds = load_dataset(data, size=trained.size)
    poses = true_poses(ds, split)
    shown = poses
    if not trained.config["data"].get("hand_pose", True):  # trained with relaxed hands: shown so
        shown = PoseSequence(poses.global_orient, poses.body_pose, poses.transl)
    white = torch.ones(3)
    frame_psnr, crop_psnr = [], []
    for i in range(ds.num_frames(split)):
        frame = ds.frame(split, i)
        image = trained.render(trained.pose(shown, i), frame.camera, background=(1.0, 1.0, 1.0)).cpu()
        target = composite(torch.from_numpy(np.array(frame.image)), torch.from_numpy(np.array(frame.mask)), white)
        frame_psnr.append(psnr(image, target))
        for x0, y0, x1, y1 in hand_boxes(trained.body, poses.select(slice(i, i + 1)), frame.camera):
            if x1 - x0 >= 8 and y1 - y0 >= 8:
                crop_psnr.append(psnr(image[y0:y1, x0:x1], target[y0:y1, x0:x1]))
    return {"frames": ds.num_frames(split), "psnr": float(np.mean(frame_psnr)),
            "hand_crops": len(crop_psnr), "hand_psnr": float(np.mean(crop_psnr)),
            "hand_psnr_median": float(np.median(crop_psnr))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data")
    parser.add_argument("out", type=Path)
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    args = parser.parse_args()
    data = str(Path(args.data).resolve())
    args.out.mkdir(parents=True, exist_ok=True)
    result_path = args.out / "hands.json"
    results = json.loads(result_path.read_text()) if result_path.is_file() else {}
    for variant in args.variants.split(","):
        if variant not in VARIANTS:
            raise SystemExit(f"unknown variant {variant!r} (choose from {', '.join(VARIANTS)})")
        seconds = train_variant(data, args.out / variant, variant, args.iters, args.size, args.threads)
        results[variant] = {"iters": args.iters, "size": args.size, "train_s": round(seconds, 1),
                            **score(args.out / variant, data)}
        print(variant, json.dumps(results[variant]), flush=True)
        result_path.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
