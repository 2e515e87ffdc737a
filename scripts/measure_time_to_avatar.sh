#!/bin/bash
# A 30 s 1920x1080 clip (the synthetic turn played forward, back and forward at 7.5 frames/s, each frame
# shown 4 times at 30 frames/s) -> rmavatar capture (defaults + --still, --fps 5) -> rmavatar train at the
# demo's size and budget (256 px, 1000 iterations) at the default settings (captured poses are estimated,
# so they are refined; TRAIN_ARGS=--no-refine-poses: without), then eval of the test tail (docs/capture.md,
# "From a clip to an avatar"). Times in WORK/times.log.
set -u
W=$(realpath -m "${1:?usage: scripts/measure_time_to_avatar.sh WORK}"); mkdir -p "$W"
cd "$(dirname "$0")/.."
PY=.venv/bin/python
log() { echo "$(date +%H:%M:%S) $*" | tee -a $W/times.log; }
log start; uptime >> $W/times.log
$PY - "$W" <<'PY' > $W/clip.log 2>&1
import sys, time, numpy as np
from pathlib import Path
from rmavatar.bench.capture import synthetic_clip, _truth_image, SYNTH_SIDE, SYNTH_WIDTH
from rmavatar.animate.video import frame_writer
from rmavatar.data import load_dataset
w = Path(sys.argv[1]) / "work"
t = time.time()
video, truth, fov = synthetic_clip(w, progress=False)
print("synth", time.time() - t, "fov", fov)
ds = load_dataset(truth)
idx = sorted(set(ds.splits["train"] + ds.splits["test"]))
order = (idx + idx[::-1][1:] + idx[1:])[:225]
pad = (SYNTH_WIDTH - SYNTH_SIDE) // 2
t = time.time()
with frame_writer(Path(sys.argv[1]) / "clip30.mp4", 30.0, SYNTH_WIDTH, SYNTH_SIDE) as write:
    for i in order:
        frame = np.full((SYNTH_SIDE, SYNTH_WIDTH, 3), 255, np.uint8)
        frame[:, pad:pad + SYNTH_SIDE] = _truth_image(truth, i)
        for _ in range(4):
            write(frame)
print("encode", time.time() - t, "frames", 4 * len(order), "fov", fov)
PY
log clip made; tail -2 $W/clip.log >> $W/times.log
FOV=$(grep -o "fov [0-9.]*" $W/clip.log | tail -1 | cut -d' ' -f2)
T0=$(date +%s)
$PY -m rmavatar capture $W/clip30.mp4 --out $W/data --still --fps 5 --fov $FOV --quiet > $W/capture.log 2>&1
log "capture rc=$? in $(( $(date +%s) - T0 )) s"; uptime >> $W/times.log
T1=$(date +%s)
$PY -m rmavatar train $W/data --out $W/run --size 256 --iters 1000 ${TRAIN_ARGS:-} > $W/train.log 2>&1
log "train rc=$? in $(( $(date +%s) - T1 )) s"; uptime >> $W/times.log
T2=$(date +%s)
$PY -m rmavatar eval $W/run --split test --json $W/eval_test.json --quiet > $W/eval.log 2>&1
log "eval rc=$? in $(( $(date +%s) - T2 )) s; total capture+train $(( T2 - T0 )) s"
