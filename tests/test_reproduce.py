"""rmavatar reproduce paper end to end on small fixture datasets in the PeopleSnapshot and ZJU-MoCap
layouts (built by tests/helpers.py), a tiny budget and a local Ray instance: it runs the
jobs of Tables 1 and 2 and prints our numbers next to the paper's."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from helpers import add_zju_frame, make_peoplesnapshot, make_zju

from rmavatar.batch.jobs import load_jobs
from rmavatar.data.peoplesnapshot import SUBJECTS, split_frames
from rmavatar.data.zju import SPLITS as ZJU_SPLITS

SIZE = 32
SRC = str(Path(__file__).resolve().parents[1] / "src")


def people_snapshot(root: Path) -> Path:
    """male-3-casual with its standard split; the body 3 m in front of the camera, upright in its image."""
    _, table = SUBJECTS["male-3-casual"]
    frames = {s: split_frames(*r) for s, r in table.items()}
    subject = root / "male-3-casual"
    make_peoplesnapshot(subject, frames, size=(SIZE, SIZE))
    for split, fr in frames.items():
        n = len(fr)
        path = subject / "poses" / f"anim_nerf_{split}.npz"
        z = dict(np.load(path))
        z["transl"] = np.tile(np.array([0.0, 0.3, 3.0], np.float32), (n, 1))
        np.savez(path, **z)
    return root


def zju(root: Path) -> Path:
    """CoreView_377 seen by one camera, the paper's train (1 in 4) and test frames."""
    subject = root / "CoreView_377"
    last_train, last_test = ZJU_SPLITS["377"]
    make_zju(subject, last_test, w=SIZE, h=SIZE, n_cams=1)
    for i in list(range(0, last_train, 4)) + list(range(last_train, last_test)):
        add_zju_frame(subject, i, w=SIZE, h=SIZE, n_cams=1)
    return root


def test_reproduce_paper_on_fixture_datasets(tmp_path):
    ps, zj = people_snapshot(tmp_path / "ps"), zju(tmp_path / "zju")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (SRC, os.environ.get("PYTHONPATH")) if p)}
    cmd = [sys.executable, "-m", "rmavatar", "reproduce", "paper", "--people-snapshot", str(ps), "--zju", str(zj),
           "--body", "anny", "--out", str(tmp_path / "root"), "--tables", "1", "2",
           "--subjects", "male-3-casual", "377", "--iters", "3", "--size", str(SIZE), "--eval-frames", "4"]
    plan = subprocess.run(cmd + ["--write-jobs", str(tmp_path / "plan.yaml")], capture_output=True, text=True,
                          env=env, timeout=120)
    assert plan.returncode == 0, plan.stderr
    jobs = load_jobs(tmp_path / "plan.yaml")
    assert [j.name for j in jobs] == ["male-3-casual-full", "zju-377-full"]
    assert not (tmp_path / "root").exists()

    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = proc.stdout
    assert "### Table 1: PeopleSnapshot, test frames" in out and "### Table 2: ZJU-MoCap, test frames" in out
    assert "Table 4" not in out
    root = tmp_path / "root"
    doc = json.loads((root / "results.json").read_text())
    rows = {r["job"]: r for r in doc["rows"]}
    ps_row, zju_row = rows["male-3-casual-full"], rows["zju-377-full"]
    assert ps_row["frames"] == zju_row["frames"] == 4 and ps_row["iterations"] == 3
    # the standard test splits: 55 frames (male-3-casual 456..675 step 4), 161 (377: frames 457-617)
    assert [j["splits"]["test"]["frames_in_split"] for j in doc["jobs"]] == [55, 161]
    assert f"| male-3-casual | {ps_row['psnr']:.2f} | 34.12 | {ps_row['ssim']:.3f} | 0.985 | " \
           f"{ps_row['lpips']:.3f} | 0.013 |" in out
    assert f"| 377 | {zju_row['psnr']:.2f} | 32.68 | {zju_row['ssim']:.3f} | 0.982 |" in out
    assert "3 iterations (the paper: 50,000), evaluated at 32x32 on a white background" in out
    assert "ONLY THE FIRST FRAMES of each test split" in out
    assert (root / "paper_tables.md").read_text().count("| 34.12 |") == 2  # the subject and its mean of 1


def test_write_jobs_never_replaces_the_users_file(tmp_path, monkeypatch, capsys):
    """--write-jobs goes through the output rule: an existing file rmavatar did not write is kept; a
    jobs file it wrote itself is replaced; options that only matter to a running batch are refused."""
    from rmavatar.commands import main

    monkeypatch.setenv("RMAVATAR_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ps" / "male-3-casual").mkdir(parents=True)
    base = ["reproduce", "paper", "--people-snapshot", "ps", "--body", "anny", "--out", "runs/ps",
            "--tables", "1", "--subjects", "male-3-casual"]
    notes = tmp_path / "notes.yaml"
    notes.write_text("my notes\n")
    assert main([*base, "--write-jobs", "notes.yaml"]) == 2
    assert "refusing to replace" in capsys.readouterr().err
    assert notes.read_text() == "my notes\n"
    # A new file is written, and rmavatar may write it again (it can prove it wrote it).
    assert main([*base, "--write-jobs", "jobs.yaml"]) == 0
    assert main([*base, "--iters", "10", "--write-jobs", "jobs.yaml"]) == 0
    assert len(load_jobs(tmp_path / "jobs.yaml")) == 1
    capsys.readouterr()
    # --overwrite replaces the user's file when asked to.
    assert main([*base, "--write-jobs", "notes.yaml", "--overwrite"]) == 0
    assert len(load_jobs(notes)) == 1
    # Options that have no effect with --write-jobs, and numbers out of range, are refused up front.
    assert main([*base, "--write-jobs", "j2.yaml", "--address", "auto"]) == 2
    assert "--address has no effect with --write-jobs" in capsys.readouterr().err
    assert main([*base, "--cpus-per-job", "nan"]) == 2
    assert "--cpus-per-job" in capsys.readouterr().err
    assert main([*base, "--write-jobs", "j2.yaml", "--size", "0"]) == 2
    assert "--size" in capsys.readouterr().err
    assert main([*base, "--overwrite"]) == 2
    assert "--overwrite only applies to --write-jobs" in capsys.readouterr().err
    assert not (tmp_path / "j2.yaml").exists() and not (tmp_path / "runs").exists()
