#!/usr/bin/env python
"""The bad-input corpus of issue 43 ("nothing lost"): careless or hostile invocations of every
``rmavatar`` command, each run as the real CLI in a subprocess, classified automatically, counted
per command.

    .venv/bin/python scripts/bad_inputs_corpus.py --json benchmarks/bad_inputs_corpus.json
    .venv/bin/python scripts/bad_inputs_corpus.py --only 'eval:*' --keep      # a few cases, keep the folders
    .venv/bin/python scripts/bad_inputs_corpus.py --json after.json --before before.json   # both tables

About 255 cases: 742 s with ``--jobs 2`` on 2 otherwise idle CPU cores (most of it is Python importing
torch, once per case), about 1,050 s while other work shared the cores.

What a run does
---------------
1. Makes the shared fixtures once, in a scratch folder (``--work``, default a new temporary folder): a
   private cache (``RMAVATAR_CACHE``: the body-model cache of the user's cache is copied in, so the
   written-file registry of the user is never read or changed), a tiny synthetic dataset
   (``rmavatar synth --size 32 --train 4 --test 2 --novel-pose 2 --ss 1``), a run trained on it for two
   iterations, a motion file, an exported PLY, a folder of two frames, a jobs file and a finished
   one-job batch (``rmavatar batch --quiet``, on a local Ray instance).
2. Runs every case (``--jobs`` at a time, default 2) as ``python -m rmavatar ARGS`` with a timeout,
   in a folder of its own (its working directory), after the case has put there the files it needs
   (the user's files, broken copies of the fixtures). The shared fixtures are only ever read: a case
   that aims an output at a fixture copies it first.
3. Classifies each case, prints the counts per command and writes every case with its outcome
   (``--json``).

The classifier (strict; the first rule that matches wins)
---------------------------------------------------------
Every case states what it expects: ``error`` (a refusal), ``warn`` (a warning or a refusal), ``ok``
(the input is fine, e.g. a trailing slash on a folder, and must work) or ``quiet`` (must print
nothing at all). Each ``error``/``warn`` case also lists needles: the offending option or file name
(alternatives allowed, e.g. ``--size`` or ``data.size`` when the command line sets a config key) that
the message itself must contain.

- **lost**: a file or folder that existed before the command ran (the user's files in the case folder,
  the shared fixtures) was changed (SHA-256 differs) or removed. Checked for every case, whatever it
  expects.
- **traceback**: ``Traceback (most recent call last)``, ``Fatal Python error`` or ``Exception ignored
  in`` anywhere in stdout or stderr.
- **timeout**: still running after the case's time limit (its process group is killed).
- for ``error`` and ``warn`` cases:
  - **clear**: exit code 1 or 2, and stderr holds an error line ``rmavatar ...: error: MESSAGE``
    (the command's UserError or argparse's usage error) where MESSAGE (that line and every line after
    it) has at most 3 non-empty lines, contains every needle (case-insensitive) and does not advise
    ``allow_pickle=True`` or ``weights_only=False``.
  - **warned** (``warn`` only): exit code 0 and an output line holding ``warning`` and every needle.
  - **silent**: exit code 0 otherwise: the bad input was accepted without a word.
  - **unclear**: any other failure: another exit code, no ``error:`` line, a message that misses a
    needle or runs longer than 3 lines.
- for ``ok`` cases: **ok** when the exit code is 0, else **refused**.
- for ``quiet`` cases: **ok** when the exit code is 0 and nothing was printed, else **noisy**.

Passing outcomes: clear, warned, ok. Everything else is counted as a failure in the table.
"""

from __future__ import annotations

import argparse
import collections
import concurrent.futures
import fnmatch
import hashlib
import json
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PYTHON = sys.executable
SIZE = 32
PASSING = ("clear", "warned", "ok")
OUTCOMES = ("clear", "warned", "ok", "traceback", "silent", "lost", "timeout", "unclear", "refused", "noisy")
TRACEBACK_MARKS = ("Traceback (most recent call last)", "Fatal Python error", "Exception ignored in")
UNSAFE_ADVICE = ("allow_pickle=True", "weights_only=False")
ERROR_LINE = re.compile(r"^rmavatar(?: [\w.-]+)*: error: ")


# ----------------------------------------------------------------------------------------------- fixtures
@dataclass
class Fx:
    """Paths of the shared, read-only fixtures (strings, as they go on a command line)."""

    root: Path
    data: str = ""
    run: str = ""
    motion: str = ""
    ply: str = ""
    frames: str = ""
    jobs: str = ""
    batch: str = ""
    env: dict = field(default_factory=dict)


def cli(args: list[str], env: dict, cwd: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "rmavatar", *map(str, args)], env=env, cwd=cwd, timeout=timeout,
                          capture_output=True, text=True)


def make_fixtures(work: Path) -> Fx:
    fx = Fx(root=work / "fx")
    fx.root.mkdir(parents=True, exist_ok=True)
    cache = work / "cache"
    user_cache = Path(os.environ.get("RMAVATAR_CACHE") or Path(os.environ.get("XDG_CACHE_HOME")
                                                               or Path.home() / ".cache") / "rmavatar")
    cache.mkdir(parents=True, exist_ok=True)
    for sub in ("anny", "lpips", "numba"):  # what is slow to rebuild; never the user's outputs.json
        if (user_cache / sub).is_dir() and not (cache / sub).exists():
            shutil.copytree(user_cache / sub, cache / sub, symlinks=True)
    fx.env = {**os.environ, "RMAVATAR_CACHE": str(cache), "PYTHONUNBUFFERED": "1",
              "PYTHONPATH": os.pathsep.join(p for p in (str(REPO / "src"), os.environ.get("PYTHONPATH")) if p)}
    fx.env.pop("RAY_AUTH_MODE", None)

    def need(proc: subprocess.CompletedProcess, what: str) -> None:
        if proc.returncode != 0:
            sys.exit(f"fixture {what} failed:\n{proc.stdout}\n{proc.stderr}")

    data, run = fx.root / "data", fx.root / "run"
    if not (data / "meta.yaml").is_file():
        need(cli(["synth", data, "--size", SIZE, "--train", 4, "--test", 2, "--novel-pose", 2, "--ss", 1, "--quiet"],
                 fx.env), "dataset")
    if not (run / "checkpoints" / "last.pt").is_file():
        need(cli(["train", data, "--out", run, "--size", SIZE, "--iters", 2, "--no-refine-poses"], fx.env), "run")
    motion = fx.root / "motion.npz"
    if not motion.is_file():
        np.savez(motion, poses=np.zeros((3, 72), np.float32), trans=np.zeros((3, 3), np.float32),
                 fps=np.float32(30))
    ply = fx.root / "avatar.ply"
    if not ply.is_file():
        need(cli(["export", run, "--ply", ply], fx.env), "ply")
    frames = fx.root / "clip"
    if not frames.is_dir():
        frames.mkdir()
        for i in range(2):
            png(frames / f"frame_{i:04d}.png")
    jobs = fx.root / "jobs.yaml"
    if not jobs.is_file():
        jobs.write_text(f"defaults:\n  overrides: {{iters: 1, size: {SIZE}}}\n  splits: [test]\n"
                        f"jobs:\n  - {{name: a, data: {data}}}\n")
    batch = fx.root / "batch"
    if not (batch / "results.json").is_file():
        need(cli(["batch", jobs, "--out", batch, "--quiet"], fx.env), "batch")
    fx.data, fx.run, fx.motion, fx.ply, fx.frames, fx.jobs, fx.batch = map(
        str, (data, run, motion, ply, frames, jobs, batch))
    return fx


# ----------------------------------------------------------------------------------------------- file makers
def user_file(path: Path, text: str = "the user's own file\n") -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return str(path)


def user_bytes(path: Path, data: bytes) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return str(path)


def user_dir(path: Path, *names: str) -> str:
    path.mkdir(parents=True, exist_ok=True)
    for name in names or ("notes.txt",):
        user_file(path / name)
    return str(path)


def empty_dir(path: Path) -> str:
    path.mkdir(parents=True, exist_ok=True)
    return str(path)


def encoded(path: Path, text: str, encoding: str) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding=encoding)
    return str(path)


def png(path: Path, size: int = SIZE, value: int = 128) -> str:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((size, size, 3), value, np.uint8)).save(path)
    return str(path)


def copy(src: str, dst: Path) -> str:
    if Path(src).is_dir():
        shutil.copytree(src, dst, symlinks=True)
    else:
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, dst)
    return str(dst)


def truncated(src: str, dst: Path, keep: float = 0.5) -> str:
    data = Path(src).read_bytes()
    return user_bytes(dst, data[: max(1, int(len(data) * keep))])


def garbage(dst: Path, n: int = 4096, seed: int = 0) -> str:
    return user_bytes(dst, np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes())


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pickle-ran > pwned",))


def pickled(dst: Path, obj=None) -> str:
    dst.parent.mkdir(parents=True, exist_ok=True)
    with open(dst, "wb") as fh:
        pickle.dump(obj if obj is not None else {"poses": _Evil()}, fh)
    return str(dst)


def npz(dst: Path, **arrays) -> str:
    dst.parent.mkdir(parents=True, exist_ok=True)
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)
    return str(dst)


def motion(dst: Path, n: int = 3, **over) -> str:
    arrays = {"poses": np.zeros((n, 72), np.float32), "trans": np.zeros((n, 3), np.float32), "fps": np.float32(30)}
    arrays.update(over)
    return npz(dst, **{k: v for k, v in arrays.items() if v is not None})


def run_copy(fx: Fx, t: Path, name: str = "myrun") -> Path:
    return Path(copy(fx.run, t / name))


def broken_run(fx: Fx, t: Path, how: str) -> str:
    run = run_copy(fx, t)
    ckpt = run / "checkpoints" / "last.pt"
    if how == "truncated":
        truncated(str(ckpt), ckpt, 0.3)
    elif how == "empty":
        ckpt.write_bytes(b"")
    elif how == "garbage":
        garbage(ckpt)
    elif how == "pickle":
        pickled(ckpt, {"format": _Evil()})
    elif how == "folder":
        ckpt.unlink()
        ckpt.mkdir()
    elif how == "missing":
        ckpt.unlink()
    elif how == "config-utf16":
        text = (run / "config.yaml").read_text()
        (run / "config.yaml").write_text(text, encoding="utf-16")
    elif how == "config-garbage":
        garbage(run / "config.yaml")
    elif how == "marker-garbage":
        user_file(run / "rmavatar-run.json", "{not json")
    return str(run)


def data_copy(fx: Fx, t: Path, name: str = "mydata") -> Path:
    return Path(copy(fx.data, t / name))


def broken_data(fx: Fx, t: Path, how: str, arg: str = "") -> str:
    d = data_copy(fx, t)
    meta = d / "meta.yaml"
    if how == "meta":  # arg: "old=>new"
        old, new = arg.split("=>")
        text = meta.read_text()
        assert old in text, (old, text)
        meta.write_text(text.replace(old, new))
    elif how == "meta-latin1":
        meta.write_text(meta.read_text().replace("name: synth-seed0", "name: café"), encoding="latin-1")
    elif how == "meta-utf16":
        meta.write_text(meta.read_text(), encoding="utf-16")
    elif how == "meta-garbage":
        garbage(meta)
    elif how == "meta-missing":
        meta.unlink()
    elif how == "meta-folder":
        meta.unlink()
        meta.mkdir()
    elif how == "meta-empty":
        meta.write_text("")
    elif how == "png-truncated":
        truncated(str(d / "images" / "00001.png"), d / "images" / "00001.png", 0.4)
    elif how == "png-garbage":
        garbage(d / "images" / "00002.png", 500)
    elif how == "png-missing":
        (d / "images" / "00003.png").unlink()
    elif how == "png-wrong-size":
        png(d / "images" / "00001.png", size=48)
    elif how == "mask-missing":
        (d / "masks" / "00000.png").unlink()
    elif how == "cameras-garbage":
        garbage(d / "cameras.npz")
    elif how == "cameras-truncated":
        truncated(str(d / "cameras.npz"), d / "cameras.npz", 0.5)
    elif how == "cameras-nan":
        cam = dict(np.load(d / "cameras.npz"))
        cam["K"] = cam["K"].copy()
        cam["K"][:, 0, 0] = np.nan
        npz(d / "cameras.npz", **cam)
    elif how == "cameras-shape":
        npz(d / "cameras.npz", K=np.eye(3, dtype=np.float32)[None].repeat(2, 0),
            viewmat=np.eye(4, dtype=np.float32)[None].repeat(2, 0))
    elif how == "smpl-truncated":
        truncated(str(d / "smpl.npz"), d / "smpl.npz", 0.5)
    elif how == "smpl-pickle":
        pickled(d / "smpl.npz")
    elif how == "smpl-nan":
        smpl = dict(np.load(d / "smpl.npz"))
        smpl["body_pose"] = smpl["body_pose"].copy()
        smpl["body_pose"][2, 5] = np.nan
        npz(d / "smpl.npz", **smpl)
    elif how == "smpl-object":
        smpl = dict(np.load(d / "smpl.npz"))
        smpl["transl"] = np.array([{"x": 1}] * 8, dtype=object)
        with open(d / "smpl.npz", "wb") as fh:
            np.savez(fh, **smpl)
    elif how == "smpl-missing-key":
        smpl = dict(np.load(d / "smpl.npz"))
        del smpl["body_pose"]
        npz(d / "smpl.npz", **smpl)
    elif how == "images-folder-missing":
        shutil.rmtree(d / "images")
    else:
        raise ValueError(how)
    return str(d)


def batch_copy(fx: Fx, t: Path) -> Path:
    return Path(copy(fx.batch, t / "mybatch"))


def jobs_file(t: Path, text: str, name: str = "jobs.yaml") -> str:
    return user_file(t / name, text)


def job_line(fx: Fx, name: str = "a", extra: str = "") -> str:
    return (f"defaults:\n  overrides: {{iters: 1, size: {SIZE}}}\n  splits: [test]\n"
            f"jobs:\n  - {{name: {name}, data: {fx.data}{extra}}}\n")


# ----------------------------------------------------------------------------------------------- the cases
Build = Callable[[Path, Fx], list]


@dataclass
class Case:
    id: str
    build: Build
    needles: tuple = ()  # each a string or a tuple of alternatives, all must be in the message
    expect: str = "error"  # error | warn | ok | quiet
    timeout: float = 90.0
    kind: str = ""

    @property
    def command(self) -> str:
        return self.id.split(":")[0]


CASES: list[Case] = []


def case(id: str, build: Build, *needles, expect: str = "error", timeout: float = 90.0, kind: str = "") -> None:
    assert not any(c.id == id for c in CASES), id
    CASES.append(Case(id, build, tuple(needles), expect, timeout, kind))


def T(t: Path, name: str) -> str:
    return str(t / name)


# ---- train
def train(fx: Fx, t: Path, *extra) -> list:
    return ["train", fx.data, "--out", T(t, "run"), "--iters", "1", "--size", str(SIZE), *extra]


for opt, val, needle in [("--iters", "0", ("--iters", "optim.iters")), ("--size", "-32", ("--size", "data.size")),
                         ("--threads", "0", ("--threads", "threads")),
                         ("--iters", "nan", "--iters")]:
    case(f"train:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: train(fx, t) + [o, v], needle, kind="numeric")
case("train:size=100000", lambda t, fx: ["train", fx.data, "--out", T(t, "run"), "--iters", "1", "--size", "100000"],
     ("--size", "data.size"), kind="numeric")
case("train:data-missing", lambda t, fx: ["train", T(t, "nodata"), "--out", T(t, "run")], "nodata", kind="path")
case("train:data-is-a-file", lambda t, fx: ["train", user_file(t / "notes.txt"), "--out", T(t, "run")], "notes.txt",
     kind="path")
case("train:data-empty-folder", lambda t, fx: ["train", empty_dir(t / "emptydir"), "--out", T(t, "run")], "emptydir",
     kind="path")
case("train:config-missing", lambda t, fx: train(fx, t, "--config", T(t, "c.yaml")), "c.yaml", kind="path")
case("train:config-latin1", lambda t, fx: train(fx, t, "--config", encoded(t / "c.yaml", "# réglages\noptim:\n  iters: 1\n",
                                                                             "latin-1")), "c.yaml", kind="encoding")
case("train:config-utf16", lambda t, fx: train(fx, t, "--config", encoded(t / "c.yaml", "optim:\n  iters: 1\n", "utf-16")),
     "c.yaml", kind="encoding")
case("train:config-invalid-yaml", lambda t, fx: train(fx, t, "--config", user_file(t / "c.yaml", "optim: [iters: 1\n")),
     "c.yaml", kind="malformed")
case("train:config-unknown-key", lambda t, fx: train(fx, t, "--config", user_file(t / "c.yaml", "optim:\n  speed: 3\n")),
     "speed", kind="malformed")
case("train:config-iters-inf", lambda t, fx: ["train", fx.data, "--out", T(t, "run"), "--config",
                                              user_file(t / "c.yaml", "optim:\n  iters: .inf\n")], "optim.iters",
     kind="numeric")
case("train:config-lr-nan", lambda t, fx: train(fx, t, "--config", user_file(t / "c.yaml", "optim:\n  lr_position: .nan\n")),
     "lr_position", kind="numeric")
case("train:resume-run-missing", lambda t, fx: ["train", fx.data, "--out", T(t, "norun"), "--resume"], "norun",
     kind="path")
case("train:resume-checkpoint-truncated", lambda t, fx: ["train", fx.data, "--out", broken_run(fx, t, "truncated"),
                                                         "--resume", "--iters", "3"], "last.pt", kind="garbage")
case("train:resume-no-rectifier-changes-the-run", lambda t, fx: ["train", fx.data, "--out", str(run_copy(fx, t)),
                                                                 "--resume", "--iters", "3", "--no-rectifier"],
     ("--no-rectifier", "rectifier"), kind="conflict")
case("train:out-is-a-user-file", lambda t, fx: train(fx, t)[:3] + [user_file(t / "notes.txt"), "--iters", "1"],
     "notes.txt", kind="output")
case("train:out-is-the-dataset", lambda t, fx: ["train", str(d := data_copy(fx, t)), "--out", str(d), "--iters", "1"],
     "mydata", kind="output")
case("train:out-is-an-existing-run", lambda t, fx: ["train", fx.data, "--out", str(run_copy(fx, t)), "--iters", "1"],
     "myrun", kind="output")
case("train:body-smpl-garbage", lambda t, fx: train(fx, t, "--body", f"smpl:{garbage(t / 'SMPL_NEUTRAL.pkl')}"),
     "SMPL_NEUTRAL.pkl", kind="garbage")
case("train:body-anny-preset-unknown", lambda t, fx: train(fx, t, "--body", "anny:giant"), "giant", kind="value")
for how, needle in [("png-truncated", "00001.png"), ("png-wrong-size", "00001.png"), ("cameras-nan", "cameras.npz"),
                    ("smpl-truncated", "smpl.npz"), ("smpl-pickle", "smpl.npz"), ("smpl-object", "smpl.npz"),
                    ("meta-folder", "meta.yaml")]:
    case(f"train:dataset-{how}", lambda t, fx, h=how: ["train", broken_data(fx, t, h), "--out", T(t, "run"),
                                                      "--iters", "1", "--size", str(SIZE)], needle, kind="garbage")
case("train:data-trailing-slash", lambda t, fx: ["train", fx.data + "/", "--out", T(t, "run2") + "/", "--iters", "1",
                                                 "--size", str(SIZE), "--no-refine-poses"], expect="ok", kind="slash",
     timeout=150)

# ---- inspect
for name, meta_edit, needle in [
        ("num_frames-string", "num_frames: 8=>num_frames: eight", "num_frames"),
        ("width-zero", "width: 32=>width: 0", "width"),
        ("split-frame-outside", "train: [0, 1, 2, 3]=>train: [0, 1, 2, 30]", "30"),
        ("split-not-a-list", "train: [0, 1, 2, 3]=>train: 0-3", "train"),
        ("fps-nan", "fps: 7.5=>fps: .nan", "fps"),
        ("format-misspelt", "format: rmavatar-native=>format: rmavatar-nativ", "format"),
        ("body-number", "body: anny:neutral=>body: 7", "body")]:
    case(f"inspect:meta-{name}", lambda t, fx, m=meta_edit: ["inspect", broken_data(fx, t, "meta", m)], "meta.yaml",
         needle, kind="malformed")
case("inspect:meta-utf16", lambda t, fx: ["inspect", broken_data(fx, t, "meta-utf16")], "meta.yaml", kind="encoding")
case("inspect:check-png-wrong-size", lambda t, fx: ["inspect", broken_data(fx, t, "png-wrong-size"), "--check"],
     "00001.png", kind="garbage")
case("inspect:data-missing", lambda t, fx: ["inspect", T(t, "nodata")], "nodata", kind="path")
case("inspect:data-is-a-png", lambda t, fx: ["inspect", png(t / "photo.png")], "photo.png", kind="path")
case("inspect:option-a-native-dataset-does-not-take", lambda t, fx: ["inspect", f"native:{fx.data}?camera=3"], "camera",
     kind="conflict")
case("inspect:size=0", lambda t, fx: ["inspect", fx.data, "--size", "0"], "--size", kind="numeric")
case("inspect:frames=-1", lambda t, fx: ["inspect", fx.data, "--overlay", T(t, "o.png"), "--frames", "-1"], "--frames",
     kind="numeric")
case("inspect:json-is-a-folder", lambda t, fx: ["inspect", fx.data, "--json", user_dir(t / "outdir")], "outdir",
     kind="output")
case("inspect:json-trailing-slash", lambda t, fx: ["inspect", fx.data, "--json", T(t, "s.json") + "/"], "s.json",
     kind="slash")
case("inspect:json-is-the-datasets-meta", lambda t, fx: ["inspect", str(d := data_copy(fx, t)), "--json",
                                                         str(d / "meta.yaml")], "meta.yaml", kind="output")
case("inspect:overlay-not-png", lambda t, fx: ["inspect", fx.data, "--overlay", T(t, "o.jpg")], "o.jpg", kind="output")
case("inspect:frames-without-overlay", lambda t, fx: ["inspect", fx.data, "--frames", "2"], "--frames", expect="warn",
     kind="conflict")
case("inspect:body-without-overlay", lambda t, fx: ["inspect", fx.data, "--body", "anny:male"], "--body", expect="warn",
     kind="conflict")
case("inspect:overwrite-without-output", lambda t, fx: ["inspect", fx.data, "--overwrite"], "--overwrite",
     expect="warn", kind="conflict")
case("inspect:data-trailing-slash", lambda t, fx: ["inspect", fx.data + "/"], expect="ok", kind="slash")


# ---- eval
def ev(fx: Fx, t: Path, *extra, run: str | None = None) -> list:
    return ["eval", run or fx.run, "--json", T(t, "e.json"), "--no-images", "--quiet", *extra]


for opt, val, needle in [("--size", "0", "--size"), ("--frames", "-1", "--frames"), ("--fit-poses", "0", "--fit-poses"),
                         ("--size", "nan", "--size")]:
    case(f"eval:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: ev(fx, t, o, v), needle, kind="numeric")
case("eval:fit-batch=0", lambda t, fx: ev(fx, t, "--fit-poses", "1", "--fit-batch", "0"), "--fit-batch", kind="numeric")
case("eval:fit-batch-without-fit-poses", lambda t, fx: ev(fx, t, "--fit-batch", "4"), "--fit-batch", kind="conflict")
case("eval:images-and-no-images", lambda t, fx: ev(fx, t, "--images", T(t, "im")), "--images", kind="conflict")
case("eval:split-unknown", lambda t, fx: ev(fx, t, "--split", "holdout"), "holdout", kind="value")
case("eval:device-unknown", lambda t, fx: ev(fx, t, "--device", "tpu"), "tpu", kind="value")
case("eval:run-missing", lambda t, fx: ev(fx, t, run=T(t, "norun")), "norun", kind="path")
case("eval:run-is-a-dataset", lambda t, fx: ev(fx, t, run=fx.data), "fx/data", kind="path")
for how in ("truncated", "pickle", "folder"):
    case(f"eval:checkpoint-{how}", lambda t, fx, h=how: ev(fx, t, run=broken_run(fx, t, h)), "last.pt",
         *(("not a checkpoint file",) if how == "folder" else ()), kind="garbage")
# RUN/config.yaml is the user's copy to edit and pass back (--config); eval reads the checkpoint's own config.
case("eval:run-config-garbage", lambda t, fx: ev(fx, t, run=broken_run(fx, t, "config-garbage")), expect="ok",
     kind="garbage", timeout=150)
case("eval:data-missing", lambda t, fx: ev(fx, t, "--data", T(t, "nodata")), "nodata", kind="path")
case("eval:json-trailing-slash", lambda t, fx: ["eval", fx.run, "--json", T(t, "e.json") + "/", "--no-images"], "e.json",
     kind="slash")
case("eval:json-is-the-checkpoint", lambda t, fx: ["eval", str(r := run_copy(fx, t)), "--json",
                                                   str(r / "checkpoints" / "last.pt"), "--no-images"], "last.pt",
     kind="output")
case("eval:images-is-the-run", lambda t, fx: ["eval", str(r := run_copy(fx, t)), "--json", T(t, "e.json"), "--images",
                                              str(r)], "myrun", kind="output")
case("eval:images-is-the-dataset", lambda t, fx: ["eval", fx.run, "--json", T(t, "e.json"), "--images",
                                                  str(data_copy(fx, t))], "mydata", kind="output")
case("eval:default-images-dir-is-a-user-folder", lambda t, fx: (user_dir(t / "e_images", "keep.png"),
                                                                ["eval", fx.run, "--json", T(t, "e.json")])[1],
     "e_images", kind="output")
case("eval:run-trailing-slash", lambda t, fx: ["eval", fx.run + "/", "--json", T(t, "e.json"), "--no-images",
                                               "--frames", "1", "--quiet"], expect="ok", kind="slash", timeout=150)


# ---- animate
def an(fx: Fx, t: Path, *extra, mot: str | None = None, out: str | None = None) -> list:
    return ["animate", fx.run, "--motion", mot or fx.motion, "--out", out or T(t, "a.mp4"), "--size", str(SIZE), *extra]


for opt, val in [("--fps", "0"), ("--fps", "nan"), ("--fps", "inf"), ("--size", "100000"), ("--fov", "180")]:
    case(f"animate:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: an(fx, t, o, v), opt, kind="numeric")
for val in ("5:2", "abc"):
    case(f"animate:frames={val}", lambda t, fx, v=val: an(fx, t, "--frames", v), "--frames", kind="value")
for val in ("purple", "nan,0,0"):
    case(f"animate:bg={val}", lambda t, fx, v=val: an(fx, t, "--bg", v), "--bg", kind="value")
case("animate:device-unknown", lambda t, fx: an(fx, t, "--device", "tpu"), "tpu", kind="value")
case("animate:motion-missing", lambda t, fx: an(fx, t, mot=T(t, "walk.npz")), "walk.npz", kind="path")
case("animate:motion-truncated-npz", lambda t, fx: an(fx, t, mot=truncated(fx.motion, t / "walk.npz")), "walk.npz",
     kind="garbage")
case("animate:motion-pickle-npy", lambda t, fx: an(fx, t, mot=pickled(t / "walk.npy")), "walk.npy", kind="garbage")
case("animate:motion-utf16-text", lambda t, fx: an(fx, t, mot=encoded(t / "walk.npz", "poses: [0, 0]\n", "utf-16")),
     "walk.npz", kind="encoding")
case("animate:motion-poses-wrong-shape", lambda t, fx: an(fx, t, mot=motion(t / "walk.npz", poses=np.zeros((3, 10)))),
     "poses", kind="malformed")
case("animate:motion-poses-nan", lambda t, fx: an(fx, t, mot=motion(t / "walk.npz", poses=np.full((3, 72), np.nan))),
     "walk.npz", kind="numeric")
case("animate:motion-fps-negative", lambda t, fx: an(fx, t, mot=motion(t / "walk.npz", fps=np.float32(-30))),
     "walk.npz", "fps", kind="numeric")
case("animate:motion-trans-wrong-shape", lambda t, fx: an(fx, t, mot=motion(t / "walk.npz", trans=np.zeros((2, 3)))),
     "trans", kind="malformed")
case("animate:out-unknown-suffix", lambda t, fx: an(fx, t, out=T(t, "a.gif")), "a.gif", kind="output")
case("animate:out-existing-folder-without-slash", lambda t, fx: an(fx, t, out=user_dir(t / "frames")), "frames",
     kind="output")
case("animate:out-is-the-run-folder", lambda t, fx: ["animate", str(r := run_copy(fx, t)), "--motion", fx.motion,
                                                     "--out", str(r) + "/", "--size", str(SIZE)], "myrun",
     kind="output")
case("animate:out-mp4-trailing-slash-is-a-user-file", lambda t, fx: an(fx, t, out=user_file(t / "a.mp4") + "/"),
     "a.mp4", kind="slash")
case("animate:checkpoint-truncated", lambda t, fx: ["animate", broken_run(fx, t, "truncated"), "--motion", fx.motion,
                                                    "--out", T(t, "a.mp4"), "--size", str(SIZE)], "last.pt",
     kind="garbage")


# ---- render
def rr(t: Path, *extra) -> list:
    return ["render", "--random", "200", "--out", T(t, "r.png"), "--size", str(SIZE), *extra]


def rrun(fx: Fx, t: Path, *extra, run: str | None = None) -> list:
    return ["render", run or fx.run, "--out", T(t, "r.png"), "--size", str(SIZE), *extra]


for opt, val in [("--random", "-5"), ("--size", "0"), ("--size", "100000")]:
    case(f"render:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: rr(t, o, v), opt, kind="numeric")
for opt, val in [("--fov", "0"), ("--elevation", "90"), ("--elevation", "nan")]:
    case(f"render:run-{opt[2:]}={val}", lambda t, fx, o=opt, v=val: rrun(fx, t, o, v), opt, kind="numeric")
case("render:background-negative", lambda t, fx: rr(t, "--background", "-1", "0", "0"), "--background", kind="numeric")
case("render:ply-missing", lambda t, fx: ["render", "--ply", T(t, "a.ply"), "--out", T(t, "r.png")], "a.ply",
     kind="path")
case("render:ply-truncated", lambda t, fx: ["render", "--ply", truncated(fx.ply, t / "a.ply"), "--out", T(t, "r.png"),
                                            "--size", str(SIZE)], "a.ply", kind="garbage")
case("render:ply-garbage", lambda t, fx: ["render", "--ply", garbage(t / "a.ply"), "--out", T(t, "r.png")], "a.ply",
     kind="garbage")
case("render:ply-utf16-text", lambda t, fx: ["render", "--ply", encoded(t / "a.ply", "ply\nformat ascii 1.0\n", "utf-16"),
                                             "--out", T(t, "r.png")], "a.ply", kind="encoding")
case("render:ply-mesh-without-gaussian-properties",
     lambda t, fx: ["render", "--ply", user_file(t / "mesh.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                                 "property float y\nproperty float z\nend_header\n0 0 0\n"),
                    "--out", T(t, "r.png")], "mesh.ply", kind="garbage")
case("render:turntable-with-random", lambda t, fx: rr(t, "--turntable"), "--turntable", kind="conflict")
case("render:turntable-with-azimuth", lambda t, fx: ["render", fx.run, "--turntable", "--out", T(t, "t.mp4"), "--size",
                                                     str(SIZE), "--azimuth", "10"], "--azimuth", kind="conflict")
case("render:turntable-frames=0", lambda t, fx: ["render", fx.run, "--turntable", "--out", T(t, "t.mp4"), "--frames", "0",
                                                 "--size", str(SIZE)], "--frames", kind="numeric")
case("render:frames-without-turntable", lambda t, fx: rrun(fx, t, "--frames", "10"), "--frames", kind="conflict")
case("render:pose-with-random", lambda t, fx: rr(t, "--pose", "apose"), "--pose", kind="conflict")
case("render:out-jpg", lambda t, fx: ["render", "--random", "200", "--out", T(t, "r.jpg")], "r.jpg", kind="output")
case("render:out-trailing-slash", lambda t, fx: ["render", "--random", "200", "--out", T(t, "r.png") + "/"], "r.png",
     kind="slash")
case("render:backend-gsplat-without-gpu", lambda t, fx: rr(t, "--backend", "gsplat"), "gsplat", kind="value")
case("render:run-checkpoint-garbage", lambda t, fx: rrun(fx, t, run=broken_run(fx, t, "garbage")), "last.pt",
     kind="garbage")
case("render:turntable-out-is-the-run", lambda t, fx: ["render", str(r := run_copy(fx, t)), "--turntable", "--out",
                                                       str(r) + "/", "--size", str(SIZE), "--frames", "2"], "myrun",
     kind="output")

# ---- export
def ex(fx: Fx, t: Path, *extra, run: str | None = None, ply: str | None = None) -> list:
    return ["export", run or fx.run, "--ply", ply or T(t, "a.ply"), *extra]


case("export:ply-wrong-suffix", lambda t, fx: ex(fx, t, ply=T(t, "a.txt")), "a.txt", kind="output")
case("export:ply-trailing-slash", lambda t, fx: ex(fx, t, ply=T(t, "a.ply") + "/"), "a.ply", kind="slash")
case("export:ply-in-missing-folder", lambda t, fx: ex(fx, t, ply=T(t, "no/such/a.ply")), "no/such", kind="output")
case("export:ply-user-ply", lambda t, fx: ex(fx, t, ply=copy(fx.ply, t / "mine.ply")), "mine.ply", kind="output")
case("export:motion-garbage", lambda t, fx: ex(fx, t, "--motion", garbage(t / "walk.npz")), "walk.npz", kind="garbage")
case("export:motion-pickle", lambda t, fx: ex(fx, t, "--motion", pickled(t / "walk.npy")), "walk.npy", kind="garbage")
case("export:frame-outside", lambda t, fx: ex(fx, t, "--motion", fx.motion, "--frame", "999"), "--frame", kind="numeric")
case("export:frame-without-motion", lambda t, fx: ex(fx, t, "--frame", "3"), "--frame", kind="conflict")
case("export:pose-with-motion", lambda t, fx: ex(fx, t, "--motion", fx.motion, "--pose", "apose"), "--pose",
     kind="conflict")
case("export:up-z", lambda t, fx: ex(fx, t, "--up", "z"), "--up", kind="value")
case("export:checkpoint-truncated", lambda t, fx: ex(fx, t, run=broken_run(fx, t, "truncated")), "last.pt",
     kind="garbage")
case("export:checkpoint-pickle", lambda t, fx: ex(fx, t, run=broken_run(fx, t, "pickle")), "last.pt", kind="garbage")
case("export:run-trailing-slash", lambda t, fx: ex(fx, t, run=fx.run + "/"), expect="ok", kind="slash", timeout=120)


# ---- view (a server: a case that is not refused runs until its timeout)
def vw(fx: Fx, *extra, run: str | None = None) -> list:
    return ["view", run or fx.run, "--port", "0", *extra]


case("view:port=-1", lambda t, fx: ["view", fx.run, "--port", "-1"], "--port", kind="numeric", timeout=45)
case("view:port=70000", lambda t, fx: ["view", fx.run, "--port", "70000"], "--port", kind="numeric", timeout=45)
case("view:host-unresolvable", lambda t, fx: vw(fx, "--host", "no-such-host.invalid"), "no-such-host.invalid",
     kind="value", timeout=45)
case("view:motion-garbage", lambda t, fx: vw(fx, "--motion", garbage(t / "walk.npz")), "walk.npz", kind="garbage",
     timeout=45)
case("view:frames-bad", lambda t, fx: vw(fx, "--motion", fx.motion, "--frames", "x"), "--frames", kind="value",
     timeout=45)
case("view:frames-without-motion", lambda t, fx: vw(fx, "--frames", "0:2"), "--frames", kind="conflict", timeout=45)
case("view:pose-with-motion", lambda t, fx: vw(fx, "--motion", fx.motion, "--pose", "apose"), "--pose", kind="conflict",
     timeout=45)
case("view:checkpoint-truncated", lambda t, fx: vw(fx, run=broken_run(fx, t, "truncated")), "last.pt", kind="garbage",
     timeout=45)


# ---- synth
def sy(t: Path, *extra, out: str | None = None) -> list:
    return ["synth", out or T(t, "s"), "--size", "16", "--train", "1", "--test", "1", "--novel-pose", "1", "--ss", "1",
            "--quiet", *extra]


for opt, val in [("--size", "0"), ("--size", "100000"), ("--train", "0"), ("--novel-views", "-1"), ("--turns", "nan"),
                 ("--pose-noise", "-1"), ("--ss", "0"), ("--seed", "-1")]:
    case(f"synth:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: sy(t, o, v), opt, kind="numeric")
case("synth:out-is-a-user-file", lambda t, fx: sy(t, out=user_file(t / "notes.txt")), "notes.txt", kind="output")
case("synth:out-is-a-user-folder", lambda t, fx: sy(t, out=user_dir(t / "mine") + "/"), "mine", kind="output")
case("synth:out-is-the-current-folder", lambda t, fx: (user_file(t / "notes.txt"), sy(t, out="."))[1],
     "current folder", kind="output")
case("synth:out-is-a-run", lambda t, fx: sy(t, out=str(run_copy(fx, t))), "myrun", kind="output")

# ---- capture
def cap(fx: Fx, t: Path, *extra, inp: str | None = None, out: str | None = None) -> list:
    return ["capture", inp or fx.frames, "--out", out or T(t, "cap"), "--quiet", *extra]


for opt, val in [("--fov", "0"), ("--focal", "-5"), ("--fps", "0"), ("--size", "0"), ("--test-fraction", "1.5"),
                 ("--iters", "-1")]:
    case(f"capture:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: cap(fx, t, o, v), opt, kind="numeric", timeout=120)
case("capture:fov-and-focal", lambda t, fx: cap(fx, t, "--fov", "60", "--focal", "500"), "--focal", kind="conflict")
case("capture:body-unknown", lambda t, fx: cap(fx, t, "--body", "robot"), "robot", kind="value", timeout=120)
case("capture:input-missing", lambda t, fx: cap(fx, t, inp=T(t, "me.mp4")), "me.mp4", kind="path")
case("capture:input-folder-without-images", lambda t, fx: cap(fx, t, inp=user_dir(t / "clip", "notes.txt")), "clip",
     kind="path")
case("capture:input-truncated-mp4", lambda t, fx: cap(fx, t, inp=garbage(t / "me.mp4", 2000)), "me.mp4",
     kind="garbage", timeout=120)
case("capture:input-zero-byte-mp4", lambda t, fx: cap(fx, t, inp=user_bytes(t / "me.mp4", b"")), "me.mp4",
     kind="garbage", timeout=120)
case("capture:input-folder-with-broken-png",
     lambda t, fx: cap(fx, t, inp=(png(t / "clip" / "0001.png"), garbage(t / "clip" / "0002.png", 300),
                                   str(t / "clip"))[2]), "0002.png", kind="garbage", timeout=120)
case("capture:out-is-the-input-folder", lambda t, fx: cap(fx, t, inp=(c := copy(fx.frames, t / "clip")), out=c), "clip",
     kind="output")
case("capture:out-is-a-user-folder", lambda t, fx: cap(fx, t, out=user_dir(t / "mine")), "mine", kind="output")

# ---- body
def bd(t: Path, *extra, out: str | None = None) -> list:
    return ["body", "show", "--size", str(SIZE), "--out", out or T(t, "b.png"), *extra]


case("body:size=99999", lambda t, fx: bd(t, "--size", "99999"), "--size", kind="numeric")
case("body:views-unknown", lambda t, fx: bd(t, "--views", "top"), "--views", kind="value")
case("body:frame-outside", lambda t, fx: bd(t, "--motion", fx.motion, "--frame", "-1"), "--frame", kind="numeric")
case("body:frame-without-motion", lambda t, fx: bd(t, "--frame", "5"), "--frame", kind="conflict")
case("body:pose-with-motion", lambda t, fx: bd(t, "--motion", fx.motion, "--pose", "apose"), "--pose", kind="conflict")
case("body:orient-without-motion", lambda t, fx: bd(t, "--orient", "keep"), "--orient", kind="conflict")
case("body:smpl-garbage", lambda t, fx: bd(t, "--body", f"smpl:{garbage(t / 'SMPL_NEUTRAL.pkl')}"), "SMPL_NEUTRAL.pkl",
     kind="garbage")
case("body:smpl-folder-without-models", lambda t, fx: bd(t, "--body", f"smpl:{user_dir(t / 'mysmpl')}"), "mysmpl",
     kind="path")
case("body:anny-preset-unknown", lambda t, fx: bd(t, "--body", "anny:giant"), "giant", kind="value")
case("body:motion-utf16", lambda t, fx: bd(t, "--motion", encoded(t / "walk.npz", "poses", "utf-16")), "walk.npz",
     kind="encoding")
case("body:out-jpg", lambda t, fx: bd(t, out=T(t, "b.jpg")), "b.jpg", kind="output")
case("body:out-trailing-slash", lambda t, fx: bd(t, out=T(t, "b.png") + "/"), "b.png", kind="slash")
case("body:gender-with-anny-preset", lambda t, fx: bd(t, "--body", "anny:female", "--gender", "male"), "--gender",
     kind="conflict")

# ---- demo (every case must stop before the demo's minutes of work)
def dm(t: Path, *extra, out: str | None = None) -> list:
    return ["demo", "--out", out or T(t, "d"), "--quiet", *extra]


for opt, val in [("--size", "16"), ("--iters", "0"), ("--threads", "-1"), ("--size", "99999")]:
    case(f"demo:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: dm(t, o, v), opt, kind="numeric")
case("demo:seed=-1", lambda t, fx: dm(t, "--seed", "-1", "--size", "32", "--iters", "1"), "--seed", kind="numeric",
     timeout=60)
case("demo:out-is-a-user-file", lambda t, fx: dm(t, out=user_file(t / "notes.txt")), "notes.txt", kind="output")
case("demo:out-is-the-current-folder", lambda t, fx: (user_file(t / "notes.txt"), dm(t, out="."))[1],
     "current folder", kind="output")
case("demo:out-is-a-run", lambda t, fx: dm(t, out=str(run_copy(fx, t))), "myrun", kind="output")


# ---- bench
def br(t: Path, *extra) -> list:
    return ["bench", "raster", "--configs", "100x32", "--repeats", "1", "--warmup", "0", "--no-reference", *extra]


for opt, val in [("--configs", "abc"), ("--configs", "0x256"), ("--repeats", "0"), ("--sh-degree", "5"),
                 ("--disc-scale", "nan"), ("--threads", "0")]:
    case(f"bench:raster-{opt[2:]}={val}", lambda t, fx, o=opt, v=val: br(t, o, v), opt, kind="numeric")
case("bench:raster-device-unknown", lambda t, fx: br(t, "--device", "tpu"), "tpu", kind="value")
case("bench:raster-json-trailing-slash", lambda t, fx: br(t, "--json", T(t, "b.json") + "/"), "b.json", kind="slash")
case("bench:raster-overwrite-without-json", lambda t, fx: br(t, "--overwrite"), "--overwrite", expect="warn",
     kind="conflict")
for opt, val in [("--iters", "0"), ("--seeds", "a,b"), ("--variants", "bogus")]:
    case(f"bench:quality-{opt[2:]}={val or 'empty'}",
         lambda t, fx, o=opt, v=val: ["bench", "quality", "--work", T(t, "w"), "--size", "32", "--iters", "1", o, v],
         opt.replace("--seeds", "--seed") if opt == "--seeds" else opt, kind="numeric", timeout=60)
for what, make, name in [("file", user_file, "notes.txt"), ("folder", user_dir, "mine")]:
    case(f"bench:quality-work-is-a-user-{what}",
         lambda t, fx, m=make, n=name: ["bench", "quality", "--work", m(t / n), "--size", "32", "--iters", "1"],
         name, kind="output", timeout=60)
for opt, val in [("--steps", "0"), ("--gaussians", "-5")]:
    case(f"bench:step-{opt[2:]}={val}",
         lambda t, fx, o=opt, v=val: ["bench", "step", "--data", fx.data, "--size", "32", "--steps", "1", "--warmup", "0",
                                      "--count-steps", "0", o, v], opt, kind="numeric", timeout=60)
case("bench:step-data-missing", lambda t, fx: ["bench", "step", "--data", T(t, "nodata"), "--steps", "1"], "nodata",
     kind="path", timeout=60)
for opt, val in [("--render-sizes", "0"), ("--raster-reference", "x")]:
    case(f"bench:speed-{opt[2:]}={val}",
         lambda t, fx, o=opt, v=val: ["bench", "speed", "--data", fx.data, "--size", "32", "--repeats", "1", "--steps", "1",
                                      "--render-sizes", "32", o, v], opt, kind="numeric", timeout=60)
case("bench:speed-run-missing", lambda t, fx: ["bench", "speed", "--run", T(t, "norun"), "--repeats", "1"], "norun",
     kind="path", timeout=60)
for opt, val in [("--gaussians", "0")]:
    case(f"bench:avatar-{opt[2:]}={val}",
         lambda t, fx, o=opt, v=val: ["bench", "avatar", "--gaussians", "100", "--repeats", "1", o, v], opt,
         kind="numeric", timeout=60)
case("bench:avatar-body-unknown", lambda t, fx: ["bench", "avatar", "--gaussians", "100", "--repeats", "1", "--body",
                                                 "mannequin"], "mannequin", kind="value", timeout=60)
for opt, val in [("--size", "0")]:
    case(f"bench:render-{opt[2:]}={val}",
         lambda t, fx, o=opt, v=val: ["bench", "render", fx.run, "--size", "32", "--frames", "1", "--warmup", "0", o, v],
         opt, kind="numeric", timeout=60)
case("bench:render-checkpoint-truncated", lambda t, fx: ["bench", "render", broken_run(fx, t, "truncated"), "--size",
                                                         "32", "--frames", "1"], "last.pt", kind="garbage")
case("bench:render-motion-garbage", lambda t, fx: ["bench", "render", fx.run, "--size", "32", "--frames", "1",
                                                   "--motion", garbage(t / "walk.npz")], "walk.npz", kind="garbage")
case("bench:render-json-user-file", lambda t, fx: ["bench", "render", fx.run, "--size", "32", "--frames", "1",
                                                   "--json", user_file(t / "mine.json", "{}")], "mine.json",
     kind="output")
case("bench:capture-input-missing", lambda t, fx: ["bench", "capture", T(t, "me.mp4")], "me.mp4", kind="path")
for opt, val in [("--frames", "0")]:
    case(f"bench:capture-{opt[2:]}={val}",
         lambda t, fx, o=opt, v=val: ["bench", "capture", fx.frames, "--work", T(t, "w"), "--quiet", o, v], opt,
         kind="numeric", timeout=120)
case("bench:capture-work-holds-a-users-captured-folder",
     lambda t, fx: ["bench", "capture", fx.frames, "--quiet", "--work", str(Path(user_dir(t / "mine" / "captured")).parent)],
     "captured", kind="output", timeout=120)


# ---- batch (every refusal must come before Ray starts)
def bt(t: Path, jobs: str, *extra, out: str | None = None) -> list:
    return ["batch", jobs, "--out", out or T(t, "b"), "--quiet", *extra]


for opt, val in [("--cpus-per-job", "0"), ("--cpus-per-job", "nan"), ("--max-retries", "-1")]:
    case(f"batch:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: bt(t, fx.jobs, o, v), opt, kind="numeric")
case("batch:jobs-is-a-folder", lambda t, fx: bt(t, user_dir(t / "jobsdir")), "jobsdir", kind="path")
case("batch:jobs-utf16", lambda t, fx: bt(t, encoded(t / "jobs.yaml", job_line(fx), "utf-16")), "jobs.yaml",
     kind="encoding")
case("batch:jobs-invalid-yaml", lambda t, fx: bt(t, jobs_file(t, "jobs:\n  - {name: a, data: x\n")), "jobs.yaml",
     kind="malformed")
case("batch:jobs-empty-list", lambda t, fx: bt(t, jobs_file(t, "jobs: []\n")), "jobs.yaml", kind="malformed")
case("batch:jobs-unknown-key", lambda t, fx: bt(t, jobs_file(t, job_line(fx, extra=", colour: red"))), "colour",
     kind="malformed")
case("batch:jobs-name-with-slash", lambda t, fx: bt(t, jobs_file(t, job_line(fx, name="'../x'"))), "../x",
     kind="malformed")
case("batch:jobs-name-reserved", lambda t, fx: bt(t, jobs_file(t, job_line(fx, name="results.json"))), "results.json",
     kind="malformed")
case("batch:jobs-iters-nan", lambda t, fx: bt(t, jobs_file(t, job_line(fx).replace("iters: 1", "iters: .nan"))),
     "iters", kind="numeric")
case("batch:jobs-eval-frames-0", lambda t, fx: bt(t, jobs_file(t, job_line(fx, extra=", eval_frames: 0"))),
     "eval_frames", kind="numeric")
case("batch:jobs-variant-unknown",
     lambda t, fx: bt(t, jobs_file(t, f"matrix:\n  subjects: [{{name: s, data: {fx.data}}}]\n  variants: [bogus]\n")),
     "bogus", kind="malformed")
case("batch:jobs-device-override", lambda t, fx: bt(t, jobs_file(t, job_line(fx, extra=", overrides: {device: cuda}"))),
     "device", kind="malformed")
case("batch:out-is-a-user-folder", lambda t, fx: bt(t, fx.jobs, out=user_dir(t / "mine")), "mine", kind="output")
case("batch:out-is-a-run", lambda t, fx: bt(t, fx.jobs, out=str(run_copy(fx, t))), "myrun", kind="output")
case("batch:out-marker-garbage", lambda t, fx: bt(t, fx.jobs, out=(user_file(t / "b" / "rmavatar-batch.json", "{oops"),
                                                                   T(t, "b"))[1]), "rmavatar-batch.json", kind="garbage")
# An earlier batch's folder in which the user keeps files of their own with names the batch writes.
case("batch:root-user-results-md",
     lambda t, fx: (user_file((b := batch_copy(fx, t)) / "results.md", "# my notes on the results\n"),
                    bt(t, fx.jobs, out=str(b)))[1], "results.md", kind="output", timeout=150)
case("batch:root-user-jobs-yaml",
     lambda t, fx: (user_file((b := batch_copy(fx, t)) / "jobs.yaml", "# my own jobs, with comments\n" + job_line(fx)),
                    bt(t, fx.jobs, out=str(b)))[1], "jobs.yaml", kind="output", timeout=150)
case("batch:root-user-folder-named-like-a-job",
     lambda t, fx: ((b := batch_copy(fx, t)), user_dir(b / "extra", "notes.txt"), copy(fx.run, b / "extra" / "run"),
                    bt(t, jobs_file(t, job_line(fx) + f"  - {{name: extra, data: {fx.data}}}\n"), out=str(b)))[3],
     "extra", kind="output", timeout=150)
case("batch:quiet-prints-nothing", lambda t, fx: bt(t, fx.jobs), expect="quiet", kind="quiet", timeout=240)

# ---- reproduce
def rp(t: Path, *extra) -> list:
    (t / "ps").mkdir(exist_ok=True)
    return ["reproduce", "paper", "--people-snapshot", T(t, "ps"), "--body", "anny", "--out", T(t, "r"), "--quiet",
            *extra]


for opt, val in [("--iters", "0"), ("--eval-frames", "0"), ("--tables", "3")]:
    case(f"reproduce:{opt[2:]}={val}", lambda t, fx, o=opt, v=val: rp(t, o, v), opt, kind="numeric")
case("reproduce:no-datasets", lambda t, fx: ["reproduce", "paper", "--body", "anny", "--out", T(t, "r")],
     ("--people-snapshot", "--zju"), kind="path")
case("reproduce:people-snapshot-missing", lambda t, fx: ["reproduce", "paper", "--people-snapshot", T(t, "nops"),
                                                         "--body", "anny", "--out", T(t, "r")], "nops", kind="path")
case("reproduce:people-snapshot-empty", lambda t, fx: rp(t), "--people-snapshot", kind="path")
case("reproduce:subjects-unknown", lambda t, fx: rp(t, "--subjects", "nobody"), "nobody", kind="value")
case("reproduce:body-smpl-missing", lambda t, fx: ["reproduce", "paper", "--people-snapshot", user_dir(t / "ps"),
                                                   "--body", f"smpl:{t / 'mymodels'}", "--out", T(t, "r")],
     "mymodels", kind="path")
case("reproduce:write-jobs-user-file", lambda t, fx: rp(t, "--write-jobs", user_file(t / "mine.yaml")), "mine.yaml",
     kind="output")
case("reproduce:write-jobs-wrong-suffix", lambda t, fx: rp(t, "--write-jobs", T(t, "jobs.txt")), "jobs.txt",
     kind="output")
case("reproduce:overwrite-without-write-jobs", lambda t, fx: rp(t, "--overwrite"), "--overwrite", kind="conflict")
case("reproduce:address-with-write-jobs", lambda t, fx: rp(t, "--write-jobs", T(t, "j.yaml"), "--address", "auto"),
     "--address", kind="conflict")
case("reproduce:out-is-a-user-folder", lambda t, fx: ["reproduce", "paper", "--people-snapshot",
                                                      str(Path(empty_dir(t / "ps" / "male-3-casual")).parent),
                                                      "--subjects", "male-3-casual", "--tables", "1", "--body", "anny",
                                                      "--out", user_dir(t / "mine")], "mine", kind="output")
case("reproduce:out-holds-a-users-paper-tables",
     lambda t, fx: ["reproduce", "paper", "--people-snapshot", str(Path(empty_dir(t / "ps" / "male-3-casual")).parent),
                    "--subjects", "male-3-casual", "--tables", "1", "--body", "anny", "--quiet", "--out",
                    str(Path(user_file(batch_copy(fx, t) / "paper_tables.md", "# my notes\n")).parent)],
     "paper_tables.md", kind="output", timeout=150)

# ---- top level
case("main:unknown-command", lambda t, fx: ["trian", fx.data], "trian", kind="value")
case("main:unknown-option", lambda t, fx: ["inspect", fx.data, "--colour"], "--colour", kind="value")


# ----------------------------------------------------------------------------------------------- running
def snapshot(root: Path) -> dict[str, str]:
    """Path -> SHA-256 of every file (and 'dir' for every folder) below ``root``."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for d in dirs:
            out[os.path.join(dirpath, d)] = "dir"
        for name in files:
            p = os.path.join(dirpath, name)
            if os.path.islink(p):
                out[p] = "link:" + os.readlink(p)
                continue
            h = hashlib.sha256()
            try:
                with open(p, "rb") as fh:
                    for block in iter(lambda: fh.read(1 << 20), b""):
                        h.update(block)
            except OSError as exc:
                out[p] = f"unreadable:{exc.errno}"
                continue
            out[p] = h.hexdigest()
    return out


def stat_snapshot(root: Path) -> dict[str, tuple]:
    """A cheap fingerprint of the shared fixtures: (inode, size, mtime) per entry."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for name in files + dirs:
            p = os.path.join(dirpath, name)
            st = os.lstat(p)
            out[p] = (st.st_ino, st.st_size, st.st_mtime_ns if name in files else 0)
    return out


def changed(before: dict, after: dict) -> list[str]:
    return sorted(p for p, v in before.items() if after.get(p) != v)


def error_message(stderr: str) -> str | None:
    lines = stderr.splitlines()
    for i, line in enumerate(lines):
        if ERROR_LINE.match(line):
            return "\n".join(lines[i:]).strip()
    return None


def has_needles(text: str, needles: tuple) -> list:
    """The needles missing from ``text`` (case-insensitive; a tuple is a set of alternatives)."""
    low = text.casefold()
    missing = []
    for n in needles:
        alts = n if isinstance(n, tuple) else (n,)
        if not any(a.casefold() in low for a in alts):
            missing.append(n)
    return missing


def classify(c: Case, code: int | None, out: str, err: str, lost: list[str]) -> tuple[str, str]:
    text = out + "\n" + err
    if lost:
        return "lost", f"changed or removed: {', '.join(lost[:5])}"
    if any(m in text for m in TRACEBACK_MARKS):
        return "traceback", next(ln for ln in text.splitlines()[::-1] if ln.strip())[:300]
    if code is None:
        return "timeout", f"still running after {c.timeout:g} s"
    if c.expect == "ok":
        return ("ok", "") if code == 0 else ("refused", (error_message(err) or err.strip()[-300:]))
    if c.expect == "quiet":
        return ("ok", "") if code == 0 and not text.strip() else ("noisy", text.strip()[:500])
    if code == 0:
        if c.expect == "warn":
            for line in text.splitlines():
                if "warning" in line.casefold() and not has_needles(line, c.needles):
                    return "warned", line.strip()
        return "silent", "exit code 0" + (f"; output ends: {text.strip()[-200:]}" if text.strip() else "")
    msg = error_message(err)
    if code not in (1, 2):
        return "unclear", f"exit code {code}: {(msg or err.strip())[-300:]}"
    if msg is None:
        return "unclear", f"no 'rmavatar ...: error:' line; stderr ends: {err.strip()[-300:]}"
    if len([ln for ln in msg.splitlines() if ln.strip()]) > 3:
        return "unclear", f"the message has more than 3 lines: {msg[:400]}"
    if any(u in msg for u in UNSAFE_ADVICE):
        return "unclear", f"the message advises unsafe loading: {msg[:300]}"
    missing = has_needles(msg, c.needles)
    if missing:
        return "unclear", f"the message does not name {missing}: {msg[:400]}"
    return "clear", msg


def run_case(c: Case, fx: Fx, work: Path, fx_stat: dict) -> dict:
    t = work / "cases" / re.sub(r"[^A-Za-z0-9_.=-]+", "_", c.id)
    if t.exists():
        shutil.rmtree(t)
    t.mkdir(parents=True)
    started = time.monotonic()
    try:
        argv = [str(a) for a in c.build(t, fx)]
    except Exception as exc:  # a bug in the case itself: reported, never counted as a pass
        return {"id": c.id, "command": c.command, "kind": c.kind, "expect": c.expect, "outcome": "unclear",
                "detail": f"the case could not be built: {type(exc).__name__}: {exc}", "argv": [], "exit_code": None}
    before = snapshot(t)
    proc = subprocess.Popen([PYTHON, "-m", "rmavatar", *argv], cwd=t, env=fx.env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=c.timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the group of the process this case started (a server, Ray)
        out, err = proc.communicate()
        code = None
    seconds = time.monotonic() - started
    lost = changed(before, snapshot(t))
    fixture_changes = changed(fx_stat, stat_snapshot(fx.root))
    lost += [f"fixture {p}" for p in fixture_changes]
    outcome, detail = classify(c, code, out, err, lost)
    rel = str(t) + os.sep
    return {"id": c.id, "command": c.command, "kind": c.kind, "expect": c.expect, "needles": [list(n) if isinstance(
        n, tuple) else n for n in c.needles], "argv": ["rmavatar", *(a.replace(rel, "") for a in argv)],
        "exit_code": code, "outcome": outcome, "detail": detail.replace(rel, ""), "seconds": round(seconds, 1),
        "stderr_tail": err.strip()[-600:].replace(rel, ""), "fixture_changed": fixture_changes}


def table(results: list[dict]) -> str:
    counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for r in results:
        counts[r["command"]][r["outcome"]] += 1
    cols = ["cases", "clear", "warned", "ok", "traceback", "silent", "lost", "timeout", "unclear", "refused", "noisy"]
    lines = ["| command | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    total = collections.Counter()
    for cmd in sorted(counts):
        n = sum(counts[cmd].values())
        total += counts[cmd]
        lines.append(f"| {cmd} | {n} | " + " | ".join(str(counts[cmd][c]) for c in cols[1:]) + " |")
    lines.append(f"| **all** | **{sum(total.values())}** | " + " | ".join(f"**{total[c]}**" for c in cols[1:]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", help="write every case and its outcome to this JSON file")
    p.add_argument("--before", metavar="JSON", help="an earlier run's --json (e.g. on the tree before a fix): "
                   "its table is printed too and its counts are kept in --json as 'before'")
    p.add_argument("--jobs", type=int, default=2, help="cases run at once (default 2)")
    p.add_argument("--only", nargs="+", metavar="GLOB", help="only the cases whose id matches one of these globs")
    p.add_argument("--work", help="scratch folder (kept; fixtures in it are reused); default: a temporary one, removed")
    p.add_argument("--keep", action="store_true", help="keep the temporary scratch folder")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    args = p.parse_args(argv)
    cases = [c for c in CASES if not args.only or any(fnmatch.fnmatch(c.id, g) for g in args.only)]
    if args.list:
        for c in cases:
            print(f"{c.id:60s} expect {c.expect:6s} {c.kind}")
        print(f"{len(cases)} cases")
        return 0
    if args.jobs < 1:
        p.error(f"--jobs must be >= 1, got {args.jobs}")
    if not cases:
        p.error("no case matches --only")
    work = Path(args.work).resolve() if args.work else Path(tempfile.mkdtemp(prefix="rmavatar-corpus-"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    print(f"fixtures in {work} ...", flush=True)
    fx = make_fixtures(work)
    print(f"fixtures ready in {time.monotonic() - t0:.0f} s; {len(cases)} cases, {args.jobs} at a time", flush=True)
    fx_sha = snapshot(fx.root)
    fx_stat = stat_snapshot(fx.root)
    results: list[dict] = []
    lock = threading.Lock()
    with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
        futures = {pool.submit(run_case, c, fx, work, fx_stat): c for c in cases}
        for fut in concurrent.futures.as_completed(futures):
            r = fut.result()
            with lock:
                results.append(r)
                mark = "  " if r["outcome"] in PASSING else "!!"
                print(f"{mark} [{len(results):3d}/{len(cases)}] {r['outcome']:9s} {r['id']}  ({r.get('seconds', 0)} s)"
                      + ("" if r["outcome"] in PASSING else f"\n      {r['detail'][:300]}"), flush=True)
    order = {c.id: i for i, c in enumerate(CASES)}
    results.sort(key=lambda r: order[r["id"]])
    fixtures_lost = changed(fx_sha, snapshot(fx.root))
    wall = time.monotonic() - t0
    before = json.loads(Path(args.before).read_text()) if args.before else None
    if before is not None:
        print(f"\nbefore ({args.before}):\n" + table(before["results"]))
        print("\nnow:")
    print("\n" + table(results))
    failing = [r for r in results if r["outcome"] not in PASSING]
    print(f"\n{len(results)} cases in {wall:.0f} s: {len(results) - len(failing)} pass, {len(failing)} fail"
          + (f"; FIXTURES CHANGED: {fixtures_lost}" if fixtures_lost else ""))
    if args.json:
        counts = {cmd: dict(collections.Counter(r["outcome"] for r in results if r["command"] == cmd))
                  for cmd in sorted({r["command"] for r in results})}
        doc = {"format": "rmavatar-bad-inputs-corpus", "version": 1, "cases": len(results),
               "pass": len(results) - len(failing), "fail": len(failing), "wall_seconds": round(wall),
               "jobs": args.jobs, "outcomes": dict(collections.Counter(r["outcome"] for r in results)),
               "per_command": counts, "fixtures_changed": fixtures_lost, "results": results}
        if before is not None:
            doc["before"] = {k: before[k] for k in ("cases", "pass", "fail", "outcomes", "per_command")}
            doc["before"]["failing"] = {r["id"]: r["outcome"] for r in before["results"]
                                        if r["outcome"] not in PASSING}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.json}")
    if not args.work and not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    elif args.keep or args.work:
        print(f"scratch kept in {work}")
    return 1 if failing or fixtures_lost else 0


if __name__ == "__main__":
    sys.exit(main())
