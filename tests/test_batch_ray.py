"""rmavatar batch end to end on a real local Ray instance (this machine): three tiny jobs, one of whose
worker processes is SIGKILLed mid-training and must be retried and finish from its checkpoint, one with
a broken dataset that fails with its message; the tables hold the two results and the failure, and a
second run of the same command does no work."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SIZE = 48
SRC = str(Path(__file__).resolve().parents[1] / "src")


def read_json(path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


@pytest.fixture(scope="module")
def data(tmp_path_factory, make_synth_subject):
    out = tmp_path_factory.mktemp("synth") / "subject"
    # Also builds the Anny cache before two workers would race to build it.
    return make_synth_subject(out, size=SIZE, seed=0, train=6, test=2, novel_pose=0, ss=1)


def batch_cmd(jobs, root):
    return [sys.executable, "-m", "rmavatar", "batch", str(jobs), "--out", str(root), "--max-retries", "1"]


def test_batch_survives_a_killed_worker_reports_a_failure_and_reruns_for_free(tmp_path, data):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "meta.yaml").write_text("format: nonsense\n")
    jobs = tmp_path / "jobs.yaml"
    jobs.write_text(f"""
defaults:
  overrides: {{size: {SIZE}, log.checkpoint_every: 10, log.tensorboard: false, log.preview_every: 1000}}
jobs:
  - {{name: good, data: {data}, overrides: {{iters: 10, no_rectifier: true}}}}
  - {{name: killed, data: {data}, overrides: {{iters: 30}}}}
  - {{name: broken, data: broken}}
""")
    root = tmp_path / "root"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (SRC, os.environ.get("PYTHONPATH")) if p)}
    out_path = tmp_path / "batch.out"
    with open(out_path, "w") as out:
        proc = subprocess.Popen(batch_cmd(jobs, root), stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        # Kill the "killed" job's worker once it has written a checkpoint and is still training.
        deadline = time.monotonic() + 400
        while True:
            p = read_json(root / "killed" / "progress.json")
            if p and p["state"] == "training" and 10 <= p["iteration"] < 30:
                break
            assert proc.poll() is None, out_path.read_text()[-3000:]
            assert time.monotonic() < deadline, "the job never reached its first checkpoint"
            time.sleep(0.05)
        assert (root / "killed" / "run" / "checkpoints" / "last.pt").is_file()
        os.kill(p["pid"], signal.SIGKILL)
        killed_at = p["iteration"]
        rc = proc.wait(timeout=400)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=60)
    output = out_path.read_text()
    assert rc == 1, output[-3000:]  # one job failed

    doc = read_json(root / "results.json")
    by_job = {r["job"]: r for r in doc["jobs"]}
    assert [r["job"] for r in doc["rows"]] == ["good", "killed", "broken"]
    good, killed, bad = by_job["good"], by_job["killed"], by_job["broken"]
    assert good["status"] == "ok" and good["iterations"] == 10 and good["attempts"] == 1
    assert good["resumed_from"] is None
    # retried after the kill, resumed from a checkpoint it had written (10 or 20), not from scratch
    assert killed["status"] == "ok" and killed["iterations"] == 30 and killed["attempts"] == 2
    assert killed["resumed_from"] in (10, 20) and killed["resumed_from"] <= killed_at
    assert len(killed["retries"]) == 1 and "WorkerCrashedError" in killed["retries"][0]
    log = (root / "killed" / "job.log").read_text()
    assert log.count("=== ") >= 3 and "attempt 2 of job killed" in log
    assert f"from iteration {killed['resumed_from']} of 30" in log  # the trainer's own resume message
    assert "worker died" in output and "retry 1 of 1" in output
    for r in (good, killed):
        m = r["splits"]["test"]
        assert 5 < m["psnr"] < 60 and 0 < m["ssim"] <= 1 and 0 <= m["lpips"] < 1 and m["frames"] == 2
        assert r["gaussians"] > 1000 and r["train_seconds"] > 0
        ev = read_json(root / r["job"] / "eval_test.json")
        assert ev["protocol"]["iteration"] == r["iterations"] and ev["mean"]["psnr"] == m["psnr"]
    # the bad input fails clearly, once, without a retry
    assert bad["status"] == "failed" and bad["attempts"] == 1 and "retries" not in bad
    assert "meta.yaml" in bad["error"] and "rmavatar-native" in bad["error"]
    assert not (root / "broken" / "run").exists()
    rows = (root / "results.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[3].startswith("broken,broken,default,,failed,")
    md = (root / "results.md").read_text()
    assert "| good | test | ok |" in md and "| killed | test | ok |" in md and "- **broken**:" in md

    # The same command again: nothing runs (no Ray), nothing is rewritten but the tables.
    stamps = {p: p.stat().st_mtime_ns for p in root.glob("*/run/checkpoints/last.pt")}
    logs = {p: p.read_text() for p in root.glob("*/job.log")}
    again = subprocess.run(batch_cmd(jobs, root), capture_output=True, text=True, env=env, timeout=120)
    assert again.returncode == 1, again.stderr[-2000:]
    assert "2 finished earlier, 1 failed earlier" in again.stdout and "0 to run" in again.stdout
    assert "nothing to run" in again.stdout and "Ray instance" not in again.stdout
    assert {p: p.stat().st_mtime_ns for p in root.glob("*/run/checkpoints/last.pt")} == stamps
    assert {p: p.read_text() for p in root.glob("*/job.log")} == logs
    doc2 = read_json(root / "results.json")
    assert doc2["rows"] == doc["rows"] and doc2["ran"] == 0 and doc2["skipped"] == 3
