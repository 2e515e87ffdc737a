"""One batch job, as it runs in a worker process: train (resuming from the last checkpoint) and evaluate.

Everything the job writes lives in its folder ``ROOT/NAME/``::

    run/                   the training run (rmavatar train's layout: checkpoints/last.pt, previews/, ...)
    job.log                the job's output, every attempt appended, each under a header line
    progress.json          state (training / evaluating / done / failed), iteration, pid, host, train time
    eval_SPLIT.json        rmavatar eval's result for each listed split
    result.json            the job's outcome: status, metrics per split, iterations, Gaussians, times

The function never raises for a problem of the job itself: a bad input (UserError) or any other error
becomes a "failed" result with its message (the traceback goes to job.log). Only the death of the
process (a kill, the OOM killer, a lost node) escapes it, and the driver then retries the job, which
resumes from the checkpoint.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
import traceback
from pathlib import Path
from typing import Any

from rmavatar.utils import UserError, atomic_path

ROOT_MARKER = "rmavatar-batch.json"
PROGRESS_EVERY_S = 1.0  # at most one progress.json write per second (and one per checkpoint)
LOG_EVERY_S = 60.0  # a progress line in job.log at least this often


def write_json(path: Path, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")


def read_json(path: Path) -> dict | None:
    """The JSON object in ``path``, or None when it is missing or unreadable (e.g. from an old crash)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def check_root_visible(root: Path, session: str) -> None:
    """UserError unless this process sees the batch root the driver prepared (the storage contract)."""
    marker = read_json(root / ROOT_MARKER)
    if marker is None or marker.get("session") != session:
        raise UserError(
            f"the batch folder {root} is not visible on node {socket.gethostname()} (its "
            f"{ROOT_MARKER} is missing or from another batch): on a multi-node cluster ROOT must be on a "
            "filesystem every node mounts at the same path (NFS, a cluster filesystem); nothing was written "
            "on this node")


def run_job(job: dict, root: str, session: str, attempt: int, threads: int, device: str) -> dict:
    """Train and evaluate ``job`` (``Job.to_dict()``) in ``root/NAME``; returns the job's result dict."""
    root = Path(root)
    name = job["name"]
    base = {"job": name, "subject": job["subject"], "variant": job["variant"], "data": job["data"],
            "fingerprint": job["fingerprint"], "attempts": attempt, "host": socket.gethostname()}
    try:
        check_root_visible(root, session)
    except UserError as exc:
        return {**base, "status": "failed", "error": str(exc)}
    job_dir = root / name
    job_dir.mkdir(exist_ok=True)
    with open(job_dir / "job.log", "a", buffering=1) as log, \
            contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        print(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} attempt {attempt} of job {name} on "
              f"{socket.gethostname()}, pid {os.getpid()}, {threads} thread(s), device {device}", flush=True)
        job_run = _JobRun(job, job_dir, session, attempt, threads, device, base)
        try:
            result = job_run.run()
        except UserError as exc:
            result = {**base, "status": "failed", "error": str(exc)}
        except Exception as exc:  # noqa: BLE001 - a job's bug must not stop the batch; the log has it all
            traceback.print_exc()
            result = {**base, "status": "failed", "error": f"{type(exc).__name__}: {exc}".strip()}
        if result["status"] in ("ok", "failed"):
            write_json(job_dir / "result.json", {"format": "rmavatar-batch-job", **result})
        job_run.write_progress(result["status"] if result["status"] != "ok" else "done", force=True)
        print(f"=== {result['status']}" + (f": {result['error']}" if result.get("error") else ""), flush=True)
    return result


class _JobRun:
    def __init__(self, job: dict, job_dir: Path, session: str, attempt: int, threads: int, device: str,
                 base: dict):
        self.job = job
        self.job_dir = job_dir
        self.run_dir = job_dir / "run"
        self.session = session
        self.attempt = attempt
        self.threads = threads
        self.device = device
        self.base = base
        self.iteration = 0
        self.total = int(job["config"]["optim"]["iters"])
        self.state = "starting"
        self.seconds_before = 0.0  # training time of earlier attempts (from progress.json)
        self.prior_time_unknown = False
        self.train_started: float | None = None
        self.train_seconds = 0.0
        self._last_write = 0.0
        self._last_log = 0.0

    # --- progress ---------------------------------------------------------------------------------
    def write_progress(self, state: str | None = None, force: bool = False) -> None:
        if state is not None:
            self.state = state
        now = time.monotonic()
        if not force and now - self._last_write < PROGRESS_EVERY_S:
            return
        self._last_write = now
        if self.train_started is not None:
            self.train_seconds = self.seconds_before + (time.perf_counter() - self.train_started)
        with contextlib.suppress(OSError):  # progress is a convenience: never fail a job over it
            write_json(self.job_dir / "progress.json", {
                "session": self.session, "attempt": self.attempt, "state": self.state, "host": self.base["host"],
                "pid": os.getpid(), "iteration": self.iteration, "total": self.total,
                "train_seconds": round(self.train_seconds, 1), "time": time.time()})

    def _on_iteration(self, iteration: int, total: int) -> None:
        self.iteration, self.total = iteration, total
        every = int(self.job["config"]["log"]["checkpoint_every"])
        checkpointed = iteration % every == 0 or iteration == total
        self.write_progress(force=checkpointed)
        now = time.monotonic()
        if checkpointed or now - self._last_log >= LOG_EVERY_S:
            self._last_log = now
            print(f"iteration {iteration}/{total}, {self.train_seconds:.0f} s of training", flush=True)

    # --- the job ----------------------------------------------------------------------------------
    def run(self) -> dict:
        from rmavatar.avatar.run import RunFolder
        from rmavatar.data import load_dataset
        from rmavatar.train import train
        from rmavatar.train.config import TrainConfig, from_dict
        from rmavatar.utils.device import set_threads

        set_threads(self.threads)
        cfg = from_dict(TrainConfig, self.job["config"], where=f"job {self.job['name']}")
        cfg.threads, cfg.device = self.threads, self.device
        # Every split the job needs must exist before an hour goes into training.
        dataset = load_dataset(cfg.data.path, size=cfg.data.size)
        for split in [cfg.data.split, *self.job["splits"]]:
            if dataset.num_frames(split) < 1:
                raise UserError(f"split '{split}' of {cfg.data.path} has no frames")
        del dataset

        run = RunFolder(self.run_dir)
        ckpt = run.read_checkpoint() if run.has_checkpoint() else None
        resumed_from = None
        if ckpt is not None:
            self._check_same_run(ckpt.config, cfg)
            resumed_from = int(ckpt.iteration)
            self.iteration = resumed_from
            previous = read_json(self.job_dir / "progress.json")
            if previous and previous.get("train_seconds") is not None:
                self.seconds_before = float(previous["train_seconds"])
            else:  # a run folder trained elsewhere: its earlier training time is unknown
                self.prior_time_unknown = True
        del ckpt
        self.train_seconds = self.seconds_before
        if resumed_from is None or resumed_from < self.total:
            self.train_started = time.perf_counter()
            self.write_progress("training", force=True)
            if resumed_from is None:
                result = train(cfg, self.run_dir, progress=False, on_iteration=self._on_iteration)
            else:
                result = train(None, self.run_dir, resume=True, data=cfg.data.path, progress=False,
                               on_iteration=self._on_iteration, overrides={
                                   "optim.iters": cfg.optim.iters, "threads": self.threads, "device": self.device,
                                   "log.checkpoint_every": cfg.log.checkpoint_every})
            self.iteration = result.iteration
            self.write_progress(force=True)
            self.train_started = None
            if result.interrupted:
                return {**self.base, "status": "interrupted", "error": "stopped by a cancel or Ctrl-C; "
                        f"checkpoint at iteration {result.iteration} (re-run the batch to resume)",
                        "iterations": result.iteration}
        else:
            print(f"already trained: checkpoint at iteration {resumed_from} of {self.total}", flush=True)

        final = run.read_checkpoint()
        iteration, gaussians = int(final.iteration), final.num_gaussians
        del final
        self.write_progress("evaluating", force=True)
        eval_started = time.perf_counter()
        splits = {split: self._evaluate(split, cfg, iteration) for split in self.job["splits"]}
        eval_seconds = time.perf_counter() - eval_started
        train_seconds = None if self.prior_time_unknown else round(self.train_seconds, 1)
        return {**self.base, "status": "ok", "error": None, "iterations": iteration,
                "target_iterations": self.total, "resumed_from": resumed_from, "gaussians": gaussians,
                "train_seconds": train_seconds, "eval_seconds": round(eval_seconds, 1), "splits": splits}

    def _check_same_run(self, saved: dict, cfg) -> None:
        """A checkpoint of another config (the job was edited) is not resumed: say which keys differ."""
        from rmavatar.train.config import config_differences

        differ = config_differences(saved, cfg, ignore=("data.path",))
        if differ:
            shown = ", ".join(differ[:6])
            raise UserError(f"{self.run_dir} holds a run trained with another config ({shown}); "
                            "give the job a new name, or remove that folder to train it again")

    def _evaluate(self, split: str, cfg, iteration: int) -> dict:
        """Mean metrics of one split, reusing an earlier evaluation of the same checkpoint."""
        from rmavatar.evaluate import evaluate_run

        path = self.job_dir / f"eval_{split}.json"
        bg = cfg.background if cfg.background in ("white", "black") else "white"
        frames = self.job.get("eval_frames")
        earlier = read_json(path)
        protocol = (earlier or {}).get("protocol", {})
        wanted = protocol.get("frames_in_split") if frames is None else min(frames, protocol.get("frames_in_split", 0))
        if earlier and protocol.get("iteration") == iteration and protocol.get("background") == bg and \
                protocol.get("frames") == wanted:
            result = earlier
            print(f"eval {split}: reusing {path.name} (iteration {iteration})", flush=True)
        else:
            result = evaluate_run(self.run_dir, split=split, bg=bg, device=self.device, max_frames=frames,
                                  progress=False)
            write_json(path, result)
        mean = result["mean"]
        psnr = "inf" if mean["psnr"] is None else f"{mean['psnr']:.2f}"
        print(f"eval {split}: PSNR {psnr} SSIM {mean['ssim']:.4f} LPIPS {mean['lpips']:.4f} "
              f"over {result['protocol']['frames']} frames", flush=True)
        return {"psnr": mean["psnr"], "ssim": mean["ssim"], "lpips": mean["lpips"],
                "frames": result["protocol"]["frames"], "frames_in_split": result["protocol"]["frames_in_split"],
                "resolution": result["protocol"]["resolution"],
                "background": bg}
