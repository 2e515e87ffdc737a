"""The batch's tables: one row per job and split, grouped means per variant, as CSV, JSON and Markdown."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from rmavatar.utils import atomic_path

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


def write_results(root: Path, results: list[dict], meta: dict) -> dict:
    """ROOT/results.{json,csv,md}; returns the JSON document."""
    rows = rows_of(results)
    doc = {"format": "rmavatar-batch-results", "version": 1, **meta, "protocol": PROTOCOL, "rows": rows,
           "by_variant": by_variant(rows), "jobs": results}
    with atomic_path(root / "results.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    with atomic_path(root / "results.csv") as tmp:
        tmp.write_text(buf.getvalue())
    with atomic_path(root / "results.md") as tmp:
        tmp.write_text(markdown(doc))
    return doc


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
