"""Time a pose fit's step three ways in one process (docs/evaluate.md, "Test-time pose fitting"):
every Gaussian posed with the face table's torch formulas (the path before), only the drawable Gaussians
(``avatar.model.drawable_copy``) with the torch formulas, and the drawable ones with the face table's
CPU kernels (today's path). The three alternate, so a shared machine slows all of them alike.

    PYTHONPATH=src python scripts/measure_fit_cost.py RUN DATA [--frames 8] [--steps 5] [--threads 1]

RUN: a trained run; DATA: its dataset (its training frames are fitted from their given poses).
Prints milliseconds per frame and fitting step, the median of the repeats after the first.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("data")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=4)
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from rmavatar.render._numba import numba

    numba.set_num_threads(args.threads)
    import rmavatar.avatar.model as model
    import rmavatar.evaluate.fit as fit
    from rmavatar.avatar.geometry import FaceTable, face_table, triangle_frames
    from rmavatar.avatar.trained import load_trained
    from rmavatar.body import PoseSequence
    from rmavatar.data import load_dataset

    run = load_trained(args.run, device=torch.device("cpu"))
    ds = load_dataset(args.data, size=run.size)
    poses = PoseSequence.from_params(ds.params("train")).select(slice(0, args.frames))
    frames = ds.frames("train", args.frames)
    cfg = fit.PoseFitConfig(steps=args.steps, silhouette=0.0, smooth=0)

    def torch_table(vertices, faces):
        return FaceTable.rows(*triangle_frames(vertices, faces))

    variants = {"every Gaussian, torch face table": (lambda avatar: avatar, torch_table),
                "drawable Gaussians, torch face table": (model.drawable_copy, torch_table),
                "drawable Gaussians, face table kernels": (model.drawable_copy, face_table)}
    times = {name: [] for name in variants}
    try:
        for _ in range(args.repeats):
            for name, (copy, table) in variants.items():
                fit.drawable_copy, model.face_table = copy, table
                start = time.perf_counter()
                fit.fit_poses(run.avatar, run.body, poses, None, frames, torch.ones(3), cfg)
                times[name].append((time.perf_counter() - start) / (args.frames * args.steps))
    finally:
        fit.drawable_copy, model.face_table = model.drawable_copy, face_table
    drawable = model.drawable_copy(run.avatar).num_gaussians
    print(json.dumps({"ms_per_frame_step": {k: round(statistics.median(v[1:]) * 1e3, 1) for k, v in times.items()},
                      "gaussians": run.avatar.num_gaussians, "drawable": drawable, "size": run.size,
                      "frames": args.frames, "steps": args.steps, "threads": args.threads}, indent=1))


if __name__ == "__main__":
    main()
