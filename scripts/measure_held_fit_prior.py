"""Where repeated held pose fits take the training poses, by what their prior pulls toward (docs/train.md,
"The defaults of version 9").

    PYTHONPATH=src python scripts/measure_held_fit_prior.py RUN DATA [--frames 30] [--rounds 5]
        [--prior 0.1] [--anchor neighbours|start] [--steps 20] [--lr-scale 1]
        [--smooth 2] [--mask 0] [--from-truth]

RUN: a two-pass run trained with ``poses.refine`` on DATA, a subject made by ``rmavatar synth`` (its true
poses in smpl_true.npz). Starting from RUN's first-pass poses averaged over +-``poses.smooth`` frames (where
its second pass starts), fits the first ``--frames`` training poses ``--rounds`` times in a row with RUN's
final avatar held still, each round as a held fit of today's defaults (20 steps, learning rates 0.005 and
0.000125, full size, no mask) with the given prior, and prints after each round how far the poses are from
the true ones: the mean distance in pixels between the projected vertices (at 128 px,
``measure_pose_pixels.pixel_error``) and the mean joint angle. ``--steps``, ``--smooth`` and ``--mask`` set
``poses.held_fit_steps``, ``poses.smooth`` (the anchor's +-frames) and ``poses.fit_mask``; ``--lr-scale``
multiplies both held-fit learning rates;
``--from-truth`` starts from the true poses instead: where the avatar's own images pull them.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from measure_pose_pixels import pixel_error
from rmavatar.avatar.trained import load_trained
from rmavatar.body import pose_error, smooth_poses
from rmavatar.data import load_dataset
from rmavatar.data.synth import true_poses
from rmavatar.evaluate.fit import fit_poses
from rmavatar.train.pose_refine import HELD_FIT_ANCHORS, PoseConfig
from rmavatar.train.poses import read_poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("data")
    ap.add_argument("--frames", type=int, default=30, help="the first this many training frames")
    ap.add_argument("--rounds", type=int, default=5, help="held fits in a row")
    ap.add_argument("--prior", type=float, default=0.1, help="the fits' prior weight (poses.held_fit_prior)")
    ap.add_argument("--anchor", choices=HELD_FIT_ANCHORS, default="neighbours",
                    help="what the prior pulls toward (poses.held_fit_anchor)")
    ap.add_argument("--steps", type=int, default=20, help="Adam steps per frame (poses.held_fit_steps)")
    ap.add_argument("--lr-scale", type=float, default=1.0, help="factor on both held-fit learning rates")
    ap.add_argument("--smooth", type=int, default=2, help="the anchor's average over +-this many frames (poses.smooth)")
    ap.add_argument("--mask", type=float, default=0.0, help="weight of the mask term (poses.fit_mask)")
    ap.add_argument("--from-truth", action="store_true", help="start from the true poses")
    args = ap.parse_args()
    torch.set_num_threads(1)
    run, n = Path(args.run), args.frames
    dataset = load_dataset(args.data, size=128)
    params = dataset.params("train")
    frame_ids = params["index"][:n]
    truth = true_poses(dataset, "train")
    if truth is None:
        raise SystemExit(f"{args.data} has no true poses (smpl_true.npz): not a synthetic subject")
    truth = truth.select(slice(0, n))
    frames = dataset.frames("train", n)
    cameras = [f.camera for f in frames]
    trained = load_trained(run, device="cpu")
    betas = torch.as_tensor(params["betas"][:n]).float() if trained.body.num_betas > 0 else None
    defaults = PoseConfig()
    settings = PoseConfig(held_fit_prior=args.prior, held_fit_anchor=args.anchor, held_fit_steps=args.steps,
                          smooth=args.smooth, fit_mask=args.mask,
                          held_fit_lr_rotation=args.lr_scale * defaults.held_fit_lr_rotation,
                          held_fit_lr_translation=args.lr_scale * defaults.held_fit_lr_translation).validate()
    if args.from_truth:
        poses = truth
    else:
        poses = read_poses(run / "pose_pass" / "poses.npz", params["index"], "train").select(slice(0, n))
        poses = smooth_poses(poses, frame_ids, settings.smooth)
    cfg = settings.fit_config(held=True)

    def report(name):
        px = pixel_error(trained.body, betas, poses, truth, cameras)
        print(f"{name}: {px:.3f} px, {pose_error(poses, truth)['joint_angle_deg']:.3f} deg", flush=True)

    report("start")
    started = time.perf_counter()
    for r in range(args.rounds):
        anchor = settings.held_anchor(poses, frame_ids)
        poses = fit_poses(trained.avatar, trained.body, poses, betas, frames, torch.ones(3), cfg, anchor=anchor)
        report(f"after fit {r + 1}")
    print(f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
