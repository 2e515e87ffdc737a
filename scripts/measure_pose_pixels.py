"""How far refined training poses are from the truth in the image, on a synthetic subject (docs/train.md).

    PYTHONPATH=src python scripts/measure_pose_pixels.py DATA RUN [RUN ...] [--size 128]

DATA: a subject made by ``rmavatar synth`` (its true poses in smpl_true.npz); RUN: runs trained on it
with ``poses.refine``. For the training frames, prints the mean distance in pixels (at ``--size``)
between the projected vertices of the body posed with a set of poses and of the body posed with the true
poses, averaged over the vertices (seen or not) and the frames: for the dataset's poses, the same
smoothed as a run starts from (+-``poses.smooth`` frames), and each run's first-pass and final refined poses.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from rmavatar.avatar.trained import load_trained
from rmavatar.body import PoseSequence, smooth_poses
from rmavatar.data import load_dataset
from rmavatar.data.synth import true_poses
from rmavatar.train.pose_refine import PoseConfig
from rmavatar.train.poses import read_poses


def pixel_error(body, betas, poses: PoseSequence, truth: PoseSequence, cameras) -> float:
    """Mean over frames and vertices of |project(v) - project(v_true)| in pixels (``Camera.project``)."""
    def vertices(p):
        with torch.no_grad():
            return body(betas, p.global_orient.float(), p.body_pose.float(), p.transl.float(),
                        hand_pose=p.hand_pose).vertices.double().numpy()

    ours, true = vertices(poses), vertices(truth)
    return float(np.mean([np.linalg.norm(cam.project(ours[i]) - cam.project(true[i]), axis=-1).mean()
                          for i, cam in enumerate(cameras)]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--size", type=int, default=128, help="image side the pixels are counted at")
    args = ap.parse_args()
    torch.set_num_threads(1)
    dataset = load_dataset(args.data, size=args.size)
    params = dataset.params("train")
    truth = true_poses(dataset, "train")
    if truth is None:
        raise SystemExit(f"{args.data} has no true poses (smpl_true.npz): not a synthetic subject")
    cameras = [f.camera for f in dataset.frames("train", len(params["index"]))]
    body = load_trained(args.runs[0], device="cpu").body
    betas = torch.as_tensor(params["betas"]).float() if body.num_betas > 0 else None
    given = PoseSequence.from_params(params)
    radius = PoseConfig().smooth
    rows = [("given", given), (f"given, smoothed +-{radius} frames", smooth_poses(given, params["index"], radius))]
    for run in map(Path, args.runs):
        for name in ("pose_pass/poses.npz", "poses.npz"):
            if (run / name).is_file():
                rows.append((str(run / name), read_poses(run / name, params["index"], "train")))
    for name, poses in rows:
        print(f"{pixel_error(body, betas, poses, truth, cameras):7.3f} px  {name}")


if __name__ == "__main__":
    main()
