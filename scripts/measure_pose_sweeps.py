"""Score one pose-refinement setting on the cheap proxy that chose the default pose sweeps (docs/train.md).

    rmavatar synth TRUE --size 256 --seed 0
    rmavatar synth NOISY --size 256 --seed 0 --pose-noise 3
    PYTHONPATH=src python scripts/measure_pose_sweeps.py WORK NAME NOISY [TRUE] [optim.KEY=VALUE ...]

Trains the local-rectifier avatar on NOISY (or, with TRUE given and ``poses.refine=False``, on
the true poses) at 128 px for 500 iterations with at most 20k Gaussians, seed 0, the settings given
applied (e.g. ``poses.refine=True "poses.fits=(0.2,0.45)"``), then reports: the refined
training poses' error, the PSNR on the avatar's own first 30 training frames (with its refined poses),
and the PSNR on the first 8 test frames of NOISY after ``eval --fit-poses`` (100 steps) from their
noisy poses. Writes WORK/NAME/run and WORK/NAME/result.json; prints the result.

Two runs side by side on a 2-core machine: give each ``threads=1``. With torch's own choice of threads
each, two such runs slowed about fivefold (docs/train.md, "The defaults of version 9").
"""

from __future__ import annotations

import ast
import json
import os
import sys
import time
from pathlib import Path

from rmavatar.bench.quality import variant_config
from rmavatar.evaluate.fit import PoseFitConfig
from rmavatar.evaluate.run import evaluate_run
from rmavatar.train import train
from rmavatar.utils.config import apply_overrides


def main(argv: list[str]) -> None:
    if len(argv) < 3:
        sys.exit(__doc__)
    work, name, noisy = Path(argv[0]), argv[1], argv[2]
    rest = argv[3:]
    data = noisy
    if rest and "=" not in rest[0]:
        data, rest = rest[0], rest[1:]
    run = work / name / "run"
    cfg = variant_config("local_rectifier", data, 128, 500, 0, 20_000, 0, "cpu")
    cfg = apply_overrides(cfg, {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in rest)}, "settings")
    load_before, started = os.getloadavg()[0], time.perf_counter()
    train(cfg, run, progress=False)
    # The training time is the whole training (both passes and every pose fit); the load averages show
    # whether another process shared the CPU meanwhile, which makes times incomparable.
    out = {"settings": rest, "data": data, "train_seconds": time.perf_counter() - started,
           "load_average_before_after": [load_before, os.getloadavg()[0]]}
    errors = run / "pose_error.json"
    if errors.exists():
        e = json.loads(errors.read_text())
        out["training_pose_error_deg"] = (e["refined"] or e["given"])["joint_angle_deg"]
    out["own_training_frames_psnr"] = evaluate_run(run, split="train", max_frames=30, progress=False)["mean"]["psnr"]
    fitted = evaluate_run(run, data=noisy, split="test", max_frames=8, progress=False, fit=PoseFitConfig())
    out["fitted_test_psnr"] = fitted["mean"]["psnr"]
    out["fitted_test_pose_error_deg"] = fitted["pose_error"]["used"]["joint_angle_deg"]
    (work / name / "result.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
