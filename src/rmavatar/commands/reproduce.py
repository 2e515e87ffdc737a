"""``rmavatar reproduce paper``: the paper's Tables 1, 2 and 4 as one batch, our numbers beside the paper's."""

from __future__ import annotations

import argparse

from rmavatar.utils import UserError
from rmavatar.utils.outputs import add_overwrite_argument

EPILOG = """What it runs (RMAvatar §4; docs/batch.md):
  Table 1  PeopleSnapshot male-3-casual, male-4-casual, female-3-casual, female-4-casual: full model,
           evaluated on each subject's test frames
  Table 2  ZJU-MoCap 377, 386, 387, 392, 393, 394 (camera 1, the paper's split): full model, test frames
  Table 4  the same PeopleSnapshot subjects without the rectifier, the offset loss, the scaling loss
  each trained for 50,000 iterations with the paper's settings: 4 x 4 + 6 = 22 jobs with both datasets.

examples:
  rmavatar reproduce paper --people-snapshot data/people_snapshot --zju data/zju_mocap \\
      --body smpl:models/smpl --out runs/paper --address auto
  rmavatar reproduce paper --people-snapshot data/people_snapshot --body smpl:models/smpl \\
      --out runs/ps --tables 1 --subjects male-3-casual --iters 2000 --size 540      # a quick look
  rmavatar reproduce paper --zju data/zju_mocap --body smpl:models/smpl --out runs/zju --write-jobs zju.yaml

Re-running the same command skips finished jobs and resumes the others. The tables are printed at the
end and written to ROOT/paper_tables.md; ROOT/results.{csv,json,md} hold every job's numbers."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from rmavatar.commands.batch import add_cluster_arguments

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("what", choices=["paper"], help="what to reproduce: 'paper' (RMAvatar's result tables)")
    parser.add_argument("--people-snapshot", metavar="DIR",
                        help="folder holding male-3-casual/, male-4-casual/, female-3-casual/, female-4-casual/ "
                        "(InstantAvatar's preprocessing)")
    parser.add_argument("--zju", metavar="DIR", help="folder holding CoreView_377/ ... CoreView_394/ (or my_377/ ...)")
    parser.add_argument("--body", required=True, metavar="SPEC",
                        help="body model: smpl:PATH (the paper's; a folder with SMPL_{NEUTRAL,MALE,FEMALE} or one "
                        "file), or anny")
    parser.add_argument("--out", required=True, metavar="ROOT", help="batch folder (see rmavatar batch)")
    parser.add_argument("--tables", type=int, nargs="+", default=[1, 2, 4], metavar="T",
                        help="which of the paper's tables: 1 2 4 (default all)")
    parser.add_argument("--subjects", nargs="+", metavar="S",
                        help="only these subjects (e.g. male-3-casual 377); default: all the paper's")
    parser.add_argument("--iters", type=int, default=None, metavar="N",
                        help="training iterations per job (default 50000, the paper's)")
    parser.add_argument("--size", type=int, default=None, metavar="S",
                        help="train and evaluate at this image size (longer side); default: the datasets' own")
    parser.add_argument("--eval-frames", type=int, default=None, metavar="N",
                        help="score only the first N frames of each test split (a quick look; default: all, "
                        "as the paper)")
    parser.add_argument("--write-jobs", metavar="FILE",
                        help="only write the batch's JOBS.yaml to FILE (to edit and run with rmavatar batch); "
                        "an existing FILE is replaced only when rmavatar wrote it (or with --overwrite)")
    add_cluster_arguments(parser)
    add_overwrite_argument(parser)


# The options that only matter when the batch runs: with --write-jobs they would have no effect.
RUN_ONLY = (("address", "--address"), ("gpus_per_job", "--gpus-per-job"), ("cpus_per_job", "--cpus-per-job"),
            ("max_retries", "--max-retries"), ("retry_failed", "--retry-failed"))
_DEFAULTS = {"address": None, "gpus_per_job": None, "cpus_per_job": 1.0, "max_retries": 2, "retry_failed": False}


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import yaml

    from rmavatar.batch.jobs import parse_jobs
    from rmavatar.batch.paper import PAPER_ITERS, comparison, paper_jobs
    from rmavatar.commands.batch import check_cluster_options, exit_code, options_from_args
    from rmavatar.utils.outputs import check_output_file, output_file

    if args.iters is not None and args.iters < 1:
        raise UserError(f"--iters must be >= 1, got {args.iters}")
    if args.size is not None and args.size < 1:
        raise UserError(f"--size must be >= 1, got {args.size}")
    if args.eval_frames is not None and args.eval_frames < 1:
        raise UserError(f"--eval-frames must be >= 1, got {args.eval_frames}")
    check_cluster_options(args)
    if args.overwrite and not args.write_jobs:
        raise UserError("--overwrite only applies to --write-jobs FILE (a batch folder is continued, never "
                        "overwritten): leave it out")
    if args.write_jobs:
        given = [opt for key, opt in RUN_ONLY if getattr(args, key) != _DEFAULTS.get(key)]
        if given:
            it = "it" if len(given) == 1 else "them"
            raise UserError(f"{', '.join(given)} ha{'s' if len(given) == 1 else 've'} no effect with --write-jobs "
                            f"(it only writes the jobs file): leave {it} out, or give {it} to rmavatar batch")
        # Checked before the jobs are made: the user's file is never replaced (see rmavatar.utils.outputs).
        check_output_file(args.write_jobs, option="--write-jobs", overwrite=args.overwrite,
                          suffixes=(".yaml", ".yml"))
    doc = paper_jobs(args.people_snapshot, args.zju, args.body, iters=args.iters or PAPER_ITERS,
                     size=args.size, tables=args.tables, subjects=args.subjects, eval_frames=args.eval_frames)
    jobs = parse_jobs(doc, where="the paper's jobs")
    if args.write_jobs:
        with output_file(args.write_jobs, option="--write-jobs", overwrite=args.overwrite,
                         suffixes=(".yaml", ".yml")) as tmp:
            tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
        print(f"wrote {len(jobs)} job(s) to {args.write_jobs}; run them with: rmavatar batch {args.write_jobs} "
              f"--out {args.out}")
        return 0
    from rmavatar.batch.driver import check_root, run_batch
    from rmavatar.batch.results import RootFiles, results_doc

    title = "# RMAvatar's tables: ours next to the paper's\n\n"
    root = Path(args.out).resolve()
    check_root(root)
    # ROOT/paper_tables.md is replaced only when rmavatar wrote it (checked before the batch starts).
    tables = RootFiles(root, {"paper_tables.md": lambda r, _: title + comparison(results_doc(r))},
                       skip=("results.json", "results.csv", "results.md", "jobs.yaml"))
    tables.check()
    result = run_batch(jobs, args.out, options_from_args(args))
    text = comparison(result)
    tables.write("paper_tables.md", title + text)
    if not args.quiet:
        print("\n" + text)
        print(f"wrote {root / 'paper_tables.md'}")
    return exit_code(result)
