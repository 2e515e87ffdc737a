"""The demo's training at one rectifier precision, then its scores (docs/model.md, "Measured choices").

    PYTHONPATH=src python scripts/measure_rectifier_precision.py DATA OUT SEED float32|bfloat16|auto [THREADS]

Trains the demo's config (local rectifier, 256 px, 1,000 iterations, at most 40,000 Gaussians, training
seed SEED) on DATA with ``model.rectifier_precision`` set, into OUT/run, and scores all test and
novel_pose frames; writes OUT/result.json (the training's wall time beside the scores) and prints it.
Two runs side by side on 2 cores: give each THREADS 1 (docs/train.md).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from rmavatar.bench.quality import variant_config
from rmavatar.evaluate.run import evaluate_run
from rmavatar.train import train


def main(argv: list[str]) -> None:
    if len(argv) not in (4, 5):
        sys.exit(__doc__)
    data, out, seed, precision = argv[0], Path(argv[1]), int(argv[2]), argv[3]
    threads = int(argv[4]) if len(argv) == 5 else 0
    cfg = variant_config("local_rectifier", data, 256, 1000, seed, 40_000, threads, "cpu")
    cfg.model.rectifier_precision = precision
    started = time.perf_counter()
    train(cfg, out / "run", progress=False)
    result = {"precision": precision, "seed": seed, "train_seconds": time.perf_counter() - started,
              "load_average": os.getloadavg()}
    for split in ("test", "novel_pose"):
        result[split] = evaluate_run(out / "run", split=split, progress=False)["mean"]
    (out / "result.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
