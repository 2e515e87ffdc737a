"""The pose-refinement rows of docs/evaluate.md's table, at the demo's size and budget.

    rmavatar synth NOISY --size 256 --seed 0 --pose-noise 3
    PYTHONPATH=src python scripts/measure_pose_refinement.py WORK NOISY [optim.KEY=VALUE ...]

Trains the local-rectifier avatar on NOISY with pose refinement on (256 px, 1,000 iterations, at most
40k Gaussians, seed 0, main's defaults unless a setting is given, e.g. ``poses.first_pass=0.0``) into
WORK/run, then scores it: its own first 30 training frames (with the poses it trained on), all test and
novel_pose frames with the dataset's (noisy) poses, and the same after ``eval --fit-poses`` (100
steps). Writes WORK/results.json (PSNR/SSIM/LPIPS, pose errors, seconds) and the error images under
WORK/img_*; prints the summary.
"""

from __future__ import annotations

import ast
import json
import sys
import time
from pathlib import Path

from rmavatar.bench.quality import variant_config
from rmavatar.evaluate.fit import PoseFitConfig
from rmavatar.evaluate.run import evaluate_run
from rmavatar.train import train
from rmavatar.utils.config import apply_overrides


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        sys.exit(__doc__)
    work, noisy = Path(argv[0]), argv[1]
    run = work / "run"
    cfg = variant_config("local_rectifier", noisy, 256, 1000, 0, 40_000, 0, "cpu")
    cfg.poses.refine = True
    cfg = apply_overrides(cfg, {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in argv[2:])}, "settings")
    out: dict = {"settings": argv[2:], "data": noisy}

    def save() -> None:
        (work / "results.json").write_text(json.dumps(out, indent=1, default=str))

    def keep(result: dict) -> dict:
        return {k: result[k] for k in ("mean", "pose_error") if k in result}

    started = time.perf_counter()
    train(cfg, run, progress=True)
    out["train_seconds"] = time.perf_counter() - started
    out["pose_error"] = json.loads((run / "pose_error.json").read_text())
    save()
    for split in ("train", "test", "novel_pose"):
        out[split] = keep(evaluate_run(run, split=split, max_frames=30 if split == "train" else None,
                                       out_dir=work / f"img_{split}", progress=False))
        save()
    for split in ("test", "novel_pose"):
        started = time.perf_counter()
        out[f"{split}_fit"] = keep(evaluate_run(run, split=split, out_dir=work / f"img_{split}_fit",
                                                progress=False, fit=PoseFitConfig()))
        out[f"{split}_fit_seconds"] = time.perf_counter() - started
        save()
    print(json.dumps({k: v["mean"] if isinstance(v, dict) and "mean" in v else v for k, v in out.items()
                      if k != "pose_error"}, indent=1))
    print("training poses (deg): given", out["pose_error"]["given"]["joint_angle_deg"], "refined",
          out["pose_error"]["refined"]["joint_angle_deg"])


if __name__ == "__main__":
    main(sys.argv[1:])
