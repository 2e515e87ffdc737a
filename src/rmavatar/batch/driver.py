"""The batch driver: hands jobs to Ray, one task per job, shows progress, retries lost workers, writes
the tables.

- Ray is the scheduler: ``address=None`` starts a private local instance on this machine; an address
  (``auto`` = the cluster ``ray start`` made here, ``HOST:PORT``) joins an existing cluster. A job asks
  for ``cpus_per_job`` CPUs and ``gpus_per_job`` GPUs (default one when the cluster has GPUs).
- Each task runs :func:`rmavatar.batch.worker.run_job` in a fresh worker process (``max_calls=1``: no
  state, threads or heap carried from one job to the next).
- A worker that dies (kill, OOM, lost node) is resubmitted up to ``max_retries`` times and resumes from
  the job's last checkpoint. A job's own error (bad input, a bug) fails that job only, with its message.
- Re-running skips jobs whose result matches their definition (``Job.fingerprint``) and resumes the
  others; jobs that failed with an error stay failed unless ``retry_failed``.
- Nothing of the user's in ROOT is replaced (the output rule of :mod:`rmavatar.utils.outputs`), checked
  before anything starts: the tables and jobs.yaml only when rmavatar wrote them (``RootFiles``), a job's
  folder ROOT/NAME only when it is absent or a job folder of a batch (its ``.rmavatar`` marker, of kind
  ``batch-job``, lists what the job writes there).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import socket
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import yaml

from rmavatar.batch.jobs import Job
from rmavatar.batch.results import RootFiles, markdown, write_results
from rmavatar.batch.worker import ROOT_MARKER, read_json, write_json
from rmavatar.utils import UserError, check_writable_folder

RAY_VERSION = "2.60.0"  # what `pip install 'rmavatar[cluster]'` installs and the tests run
INSTALL_HINT = f"pip install 'rmavatar[cluster]'  (or: pip install ray=={RAY_VERSION})"
LOCK_FILE = ".batch.lock"
JOB_KIND = "batch-job"  # the kind in a job folder's .rmavatar marker (rmavatar.utils.outputs)
CANCEL_WAIT_S = 120.0  # after Ctrl-C, how long running jobs get to write their checkpoint


@dataclass
class BatchOptions:
    address: str | None = None  # None: a local Ray instance; "auto" or HOST:PORT: an existing cluster
    gpus_per_job: float | None = None  # None: 1 when the cluster has GPUs, else 0
    cpus_per_job: float = 1.0  # CPUs Ray reserves per job; its training threads are int(this), at least 1
    max_retries: int = 2  # resubmissions after a worker death
    retry_failed: bool = False  # run again jobs that failed with an error in an earlier invocation
    progress: bool = True  # print the plan, a progress bar and the results table


def import_ray():
    try:
        import ray
    except ImportError:
        raise UserError(f"rmavatar batch runs its jobs on Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


# ----------------------------------------------------------------------------------------------- the root
def check_root(root: Path) -> None:
    """UserError unless ROOT is new, empty (but for our lock file) or an earlier batch's; writes nothing."""
    if root.exists() and not root.is_dir():
        raise UserError(f"--out {root} exists and is not a folder")
    check_writable_folder(root / ROOT_MARKER, f"--out {root}", create=True)
    marker = root / ROOT_MARKER
    if root.is_dir() and any(p.name != LOCK_FILE for p in root.iterdir()) and not marker.is_file():
        raise UserError(f"--out {root} is not empty and holds no rmavatar batch ({ROOT_MARKER} missing): "
                        "refusing to write into it; choose a new or empty folder")
    if marker.is_file():
        data = read_json(marker)
        if data is None or data.get("format") != "rmavatar-batch":
            raise UserError(f"{marker} is not an rmavatar batch marker")


def stamp_root(root: Path) -> str:
    """Give ROOT a new session id, which workers check to prove they see the same folder; returns it."""
    marker = root / ROOT_MARKER
    session = uuid.uuid4().hex
    write_json(marker, {"format": "rmavatar-batch", "version": 1, "session": session,
                        "driver_host": socket.gethostname(), "started": time.time()})
    return session


@contextlib.contextmanager
def root_lock(root: Path):
    """One batch command per ROOT at a time (an advisory lock; NFS may not honour it across hosts)."""
    try:
        import fcntl
    except ImportError:  # not on POSIX
        yield
        return
    root.mkdir(parents=True, exist_ok=True)
    with open(root / LOCK_FILE, "a") as fh:  # never truncated: it may only be locked
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise UserError(f"another rmavatar batch is running on {root}; wait for it or use another --out") from None
        yield


def earlier_result(root: Path, job: Job) -> dict | None:
    """The job's recorded outcome if it still describes this job: "ok" (with its checkpoint) or "failed"."""
    res = read_json(root / job.name / "result.json")
    if not res or res.get("fingerprint") != job.fingerprint():
        return None
    if res.get("status") == "ok" and (root / job.name / "run" / "checkpoints" / "last.pt").is_file():
        return res
    if res.get("status") == "failed":
        return res
    return None


# ----------------------------------------------------------------------------------------------- running
def check_options(options: BatchOptions) -> BatchOptions:
    """UserError for a value no batch can run with (NaN and infinity included); checked before any work."""
    if not (math.isfinite(options.cpus_per_job) and options.cpus_per_job > 0):
        raise UserError(f"--cpus-per-job must be a number > 0, got {options.cpus_per_job}")
    if options.gpus_per_job is not None and not (math.isfinite(options.gpus_per_job) and options.gpus_per_job >= 0):
        raise UserError(f"--gpus-per-job must be a number >= 0, got {options.gpus_per_job}")
    if options.max_retries < 0:
        raise UserError(f"--max-retries must be >= 0, got {options.max_retries}")
    return options


def job_files(job: Job) -> list[str]:
    """What a job writes in its folder ROOT/NAME (see :mod:`rmavatar.batch.worker`); 'run/' is a whole folder."""
    return ["job.log", "progress.json", "result.json", "run/", *(f"eval_{s}.json" for s in job.splits)]


_LOG_HEADER = re.compile(r"^=== \d{4}-\d\d-\d\d \d\d:\d\d:\d\d attempt \d+ of job (\S+) on ")


def _unmarked_job_folder(folder: Path, name: str) -> bool:
    """True for the folder of job ``name`` written before job folders carried a marker: nothing in it but
    what a job writes, and a job.log that starts with the worker's header line for that job."""
    from rmavatar.utils.files import is_temporary

    allowed = {"job.log", "progress.json", "result.json", "run"}
    for entry in folder.iterdir():
        if not (entry.name in allowed or re.fullmatch(r"eval_[^/]+\.json", entry.name) or is_temporary(entry.name)):
            return False
    try:
        with open(folder / "job.log", errors="replace") as fh:
            m = _LOG_HEADER.match(fh.readline())
    except OSError:
        return False
    return bool(m) and m.group(1) == name


def check_job_folders(root: Path, jobs: list[Job]) -> None:
    """UserError unless every job's folder ROOT/NAME is absent or a job folder of a batch holding nothing
    else; called before anything is written (a folder of the user's there is never written into)."""
    from rmavatar.utils import outputs

    for job in jobs:
        folder = root / job.name
        if not os.path.lexists(folder):
            continue
        if folder.is_symlink() or not folder.is_dir():
            raise UserError(f"--out {root}: {job.name} there is not a job folder (job {job.name!r} writes its "
                            "folder there): refusing to replace it; move it away or rename the job")
        foreign = outputs.foreign_files(folder, JOB_KIND)
        if foreign and outputs.read_marker(folder) is None and _unmarked_job_folder(folder, job.name):
            continue
        if foreign:
            raise UserError(f"--out {root}: the folder {job.name}/ holds files that rmavatar did not write there "
                            f"({outputs.some_of(foreign)}): refusing to write job {job.name!r} into it; move them away or rename "
                            "the job")


def mark_job_folders(root: Path, jobs: list[Job]) -> None:
    """Create each job's folder with its marker (listing what the job writes), or add to the marker."""
    from rmavatar.utils import outputs

    for job in jobs:
        folder = root / job.name
        files = job_files(job)
        marker = outputs.read_marker(folder) if folder.is_dir() else None
        if marker is not None and marker.get("kind") == JOB_KIND and set(files) <= set(marker.get("files", [])):
            continue
        folder.mkdir(exist_ok=True)
        outputs.mark_folder(folder, JOB_KIND, files)


def _same_file(a: Path, b: str | os.PathLike | None) -> bool:
    try:
        return b is not None and os.path.samefile(a, b)
    except OSError:
        return False


def run_batch(jobs: list[Job], root: str | os.PathLike, options: BatchOptions | None = None, *,
              jobs_file: str | os.PathLike | None = None) -> dict:
    """Run ``jobs`` under ``root``; returns the results document (also written to ROOT/results.*).

    ``jobs_file``: the JOBS.yaml the jobs were read from; when it is ROOT/jobs.yaml itself, it is the
    user's and is left as it is (otherwise ROOT/jobs.yaml gets the resolved jobs)."""
    options = check_options(options or BatchOptions())
    import_ray()  # say what to install before anything is written
    root = Path(root).resolve()
    check_root(root)
    keep_jobs_yaml = _same_file(root / "jobs.yaml", jobs_file)
    files = RootFiles(root, skip=("jobs.yaml",) if keep_jobs_yaml else ())
    files.check()
    check_job_folders(root, jobs)
    with root_lock(root):
        check_root(root)  # again, now that no other batch can be writing it
        files.check()
        check_job_folders(root, jobs)
        session = stamp_root(root)
        mark_job_folders(root, jobs)
        # The resolved jobs of this invocation: absolute paths, every setting; `rmavatar batch
        # ROOT/jobs.yaml --out ROOT` runs the same batch again.
        if not keep_jobs_yaml:
            files.write("jobs.yaml", yaml.safe_dump({"jobs": [job.yaml_entry() for job in jobs]}, sort_keys=False))
        return _Driver(jobs, root, session, options, files).run()


class _Driver:
    def __init__(self, jobs: list[Job], root: Path, session: str, options: BatchOptions,
                 files: RootFiles | None = None):
        self.files = files
        self.jobs = jobs
        self.root = root
        self.session = session
        self.options = options
        self.results: dict[str, dict] = {}
        self.retries: dict[str, list[str]] = {}
        self.started: set[str] = set()
        self.started_at = time.time()
        self.bar = None
        self.stopping = False  # Ctrl-C: no more retries, collect what finishes

    def say(self, msg: str, *, always: bool = False) -> None:
        """A progress line; ``always``: also with --quiet (a job that failed), then on stderr."""
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        if not self.options.progress:
            if always:
                print(line, file=sys.stderr, flush=True)
        elif self.bar is not None:
            self.bar.write(line)
        else:
            print(line, flush=True)

    def run(self) -> dict:
        todo, skipped = [], 0
        for job in self.jobs:
            earlier = earlier_result(self.root, job)
            if earlier is not None and (earlier["status"] == "ok" or not self.options.retry_failed):
                self.results[job.name] = earlier
                skipped += 1
            else:
                todo.append(job)
        failed_before = sum(1 for r in self.results.values() if r["status"] == "failed")
        if self.options.progress:
            print(f"batch: {len(self.jobs)} job(s) in {self.root}: {skipped - failed_before} finished earlier, "
                  f"{failed_before} failed earlier{' (--retry-failed runs them again)' if failed_before else ''}, "
                  f"{len(todo)} to run", flush=True)
        ray_info = None
        if todo:
            ray_info = self._run_on_ray(todo)
        elif self.options.progress:
            print("nothing to run", flush=True)
        wall = time.time() - self.started_at
        ordered = [self.results[j.name] for j in self.jobs]
        doc = write_results(self.root, ordered, {
            "root": str(self.root), "session": self.session, "wall_seconds": round(wall, 1),
            "ran": len(todo), "skipped": skipped, "ray": ray_info}, files=self.files)
        if self.options.progress:
            print("\n" + markdown(doc))
            print(f"wrote {self.root / 'results.md'}, results.csv and results.json; wall time {wall:.0f} s")
        if self.stopping:
            raise KeyboardInterrupt
        return doc

    # --- Ray ------------------------------------------------------------------------------------------
    def _run_on_ray(self, todo: list[Job]) -> dict:
        ray = import_ray()
        _init_ray(ray, self.options.address, quiet=not self.options.progress)
        try:
            return self._schedule(ray, todo)
        finally:
            ray.shutdown()

    def _schedule(self, ray, todo: list[Job]) -> dict:
        from rmavatar.batch.worker import run_job

        opts = self.options
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        total_gpus = sum(n["Resources"].get("GPU", 0) for n in nodes)
        gpus = opts.gpus_per_job if opts.gpus_per_job is not None else (1 if total_gpus >= 1 else 0)
        cpus = opts.cpus_per_job
        if not any(n["Resources"].get("CPU", 0) >= cpus and n["Resources"].get("GPU", 0) >= gpus for n in nodes):
            have = ", ".join(f"{n['NodeManagerAddress']}: {n['Resources'].get('CPU', 0):g} CPUs, "
                             f"{n['Resources'].get('GPU', 0):g} GPUs" for n in nodes)
            raise UserError(f"no node of the Ray cluster has {cpus:g} CPU(s) and {gpus:g} GPU(s) for a job "
                            f"(nodes: {have}); lower --cpus-per-job / --gpus-per-job")
        device = "cuda" if gpus > 0 else "cpu"
        threads = max(1, int(cpus))
        slots = sum(min(int(n["Resources"].get("CPU", 0) // cpus),
                        int(n["Resources"].get("GPU", 0) // gpus) if gpus else 10**9) for n in nodes)
        info = {"address": opts.address or "local", "nodes": len(nodes), "cpus_per_job": cpus,
                "gpus_per_job": gpus, "device": device, "threads_per_job": threads, "parallel_jobs": slots}
        if opts.progress:
            where = "a local Ray instance" if opts.address is None else f"the Ray cluster at {opts.address}"
            print(f"running {len(todo)} job(s) on {where}: {len(nodes)} node(s), "
                  f"{sum(n['Resources'].get('CPU', 0) for n in nodes):g} CPUs, {total_gpus:g} GPUs; "
                  f"{cpus:g} CPU(s) ({threads} thread(s)) and {gpus:g} GPU(s) per job, up to {slots} at once, "
                  f"training on {device}; each job's log: {self.root}/NAME/job.log", flush=True)
        remote = ray.remote(max_calls=1)(run_job)

        def submit(job: Job, attempt: int):
            return remote.options(num_cpus=cpus, num_gpus=gpus, max_retries=0, retry_exceptions=False,
                                  name=f"rmavatar-batch:{job.name}").remote(
                job.to_dict(), str(self.root), self.session, attempt, threads, device)

        pending = {submit(job, 1): (job, 1) for job in todo}
        from tqdm import tqdm

        self.bar = tqdm(total=len(todo), unit="job", desc="batch", disable=not opts.progress, dynamic_ncols=True)
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=1.0)
                for ref in ready:
                    job, attempt = pending.pop(ref)
                    again = self._collect(ray, ref, job, attempt)
                    if again:
                        pending[submit(job, attempt + 1)] = (job, attempt + 1)
                    else:
                        self.bar.update(1)
                self._show(pending)
        except KeyboardInterrupt:  # a second one, while _cancel waits, stops at once
            self.stopping = True
            self._cancel(ray, pending)
        finally:
            self.bar.close()
            self.bar = None
        return info

    def _collect(self, ray, ref, job: Job, attempt: int) -> bool:
        """Record a finished task; True when it must be resubmitted (its worker died, retries left)."""
        name = job.name
        try:
            result = ray.get(ref)
        except ray.exceptions.TaskCancelledError:
            result = self._synth(job, attempt, "interrupted", "cancelled before it finished; re-run to resume")
        except ray.exceptions.RayTaskError as exc:  # the task could not even start its own error handling
            result = self._synth(job, attempt, "failed", _short(exc))
        except ray.exceptions.RayError as exc:  # the worker process or its node died
            reason = f"{type(exc).__name__}: {_short(exc)}"
            self.retries.setdefault(name, []).append(reason)
            if attempt <= self.options.max_retries and not self.stopping:
                self.say(f"{name}: worker died ({reason}); retry {attempt} of {self.options.max_retries}, "
                         "resuming from its last checkpoint")
                return True
            result = self._synth(job, attempt, "lost", f"worker died {attempt} time(s), last: {reason}; re-run "
                                 "the batch to resume from its checkpoint")
        result["attempts"] = attempt
        if self.retries.get(name):
            result["retries"] = self.retries[name]
        self.results[name] = result
        if result["status"] == "ok":
            metrics = ", ".join(f"{s} PSNR {m['psnr']:.2f}" if m["psnr"] is not None else f"{s} PSNR inf"
                                for s, m in result["splits"].items())
            resumed = f", resumed from iteration {result['resumed_from']}" if result.get("resumed_from") else ""
            self.say(f"{name}: done: {result['iterations']} iterations, {metrics}{resumed}")
        else:
            self.say(f"{name}: {result['status']}: {result['error']}", always=True)
        return False

    def _synth(self, job: Job, attempt: int, status: str, error: str) -> dict:
        return {"job": job.name, "subject": job.subject, "variant": job.variant, "data": job.data,
                "fingerprint": job.fingerprint(), "attempts": attempt, "status": status, "error": error}

    def _show(self, pending: dict) -> None:
        running, waiting = [], 0
        for job, attempt in pending.values():
            p = read_json(self.root / job.name / "progress.json")
            if p and p.get("session") == self.session and p.get("attempt") == attempt:
                if (job.name, attempt) not in self.started:
                    self.started.add((job.name, attempt))
                    self.say(f"{job.name}: started on {p.get('host')} (pid {p.get('pid')}, attempt {attempt})")
                state = p.get("state")
                running.append(f"{job.name} {p.get('iteration')}/{p.get('total')}"
                               + (" eval" if state == "evaluating" else ""))
            else:
                waiting += 1
        failed = sum(1 for r in self.results.values() if r["status"] != "ok")
        shown = ", ".join(running[:4]) + (f", +{len(running) - 4}" if len(running) > 4 else "")
        self.bar.set_postfix_str(f"running {len(running)}, waiting {waiting}, failed {failed}"
                                 + (f" | {shown}" if shown else ""))

    def _cancel(self, ray, pending: dict) -> None:
        """Ctrl-C: ask running jobs to stop (they checkpoint, as on Ctrl-C in rmavatar train), wait a while
        for them, and record every job still pending as interrupted."""
        self.say(f"interrupted: stopping {len(pending)} job(s); they save a checkpoint, re-run to resume")
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=False)
        deadline = time.monotonic() + CANCEL_WAIT_S
        while pending and time.monotonic() < deadline:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=1.0)
            for ref in ready:
                job, attempt = pending.pop(ref)
                self._collect(ray, ref, job, attempt)
        for job, attempt in pending.values():
            self.results[job.name] = self._synth(job, attempt, "interrupted", "still stopping when the batch "
                                                 "gave up waiting; re-run to resume")


def _init_ray(ray, address: str | None, quiet: bool = False) -> None:
    import rmavatar

    # Before torch loads in a worker: idle OpenMP threads sleep instead of spinning (see rmavatar.commands.main).
    env = {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    # --quiet: Ray's own notices (e.g. "Token authentication is enabled for this Ray cluster", which Ray
    # 2.60 logs as a warning whenever it starts a local instance) are not printed; its errors still are.
    kwargs = dict(log_to_driver=False, logging_level=logging.ERROR if quiet else logging.WARNING)
    if address is None:
        # The local workers import the same rmavatar as this process.
        here = str(Path(rmavatar.__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)
        ray.init(address="local", include_dashboard=False, runtime_env={"env_vars": env}, **kwargs)
        return
    try:
        ray.init(address=address, runtime_env={"env_vars": env}, **kwargs)
    except ConnectionError as exc:
        raise UserError(f"--address {address}: cannot join a Ray cluster there ({exc}); start one with 'ray start "
                        "--head', or leave --address out to use this machine alone. A cluster with token "
                        "authentication needs RAY_AUTH_MODE=token (and its token) in this command's environment, "
                        "as any Ray client does") from None


def _short(exc: BaseException) -> str:
    """The last non-empty line of a (possibly multi-line, traceback-carrying) Ray error message."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[-1] if lines else type(exc).__name__
