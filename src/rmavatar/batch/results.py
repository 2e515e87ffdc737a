"""The batch's tables: one row per job and split, grouped means per variant, as CSV, JSON and Markdown."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
from pathlib import Path
from typing import Callable

from rmavatar.utils import UserError

COLUMNS = ("job", "subject", "variant", "split", "status", "psnr", "ssim", "lpips", "frames", "iterations",
           "gaussians", "train_seconds", "eval_seconds", "attempts", "error")
PROTOCOL = ("full images (not masked) over the training background, at the training resolution; PSNR "
            "20 log10(1/RMSE) per image, SSIM 11x11 Gaussian window (sigma 1.5), LPIPS AlexNet v0.1 on "
            "[-1,1] inputs, each averaged over the split's frames; no test-time pose refinement")


def rows_of(results: list[dict]) -> list[dict]:
    """One row per job and evaluated split; a job that did not finish is one row with its error."""
    rows = []
    for r in results:
        common = {"job": r["job"], "subject": r["subject"], "variant": r["variant"], "status": r["status"],
                  "iterations": r.get("iterations"), "gaussians": r.get("gaussians"),
                  "train_seconds": r.get("train_seconds"), "eval_seconds": r.get("eval_seconds"),
                  "attempts": r.get("attempts"), "error": r.get("error")}
        if r["status"] == "ok":
            for split, m in r["splits"].items():
                rows.append({**common, "split": split, "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
                             "frames": m["frames"]})
        else:
            rows.append({**common, "split": None, "psnr": None, "ssim": None, "lpips": None, "frames": None})
    return [{c: row.get(c) for c in COLUMNS} for row in rows]


def by_variant(rows: list[dict]) -> list[dict]:
    """Means over the finished jobs of each (variant, split), in first-seen order."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        if row["status"] == "ok":
            groups.setdefault((row["variant"], row["split"]), []).append(row)
    out = []
    for (variant, split), members in groups.items():
        entry = {"variant": variant, "split": split, "jobs": len(members)}
        for key in ("psnr", "ssim", "lpips", "train_seconds", "iterations", "gaussians"):
            values = [m[key] for m in members if m[key] is not None]
            entry[key] = sum(values) / len(values) if len(values) == len(members) and values else None
        out.append(entry)
    return out


def write_results(root: Path, results: list[dict], meta: dict, files: RootFiles | None = None) -> dict:
    """ROOT/results.{json,csv,md}; returns the JSON document. ``files``: the root's files as checked before
    the batch started (see :class:`RootFiles`); by default they are checked now."""
    rows = rows_of(results)
    doc = {"format": "rmavatar-batch-results", "version": 1, **meta, "protocol": PROTOCOL, "rows": rows,
           "by_variant": by_variant(rows), "jobs": results}
    if files is None:
        files = RootFiles(root)
        files.check()
    texts = {"results.json": json.dumps(doc, indent=2, allow_nan=False) + "\n", "results.csv": csv_text(rows),
             "results.md": markdown(doc)}
    for name in texts:  # all three before any is written: none of them may have become the user's meanwhile
        files.check_unchanged(name)
    for name, text in texts.items():
        files.write(name, text)
    return doc


def csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------- the root's files
def _results_document(text: str) -> dict:
    """The results document in ``text`` (ValueError when it is not one)."""
    doc = json.loads(text)
    if not isinstance(doc, dict) or doc.get("format") != "rmavatar-batch-results":
        raise ValueError("not a results document")
    return doc


def results_doc(root: Path) -> dict:
    return _results_document((root / "results.json").read_text())


def _same_json(text: str) -> str:
    return json.dumps(_results_document(text), indent=2, allow_nan=False) + "\n"


def _same_jobs_yaml(text: str) -> str:
    import yaml

    data = yaml.safe_load(text)
    if not isinstance(data, dict) or set(data) != {"jobs"} or not isinstance(data["jobs"], list):
        raise ValueError("not a resolved jobs file")
    return yaml.safe_dump(data, sort_keys=False)


# name -> what rmavatar writes there, made from the file's own text (JSON, YAML) or from ROOT/results.json
# (the tables), for files the written-file registry does not know (written on another host, or before the
# registry kept the batch's files): a file that is exactly what rmavatar would write is rmavatar's.
Regenerate = Callable[[Path, str], str]
REGENERATE: dict[str, Regenerate] = {
    "results.json": lambda root, text: _same_json(text),
    "results.csv": lambda root, text: csv_text(results_doc(root)["rows"]),
    "results.md": lambda root, text: markdown(results_doc(root)),
    "jobs.yaml": lambda root, text: _same_jobs_yaml(text),
}


class RootFiles:
    """The files a batch writes directly in its folder ROOT (the tables, jobs.yaml; reproduce's
    paper_tables.md), under the output rule of :mod:`rmavatar.utils.outputs`: a file there is replaced
    only when rmavatar wrote it (the written-file registry, or exactly what rmavatar would write, see
    ``REGENERATE``), never a file of the user's. :meth:`check` proves it for every file before the batch
    starts, and remembers each file's content; :meth:`write` replaces a file only while it still holds
    that content (or is absent, as it was)."""

    def __init__(self, root: str | os.PathLike, extra: dict[str, Regenerate | None] | None = None,
                 skip: tuple[str, ...] = ()):
        self.root = Path(root)
        self.regenerate: dict[str, Regenerate | None] = {**REGENERATE, **(extra or {})}
        for name in skip:
            self.regenerate.pop(name, None)
        self.seen: dict[str, str | None] = {}

    def _state(self, name: str) -> str | None:
        path = self.root / name
        if not os.path.lexists(path):
            return None
        if path.is_symlink() or not path.is_file():
            return "not a file"
        return hashlib.sha256(path.read_bytes()).hexdigest()

    def _refuse(self, name: str, why: str) -> UserError:
        return UserError(f"--out {self.root}: {name} there {why}: refusing to replace it; move it away, or "
                         "choose another --out")

    def check(self, names: tuple[str, ...] | None = None) -> None:
        """UserError unless every file (or ``names``) may be replaced; remembers what each holds now."""
        from rmavatar.utils.outputs import wrote_file

        for name in names or tuple(self.regenerate):
            path = self.root / name
            state = self._state(name)
            if state == "not a file":
                raise self._refuse(name, "is not a regular file")
            if state is not None and not wrote_file(path) and not self._regenerated(name):
                raise self._refuse(name, "was not written by rmavatar, or was changed since")
            self.seen[name] = state

    def _regenerated(self, name: str) -> bool:
        make = self.regenerate.get(name)
        if make is None:
            return False
        try:
            text = (self.root / name).read_text()
            return make(self.root, text) == text
        except Exception:  # noqa: BLE001 - any failure to regenerate only means: not proven
            return False

    def check_unchanged(self, name: str) -> None:
        """UserError when ``name`` changed since :meth:`check` (a file the user put there meanwhile)."""
        if name not in self.seen:
            self.check((name,))
        elif self._state(name) != self.seen[name]:
            raise self._refuse(name, "changed while the batch ran")

    def write(self, name: str, text: str) -> None:
        """Replace ``name`` with ``text`` (atomically, recorded in the written-file registry)."""
        from rmavatar.utils.outputs import output_file

        self.check_unchanged(name)
        with output_file(self.root / name, option=f"--out {self.root}: {name}", overwrite=True) as tmp:
            tmp.write_text(text)
        self.seen[name] = self._state(name)


def _num(value, digits: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def markdown(doc: dict) -> str:
    """The per-job table, the per-variant means and the protocol, as Markdown."""
    lines = ["| job | split | status | PSNR | SSIM | LPIPS | iterations | Gaussians | train s | eval s | attempts |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    failures = []
    for r in doc["rows"]:
        status = r["status"] if not r["error"] else f"{r['status']} (see below)"
        lines.append(f"| {r['job']} | {r['split'] or '-'} | {status} | {_num(r['psnr'], 2)} | "
                     f"{_num(r['ssim'], 4)} | {_num(r['lpips'], 4)} | {_num(r['iterations'], 0)} | "
                     f"{_num(r['gaussians'], 0)} | {_num(r['train_seconds'], 0)} | {_num(r['eval_seconds'], 0)} | "
                     f"{_num(r['attempts'], 0)} |")
        if r["error"]:
            failures.append(f"- **{r['job']}**: {r['error']}")
    lines += ["", "Means per variant (finished jobs):", "",
              "| variant | split | jobs | PSNR | SSIM | LPIPS | train s | Gaussians |",
              "|---|---|---|---|---|---|---|---|"]
    for g in doc["by_variant"]:
        lines.append(f"| {g['variant']} | {g['split']} | {g['jobs']} | {_num(g['psnr'], 2)} | {_num(g['ssim'], 4)} | "
                     f"{_num(g['lpips'], 4)} | {_num(g['train_seconds'], 0)} | {_num(g['gaussians'], 0)} |")
    if failures:
        lines += ["", "Jobs that did not finish:", "", *failures]
    wall = doc.get("wall_seconds")
    lines += ["", f"Protocol: {doc['protocol']}."]
    if wall is not None:
        lines.append(f"Wall time of the last `rmavatar batch` invocation: {wall:.0f} s "
                     f"({doc.get('ran', 0)} job(s) run, {doc.get('skipped', 0)} finished earlier).")
    return "\n".join(lines) + "\n"
