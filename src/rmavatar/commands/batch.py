"""``rmavatar batch JOBS.yaml --out ROOT``: train and evaluate many avatars on a Ray cluster (or this machine)."""

from __future__ import annotations

import argparse

EPILOG = """JOBS.yaml (relative paths are taken from the file's folder):

  defaults:
    overrides: {iters: 1000, size: 256, density.max_gaussians: 40000}
    splits: [test, novel_pose]
  matrix:
    subjects:
      - {name: s0, data: data/synth0}
      - {name: s1, data: data/synth1}
    variants: [full, no_rectifier]        # or {name: V, overrides: {...}}
  jobs:                                   # single jobs, alone or beside a matrix
    - {name: m3c, data: "peoplesnapshot:data/male-3-casual", body: "smpl:models/smpl"}

examples:
  rmavatar batch jobs.yaml --out runs/batch1                  # a local Ray instance on this machine
  rmavatar batch jobs.yaml --out /nfs/runs/b1 --address auto  # the cluster 'ray start' joined
  rmavatar batch jobs.yaml --out runs/batch1                  # again: skips finished jobs, resumes the rest

Each job gets ROOT/NAME/ (run/, job.log, progress.json, eval_SPLIT.json, result.json); at the end
ROOT/results.csv, results.json and results.md hold one row per job and split plus the means per
variant. On a multi-node cluster ROOT must be on a filesystem every node mounts at the same path.
Needs Ray: pip install 'rmavatar[cluster]'. Details: docs/batch.md."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("jobs", metavar="JOBS.yaml", help="the jobs to run (format below and in docs/batch.md)")
    parser.add_argument("--out", required=True, metavar="ROOT",
                        help="batch folder: one sub-folder per job and the results tables (new, empty or an "
                        "earlier batch's)")
    add_cluster_arguments(parser)


def add_cluster_arguments(parser: argparse.ArgumentParser) -> None:
    """The Ray options, shared with ``rmavatar reproduce``."""
    parser.add_argument("--address", metavar="ADDR",
                        help="join this Ray cluster ('auto' = the one 'ray start' made on this machine, or "
                        "HOST:PORT); default: start a local Ray instance on this machine alone")
    parser.add_argument("--gpus-per-job", type=float, metavar="G",
                        help="GPUs per job (default: 1 when the cluster has GPUs, else 0 and jobs train on CPU)")
    parser.add_argument("--cpus-per-job", type=float, default=1.0, metavar="C",
                        help="CPUs per job, also its torch thread count (default 1: on CPUs, several one-thread "
                        "jobs side by side use cores better than one job with many threads)")
    parser.add_argument("--max-retries", type=int, default=2, metavar="N",
                        help="resubmit a job whose worker died (kill, out of memory, lost node) up to N times; "
                        "it resumes from its last checkpoint (default 2)")
    parser.add_argument("--retry-failed", action="store_true",
                        help="run again jobs that failed with an error in an earlier run of this batch")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def options_from_args(args: argparse.Namespace):
    from rmavatar.batch.driver import BatchOptions

    return BatchOptions(address=args.address, gpus_per_job=args.gpus_per_job, cpus_per_job=args.cpus_per_job,
                        max_retries=args.max_retries, retry_failed=args.retry_failed, progress=not args.quiet)


def check_cluster_options(args: argparse.Namespace) -> None:
    """UserError for a Ray option out of range (NaN included), before any work is done."""
    from rmavatar.batch.driver import check_options

    check_options(options_from_args(args))


def exit_code(doc: dict) -> int:
    """0 when every job finished, 1 when some failed or were lost (the tables say which)."""
    return 0 if all(r["status"] == "ok" for r in doc["jobs"]) else 1


def run(args: argparse.Namespace) -> int:
    from rmavatar.batch.driver import run_batch
    from rmavatar.batch.jobs import load_jobs

    check_cluster_options(args)
    jobs = load_jobs(args.jobs)  # every job is validated before anything starts
    doc = run_batch(jobs, args.out, options_from_args(args), jobs_file=args.jobs)
    return exit_code(doc)
