"""Time a pose fit's step three ways in one process (docs/evaluate.md, "Test-time pose fitting"):
every Gaussian posed with the face table's torch formulas (the path before), only the drawable Gaussians
(``avatar.model.drawable_copy``) with the torch formulas, and the drawable ones with the face table's
CPU kernels (today's path). The three alternate, so a shared machine slows all of them alike.

    PYTHONPATH=src python scripts/measure_fit_cost.py RUN DATA [--frames 8] [--steps 5] [--threads 1] [--stages]

RUN: a trained run; DATA: its dataset (its training frames are fitted from their given poses).
Prints milliseconds per frame and fitting step, the median of the repeats after the first. ``--stages``:
also where today's path spends them, its numba kernels timed one by one (compositing forward and
backward, projection, binning, the per-Gaussian sums, the face table) over the repeats after the first;
the rest is torch operations and Python.
"""

from __future__ import annotations

import argparse
import contextlib
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
    parser.add_argument("--stages", action="store_true", help="time today's path's kernels one by one")
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
    today = list(variants)[-1]
    stages = _StageClock() if args.stages else None
    try:
        for repeat in range(args.repeats):
            for name, (copy, table) in variants.items():
                fit.drawable_copy, model.face_table = copy, table
                timing = stages is not None and name == today and repeat > 0
                with stages if timing else contextlib.nullcontext():
                    start = time.perf_counter()
                    fit.fit_poses(run.avatar, run.body, poses, None, frames, torch.ones(3), cfg)
                    times[name].append((time.perf_counter() - start) / (args.frames * args.steps))
    finally:
        fit.drawable_copy, model.face_table = model.drawable_copy, face_table
    drawable = model.drawable_copy(run.avatar).num_gaussians
    report = {"ms_per_frame_step": {k: round(statistics.median(v[1:]) * 1e3, 1) for k, v in times.items()},
              "gaussians": run.avatar.num_gaussians, "drawable": drawable, "size": run.size,
              "frames": args.frames, "steps": args.steps, "threads": args.threads}
    if stages is not None:
        frame_steps = (args.repeats - 1) * args.frames * args.steps
        report["stages_ms_per_frame_step"] = {k: round(v / frame_steps * 1e3, 1) for k, v in stages.totals().items()}
    print(json.dumps(report, indent=1))


class _StageClock:
    """Times the numba kernels of a pose fit (seconds per kernel, summed) inside ``with``; the modules' own
    functions are put back on leaving it."""

    def __init__(self):
        import rmavatar.avatar.face_kernels as face_kernels
        import rmavatar.render.kernels as kernels
        import rmavatar.render.kernels_project as kernels_project

        names = {kernels: ("composite_forward", "composite_backward", "bin_tiles", "sum_per_gaussian"),
                 kernels_project: ("project_forward", "project_backward"),
                 face_kernels: ("face_table_forward", "face_table_backward")}
        self.kernels = [(module, name, getattr(module, name)) for module, ns in names.items() for name in ns]
        self.seconds = {name: 0.0 for _, name, _ in self.kernels}

    def _timed(self, name, kernel):
        def call(*args):
            start = time.perf_counter()
            out = kernel(*args)
            self.seconds[name] += time.perf_counter() - start
            return out
        return call

    def __enter__(self) -> "_StageClock":
        for module, name, kernel in self.kernels:
            setattr(module, name, self._timed(name, kernel))
        return self

    def __exit__(self, *exc) -> bool:
        for module, name, kernel in self.kernels:
            setattr(module, name, kernel)
        return False

    def totals(self) -> dict:
        return dict(sorted(self.seconds.items(), key=lambda kv: -kv[1]))


if __name__ == "__main__":
    main()
