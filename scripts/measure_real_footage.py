#!/usr/bin/env python
"""The real-footage protocol (docs/real.md): Pose2Sim's Demo_SinglePerson, one man filmed by four
calibrated, static lab cameras (BSD-3-Clause; its wheel on PyPI holds the videos and the calibration).

Train from cam04 alone; score the avatar on
  train       its own 32 training frames (with the poses training refined)
  val         8 frames held out between them (every 5th), poses fitted to each image (--fit-poses)
  test        the clip's last 10 frames, new poses, fitted likewise
  novel_view  cam03 and cam01 (55 and 107 degrees round from cam04) at the training instants, posed as
              training posed those instants: real ground truth for views the avatar never saw
and measure how solid the avatar is (bench.solid: its T-pose from 8 sides) and how well the captured
body fills the masks (the capture's silhouette IoU).

    pip download --no-deps pose2sim==0.10.49 -d wheels && unzip -q wheels/pose2sim-*.whl 'Pose2Sim/Demo_SinglePerson/*'
    python scripts/measure_real_footage.py Pose2Sim/Demo_SinglePerson WORK --name defaults \\
        [--capture-args "..."] [--train-args "--no-refine-poses"] [--json benchmarks/real_footage.json]

The capture is made once per --capture-args in WORK (reused), each --name trains a run of its own
(reused when it is there); the row (commands, seconds, scores) is added to --json, replacing a row of
the same name.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

CAPTURE = "--fps 30 --val-every 5"  # 100 frames at 60 fps -> 50: 32 train, 8 val, 10 test
TRAIN = "--size 256 --iters 400"  # the budget
SPLITS = {"train": [], "val": ["--fit-poses"], "test": ["--fit-poses"], "novel_view": []}


def rmavatar(*args: str) -> float:
    """Run ``rmavatar ARGS`` (this interpreter's package), stop on failure; returns the seconds it took."""
    start = time.perf_counter()
    cmd = [sys.executable, "-m", "rmavatar", *args]
    print("$ rmavatar " + shlex.join(args), flush=True)
    subprocess.run(cmd, check=True)
    return time.perf_counter() - start


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("demo", type=Path, help="Pose2Sim's Demo_SinglePerson folder (videos/, calibration/)")
    p.add_argument("work", type=Path, help="working folder (captures and runs are kept and reused)")
    p.add_argument("--name", required=True, help="this variant's name (its run folder and JSON row)")
    p.add_argument("--capture-args", default="", help="extra rmavatar capture options")
    p.add_argument("--data", type=Path, default=None, help="a captured dataset to use instead of capturing")
    p.add_argument("--train-args", default="", help="extra rmavatar train options")
    p.add_argument("--json", type=Path, default=None, help="JSON file the row is added to")
    p.add_argument("--threads", type=int, default=0, help="torch threads for training (0: torch's choice)")
    args = p.parse_args()

    videos, calib = args.demo / "videos", args.demo / "calibration" / "Calib.qca.txt"
    capture_args = shlex.split(CAPTURE) + shlex.split(args.capture_args)
    key = hashlib.sha1(" ".join(capture_args).encode()).hexdigest()[:8]
    data = args.data or args.work / f"data_{key}"
    row: dict = {"name": args.name, "commands": {}, "seconds": {}}
    capture_cmd = ["capture", str(videos / "cam04.mp4"), "--out", str(data), "--calibration", str(calib),
                   "--novel-view", str(videos / "cam03.mp4"), "--novel-view", str(videos / "cam01.mp4"),
                   "--quiet", *capture_args]
    row["commands"]["capture"] = "rmavatar " + shlex.join(capture_cmd)
    if not (data / "meta.yaml").is_file():
        row["seconds"]["capture"] = rmavatar(*capture_cmd)
    run = args.work / "runs" / args.name
    train_cmd = ["train", str(data), "--out", str(run), *shlex.split(TRAIN), *shlex.split(args.train_args)]
    if args.threads:
        train_cmd += ["--threads", str(args.threads)]
    row["commands"]["train"] = "rmavatar " + shlex.join(train_cmd)
    if not (run / "checkpoints" / "last.pt").is_file():
        row["seconds"]["train"] = rmavatar(*train_cmd)
    row["scores"] = {}
    for split, extra in SPLITS.items():
        out = args.work / "evals" / args.name / f"{split}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        cmd = ["eval", str(run), "--split", split, "--json", str(out), "--quiet", "--overwrite", *extra]
        row["commands"][f"eval_{split}"] = "rmavatar " + shlex.join(cmd)
        row["seconds"][f"eval_{split}"] = rmavatar(*cmd)
        result = json.loads(out.read_text())
        row["scores"][split] = {k: round(v, 4) for k, v in result["mean"].items()}
        row["scores"][split]["frames"] = result["protocol"]["frames"]
        if split == "novel_view":  # per camera, too
            row["scores"]["novel_view_cameras"] = _per_camera(data, result)
    row.update(_solid_and_capture(run, data))
    print(json.dumps(row, indent=2))
    if args.json is not None:
        rows = json.loads(args.json.read_text()) if args.json.is_file() else []
        rows = [r for r in rows if r.get("name") != args.name] + [row]
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


def _per_camera(data: Path, result: dict) -> dict:
    """The novel_view means per camera (meta.yaml's extra.novel_views names each frame's camera)."""
    import numpy as np
    import yaml

    meta = yaml.safe_load((data / "meta.yaml").read_text())
    cams = meta["extra"]["novel_views"]["cameras"]
    order = meta["splits"]["novel_view"]
    names = [name for name, v in cams.items() for _ in range(v["frames"])]
    by = {}
    for row in result["frames"]:
        by.setdefault(names[order.index(row["index"])], []).append(row)
    return {name: {k: round(float(np.mean([r[k] for r in rows])), 4) for k in ("psnr", "ssim", "lpips")}
            for name, rows in by.items()}


def _solid_and_capture(run: Path, data: Path) -> dict:
    """How solid the avatar is (bench.solid) and the capture's body IoU with its masks (bench.capture)."""
    from rmavatar.avatar import load_trained
    from rmavatar.bench.capture import assess
    from rmavatar.bench.solid import solidity

    solid = solidity(load_trained(run))
    return {"solid": {k: round(v, 4) if isinstance(v, float) else v for k, v in solid.items()},
            "capture": {k: v for k, v in assess(data).items() if "iou" in k}}


if __name__ == "__main__":
    sys.exit(main())
