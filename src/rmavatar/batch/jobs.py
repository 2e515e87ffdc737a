"""JOBS.yaml: the list of avatars a batch trains and evaluates, read and validated before anything runs.

A job is one training run plus the evaluation of some of its dataset's splits. The file lists jobs
directly, or as a ``matrix`` of subjects x variants (or both; ``matrix`` may also be a list of
matrices)::

    defaults:                         # optional, for every job
      body: anny                      # body model spec (default: the dataset's own choice)
      splits: [test]                  # splits to evaluate (default [test])
      eval_frames: null               # score only the first N frames of each split (default: all)
      overrides: {iters: 1000, size: 256, density.max_gaussians: 40000}
    jobs:
      - name: s0                      # folder name under ROOT: letters, digits, . _ -
        data: data/synth0             # dataset spec, relative paths from this file's folder
        splits: [test, novel_pose]
    matrix:
      subjects:
        - {name: s1, data: data/synth1}
      variants: [full, no_rectifier]  # the paper's ablations by name, or {name, overrides}

Config overrides are dotted ``TrainConfig`` keys (``optim.iters``, ``model.rectifier``; nested mappings
also work) or the friendly switches in :data:`SWITCHES` / :data:`rmavatar.train.config.ABLATIONS`;
they are applied defaults -> subject -> variant (-> job) and type-checked by the config's own
machinery, so an error names the job and the key.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rmavatar.utils import UserError

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
# Names that are files of the batch root, not job folders.
RESERVED_NAMES = {"results.csv", "results.json", "results.md", "rmavatar-batch.json", "jobs.yaml",
                  "paper_tables.md"}
# Friendly switches: key -> dotted TrainConfig key (value copied as is).
SWITCHES = {"iters": "optim.iters", "size": "data.size", "seed": "seed"}
# Keys the batch itself sets: the dataset and body come from the job's own fields, the device and
# thread count from --gpus-per-job / --cpus-per-job.
OWNED_KEYS = {"data.path": "the job's data: field", "model.body": "the job's body: field",
              "device": "--gpus-per-job (the batch picks cpu or cuda)",
              "threads": "--cpus-per-job (a job's torch threads)"}
# Settings that do not change what a run computes: they may differ between invocations of a batch
# (a resumed run keeps training) and are left out of a job's fingerprint.
RUNTIME_KEYS = ("threads", "device", "log")
DEFAULT_SPLITS = ("test",)
DEFAULT_VARIANT = "default"


@dataclass
class Job:
    """One training run + evaluation. ``config`` is a complete TrainConfig as a plain dict."""

    name: str
    subject: str
    variant: str
    data: str  # dataset spec, path absolute
    body: str | None
    splits: list[str]
    config: dict = field(repr=False)
    eval_frames: int | None = None  # score only the first N frames of each split; None = all

    def fingerprint(self) -> str:
        """A hash of everything that decides the job's results (not threads, device or logging)."""
        cfg = {k: v for k, v in self.config.items() if k not in RUNTIME_KEYS}
        blob = json.dumps({"config": cfg, "splits": self.splits, "eval_frames": self.eval_frames}, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        return {"name": self.name, "subject": self.subject, "variant": self.variant, "data": self.data,
                "body": self.body, "splits": list(self.splits), "eval_frames": self.eval_frames,
                "config": self.config,
                "fingerprint": self.fingerprint()}

    def yaml_entry(self) -> dict:
        """This job as a JOBS.yaml entry with absolute paths and every non-default setting as an override
        (reading it back gives the same job and fingerprint)."""
        from rmavatar.train.config import TrainConfig, flatten, to_dict

        default = flatten(to_dict(TrainConfig()))
        overrides = {k: v for k, v in flatten(self.config).items()
                     if k not in OWNED_KEYS and default.get(k) != v}
        entry = {"name": self.name, "subject": self.subject, "variant": self.variant, "data": self.data}
        if self.body is not None:
            entry["body"] = self.body
        entry["splits"] = list(self.splits)
        if self.eval_frames is not None:
            entry["eval_frames"] = self.eval_frames
        if overrides:
            entry["overrides"] = overrides
        return entry


# ----------------------------------------------------------------------------------------------- reading
def load_jobs(path: str | os.PathLike) -> list[Job]:
    """Read and validate a JOBS.yaml; every problem is a UserError naming the file, the job and the key."""
    from rmavatar.utils.files import read_yaml_file

    path = Path(path)
    data = read_yaml_file(path, "jobs file", mapping=False)  # parse_jobs says what the top level must be
    return parse_jobs(data, base=path.resolve().parent, where=str(path))


def parse_jobs(data: Any, base: str | os.PathLike = ".", where: str = "JOBS.yaml") -> list[Job]:
    """Jobs from the parsed YAML ``data``; relative paths are taken from folder ``base``."""
    base = Path(base)
    if not isinstance(data, dict):
        raise UserError(f"{where}: expected a mapping with jobs: and/or matrix: at the top level")
    _check_keys(data, {"defaults", "jobs", "matrix"}, where)
    defaults = data.get("defaults") or {}
    _check_mapping(defaults, f"{where}: defaults")
    _check_keys(defaults, {"body", "splits", "eval_frames", "overrides"}, f"{where}: defaults")
    raw: list[tuple[str, dict]] = []  # (where, merged job fields)
    jobs_in = data.get("jobs") or []
    if not isinstance(jobs_in, list):
        raise UserError(f"{where}: jobs: must be a list of jobs")
    for i, job in enumerate(jobs_in):
        w = f"{where}: jobs[{i}]"
        _check_mapping(job, w)
        name = job.get("name")
        w = f"{where}: job {name!r}" if isinstance(name, str) else w
        _check_keys(job, {"name", "data", "body", "splits", "eval_frames", "overrides", "subject", "variant"}, w)
        raw.append((w, {
            "name": name, "data": job.get("data"), "body": job.get("body", defaults.get("body")),
            "splits": job.get("splits", defaults.get("splits")),
            "eval_frames": job.get("eval_frames", defaults.get("eval_frames")),
            "subject": job.get("subject", name), "variant": job.get("variant", DEFAULT_VARIANT),
            "overrides": [(f"{where}: defaults", defaults.get("overrides")), (w, job.get("overrides"))],
        }))
    matrices = data.get("matrix") or []
    if isinstance(matrices, dict):
        matrices = [matrices]
    if not isinstance(matrices, list):
        raise UserError(f"{where}: matrix: must be a mapping (subjects:, variants:) or a list of them")
    for m, matrix in enumerate(matrices):
        mw = f"{where}: matrix" if len(matrices) == 1 else f"{where}: matrix[{m}]"
        raw.extend(_expand_matrix(matrix, defaults, mw, where))
    if not raw:
        raise UserError(f"{where}: no jobs (give jobs: and/or matrix:)")
    jobs = [_make_job(w, fields, base) for w, fields in raw]
    seen: dict[str, str] = {}
    for (w, _), job in zip(raw, jobs):
        if job.name in seen:
            raise UserError(f"{w}: the name {job.name!r} is used twice (job folders must differ)")
        seen[job.name] = w
    return jobs


def _expand_matrix(matrix: Any, defaults: dict, mw: str, where: str) -> list[tuple[str, dict]]:
    _check_mapping(matrix, mw)
    _check_keys(matrix, {"subjects", "variants", "splits"}, mw)
    subjects, variants = matrix.get("subjects"), matrix.get("variants", [{"name": DEFAULT_VARIANT}])
    if not isinstance(subjects, list) or not subjects:
        raise UserError(f"{mw}: subjects: must be a non-empty list of {{name, data}}")
    if not isinstance(variants, list) or not variants:
        raise UserError(f"{mw}: variants: must be a non-empty list")
    out = []
    for i, subject in enumerate(subjects):
        sw = f"{mw}.subjects[{i}]"
        _check_mapping(subject, sw)
        _check_keys(subject, {"name", "data", "body", "splits", "overrides"}, sw)
        for j, variant in enumerate(variants):
            vw = f"{mw}.variants[{j}]"
            variant = _variant(variant, vw)
            sname, vname = subject.get("name"), variant["name"]
            w = f"{where}: job '{sname}-{vname}' ({sw} x {vw})"
            splits = variant.get("splits", subject.get("splits", matrix.get("splits", defaults.get("splits"))))
            out.append((w, {
                "name": f"{sname}-{vname}" if isinstance(sname, str) else sname,
                "data": subject.get("data"), "body": subject.get("body", defaults.get("body")),
                "splits": splits, "eval_frames": defaults.get("eval_frames"), "subject": sname, "variant": vname,
                "overrides": [(f"{where}: defaults", defaults.get("overrides")), (sw, subject.get("overrides")),
                              (vw, variant.get("overrides"))],
            }))
    return out


def _variant(variant: Any, vw: str) -> dict:
    """A variant entry: a known ablation's name, or {name, overrides, splits}."""
    from rmavatar.train.config import ABLATIONS

    if isinstance(variant, str):
        if variant not in ABLATIONS:
            raise UserError(f"{vw}: unknown variant {variant!r}: a bare name must be one of "
                            f"{', '.join(ABLATIONS)}; write {{name: ..., overrides: {{...}}}} for your own")
        return {"name": variant, "overrides": {variant: True}}
    _check_mapping(variant, vw)
    _check_keys(variant, {"name", "overrides", "splits"}, vw)
    if not isinstance(variant.get("name"), str):
        raise UserError(f"{vw}: a variant needs a name")
    return variant


def _make_job(w: str, f: dict, base: Path) -> Job:
    from rmavatar.train.config import TrainConfig, apply_overrides, to_dict

    name = f["name"]
    if not isinstance(name, str) or not NAME_RE.match(name) or name in RESERVED_NAMES:
        raise UserError(f"{w}: name must be 1-100 letters, digits, '.', '_' or '-' (not starting with "
                        f"'.', '_' or '-') and not a results file name; got {name!r}")
    for label in ("subject", "variant"):
        if not isinstance(f[label], str) or not f[label]:
            raise UserError(f"{w}: {label} must be a non-empty string, got {f[label]!r}")
    data = f["data"]
    if not isinstance(data, str) or not data.strip():
        raise UserError(f"{w}: data: must be a dataset spec (a folder or KIND:PATH), got {data!r}")
    data = resolve_spec(data, base)
    body = f["body"]
    if body is not None:
        if not isinstance(body, str) or not (body == "anny" or body.startswith(("anny:", "smpl:"))):
            raise UserError(f"{w}: body: must be anny, anny:PRESET or smpl:PATH, got {body!r}")
        if body.startswith("smpl:"):
            body = "smpl:" + str(_absolute(body[5:], base))
    splits = list(DEFAULT_SPLITS) if f["splits"] is None else f["splits"]
    if (not isinstance(splits, list) or not splits or not all(isinstance(s, str) and s for s in splits)
            or len(set(splits)) != len(splits)):
        raise UserError(f"{w}: splits: must be a non-empty list of distinct split names, got {splits!r}")
    eval_frames = f["eval_frames"]
    if eval_frames is not None and (not isinstance(eval_frames, int) or isinstance(eval_frames, bool)
                                    or eval_frames < 1):
        raise UserError(f"{w}: eval_frames: must be a whole number >= 1 (or null for all), got {eval_frames!r}")
    cfg = TrainConfig()
    for ow, overrides in f["overrides"]:
        if overrides is None:
            continue
        _check_mapping(overrides, f"{ow}: overrides")
        cfg = apply_overrides(cfg, expand_switches(overrides, f"{ow}: overrides"), where=f"{ow}: overrides")
    cfg.data.path = data
    cfg.model.body = body
    try:
        cfg.validate()
    except UserError as exc:
        raise UserError(f"{w}: {exc}") from None
    return Job(name=name, subject=f["subject"], variant=f["variant"], data=data, body=body,
               splits=splits, config=to_dict(cfg), eval_frames=eval_frames)


def expand_switches(overrides: dict, where: str) -> dict:
    """Friendly switches -> dotted TrainConfig keys; other keys pass through (flattened)."""
    from rmavatar.train.config import ABLATIONS, flatten

    out: dict[str, Any] = {}
    for key, value in flatten(overrides).items():
        if key in SWITCHES:
            out[SWITCHES[key]] = value
        elif key in ABLATIONS:
            if not isinstance(value, bool):
                raise UserError(f"{where}.{key}: expected true/false, got {value!r}")
            if value:
                out.update(ABLATIONS[key])
        else:
            if key in OWNED_KEYS:
                raise UserError(f"{where}.{key}: set by the batch, not an override: use {OWNED_KEYS[key]}")
            out[key] = value
    return out


def resolve_spec(spec: str, base: Path) -> str:
    """A dataset spec with its path made absolute against ``base`` (kind and ?options kept)."""
    from rmavatar.data.registry import parse_spec

    kind, path, options = parse_spec(spec)
    query = "&".join(f"{k}={v}" for k, v in options.items())
    return f"{kind + ':' if kind else ''}{_absolute(str(path), base)}{'?' + query if query else ''}"


def _absolute(path: str, base: Path) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else (base / p).resolve()


def _check_mapping(value: Any, where: str) -> None:
    if not isinstance(value, dict):
        raise UserError(f"{where}: expected a mapping, got {value!r}")


def _check_keys(d: dict, known: set[str], where: str) -> None:
    unknown = sorted(str(k) for k in set(d) - known)
    if unknown:
        raise UserError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
