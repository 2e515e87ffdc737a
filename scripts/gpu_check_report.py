"""Gather a ``scripts/gpu-check`` logs folder into one JSON and print a short summary.

    python scripts/gpu_check_report.py LOGS OUT.json

LOGS holds steps.tsv (name, rc, seconds, time limit per step; rc "skipped" when the budget was spent),
settings.tsv, versions.json, nvidia-smi.txt, mem.csv and each step's log and JSON. Every file may be
missing or broken (its step failed): what is there is reported, the rest is null. Needs no torch.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path


def _json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _text(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def _tsv(path: Path) -> list[list[str]]:
    return [line.split("\t") for line in _text(path).splitlines() if line.strip()]


def _ms(seconds):
    return None if seconds is None else round(1e3 * seconds, 3)


def _scalars(d, depth: int = 2) -> dict:
    """The numbers, strings and booleans of a JSON object, nested objects flattened with '.' (for results
    whose layout this script does not know)."""
    out = {}
    for k, v in (d or {}).items():
        if isinstance(v, (int, float, str, bool)) or v is None:
            out[k] = v
        elif isinstance(v, dict) and depth > 1:
            out.update({f"{k}.{kk}": vv for kk, vv in _scalars(v, depth - 1).items()})
    return out


def steps(logs: Path) -> dict:
    out = {}
    for row in _tsv(logs / "steps.tsv"):
        name, rc, secs, limit = (row + [None] * 4)[:4]
        out[name] = {"rc": int(rc) if rc and rc.lstrip("-").isdigit() else rc,
                     "seconds": float(secs) if secs else None, "limit_s": int(limit) if limit else None}
    return out


def pytest_counts(log: str) -> dict | None:
    """'27 passed, 1 skipped in 50.21s' (pytest's last line) as numbers."""
    lines = [s for s in log.splitlines() if re.search(r"\d+ (passed|failed|error|skipped)", s)]
    if not lines:
        return None
    kinds = r"(\d+) (passed|failed|errors?|skipped|deselected|xfailed|xpassed)"
    counts = {k: int(n) for n, k in re.findall(kinds, lines[-1])}
    failed = [s.split(" ")[1] for s in log.splitlines() if s.startswith(("FAILED ", "ERROR "))]
    return {**counts, "failed_tests": failed[:30]}


def train_summary(log: str) -> dict | None:
    """The trainer's closing line: 'done: N iterations in S s (X it/s), G Gaussians, last training PSNR P dB'."""
    m = re.search(r"done: (\d+) iterations in ([\d.]+) s \(([\d.]+) it/s\), (\d+) Gaussians"
                  r"(?:, last training PSNR ([\d.]+) dB)?", log.replace("\r", "\n"))
    if not m:
        return None
    graphs = re.search(r"^(CUDA graphs.*)$", log.replace("\r", "\n"), re.M)
    passes = [float(s) for s in re.findall(r"done: \d+ iterations in ([\d.]+) s", log.replace("\r", "\n"))]
    return {"iterations": int(m[1]), "seconds": float(m[2]), "iterations_per_s": float(m[3]),
            "gaussians": int(m[4]), "train_psnr": float(m[5]) if m[5] else None,
            "cuda_graphs": graphs[1] if graphs else None,
            "all_passes_seconds": sum(passes), "passes": len(passes)}  # a pose-refining run has two


def memory(path: Path) -> dict | None:
    used = [int(s) for s in re.findall(r"^\s*(\d+)", _text(path), re.M)]
    return {"idle_mib": used[0], "peak_mib": max(used), "samples": len(used)} if used else None


def bench_step(d) -> dict | None:
    if not d:
        return None
    counts = d.get("counts") or {}
    return {"step_median_ms": _ms(d.get("step_median_s")), "iterations_per_s": d.get("iterations_per_s"),
            "gaussians": d.get("gaussians"), "capacity": d.get("capacity"),
            "cuda_graphs": (d.get("cuda_graphs") or {}).get("used"),
            "captures": (d.get("cuda_graphs") or {}).get("captures"),
            "host_syncs_per_step": counts.get("syncs_per_step"), "ops_per_step": counts.get("ops_per_step"),
            "stages_ms": {k: _ms(v.get("wall_s")) for k, v in (d.get("stages") or {}).items()},
            "other_ms": _ms((d.get("other") or {}).get("wall_s"))}


def bench_render(d) -> dict | None:
    if not d:
        return None
    keys = {"fps": d.get("fps"), "frame_ms": _ms(d.get("frame_s")), "posing_ms": _ms(d.get("posing_s")),
            "raster_ms": _ms(d.get("raster_s")), "gaussians": d.get("gaussians"), "size": d.get("size"),
            "graph": (d.get("graph") or {}).get("used") if isinstance(d.get("graph"), dict) else d.get("graph")}
    if keys["fps"] is None:  # a layout this script does not know yet: keep its plain values
        return _scalars(d)
    return keys


def evaluation(d) -> dict | None:
    return None if not d else {**(d.get("mean") or {}), "frames": len(d.get("frames") or [])}


def report(logs: Path) -> dict:
    settings = {row[0]: row[1] if len(row) > 1 else "" for row in _tsv(logs / "settings.tsv")}
    smi = [s.strip() for s in _text(logs / "nvidia-smi.txt").strip().split(",")]
    profile = _json(logs / "profile.json")
    return {
        "settings": settings,
        "gpu": {"name": smi[0] or None, "driver": smi[1] if len(smi) > 1 else None,
                "memory_total": smi[2] if len(smi) > 2 else None},
        "versions": _json(logs / "versions.json"),
        "steps": steps(logs),
        "tests": pytest_counts(_text(logs / "tests.log")),
        "bench_step": bench_step(_json(logs / "bench_step.json")),
        "bench_step_eager": bench_step(_json(logs / "bench_step_eager.json")),
        "bench_step_refine": bench_step(_json(logs / "bench_step_refine.json")),
        "train": train_summary(_text(logs / "train.log")),
        "train_plain_short": train_summary(_text(logs / "train_plain_short.log")),
        "train_refine": train_summary(_text(logs / "train_refine.log")),
        "train_gpu_memory": memory(logs / "mem.csv"),
        "eval_test": evaluation(_json(logs / "eval_test.json")),
        "eval_novel_pose": evaluation(_json(logs / "eval_novel_pose.json")),
        "bench_render": bench_render(_json(logs / "bench_render.json")),
        "bench_render_eager": bench_render(_json(logs / "bench_render_eager.json")),
        "profile": None if not profile else {k: v for k, v in profile.items() if k != "top_kernels"},
        "profile_top_kernels": None if not profile else (profile.get("top_kernels") or [])[:10],
    }


def _f(v, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt) if isinstance(v, (int, float)) else str(v)


def summary(r: dict) -> str:
    s = r["settings"]
    lines = [f"gpu-check: {r['gpu']['name'] or 'no GPU'} (driver {_f(r['gpu']['driver'])}), torch "
             f"{_f((r['versions'] or {}).get('torch'))}, device {s.get('DEVICE')}, size {s.get('SIZE')}, "
             f"{s.get('ITERS')} iterations"]
    lines.append("  steps: " + ", ".join(f"{k} {'ok' if v['rc'] == 0 else 'rc=' + str(v['rc'])} "
                                         f"{_f(v['seconds'], '.0f')} s" for k, v in r["steps"].items()))
    if r["tests"]:
        lines.append("  tests: " + ", ".join(f"{v} {k}" for k, v in r["tests"].items() if k != "failed_tests")
                     + ("; failed: " + " ".join(r["tests"]["failed_tests"]) if r["tests"]["failed_tests"] else ""))
    for key, what in (("bench_step", "training step"), ("bench_step_eager", "eager step"),
                      ("bench_step_refine", "refining step")):
        if b := r.get(key):
            rows = f" in buffers of {b['capacity']} rows" if b.get("capacity") else ""
            lines.append(f"  {what}: {_f(b['step_median_ms'])} ms median, {b['gaussians']} Gaussians{rows}, "
                         f"{_f(b['host_syncs_per_step'])} host syncs/step, CUDA graphs {b['cuda_graphs']}")
    if t := r["train"]:
        lines.append(f"  training: {t['iterations']} iterations in {_f(t['seconds'], '.0f')} s "
                     f"({_f(t['iterations_per_s'], '.1f')} it/s), {t['gaussians']} Gaussians")
        if t.get("cuda_graphs"):
            lines.append(f"    {t['cuda_graphs']}")
    plain, refine = r.get("train_plain_short"), r.get("train_refine")
    finished = all((r["steps"].get(k) or {}).get("rc") == 0 for k in ("train_plain_short", "train_refine"))
    if plain and refine and not finished:
        lines.append("  pose refinement: not compared (a run did not finish)")
    elif plain and refine:
        r_s, p_s = refine["all_passes_seconds"], plain["all_passes_seconds"]
        lines.append(f"  pose refinement: {refine['passes']} passes in {_f(r_s, '.0f')} s against "
                     f"{_f(p_s, '.0f')} s plain = {_f(r_s / p_s if p_s else None)}x")
    if m := r["train_gpu_memory"]:
        lines.append(f"  GPU memory during training (nvidia-smi): peak {m['peak_mib']} MiB (idle {m['idle_mib']})")
    for split in ("test", "novel_pose"):
        if e := r[f"eval_{split}"]:
            lines.append(f"  eval {split}: PSNR {_f(e.get('psnr'))}, SSIM {_f(e.get('ssim'), '.4f')}, "
                         f"LPIPS {_f(e.get('lpips'), '.4f')} ({e['frames']} frames)")
    for key, what in (("bench_render", "render"), ("bench_render_eager", "render, eager posing")):
        if (g := r.get(key)) and "fps" in g:
            lines.append(f"  {what} at {g.get('size')} px: {_f(g.get('frame_ms'))} ms/frame = {_f(g['fps'], '.0f')} "
                         f"FPS (posing {_f(g.get('posing_ms'))}, rasterizing {_f(g.get('raster_ms'))}, graph {g.get('graph')})")
    if p := r["profile"]:
        lines.append(f"  profile: wall {_f(p.get('wall_ms'))} ms/step, GPU kernels {_f(p.get('gpu_kernel_ms'))} "
                     f"ms/step, {_f(p.get('gpu_kernels'), '.0f')} kernels and {_f(p.get('kernel_launches'), '.0f')} "
                     f"launches/step, {_f(p.get('host_syncs'))} host syncs/step")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    r = report(Path(argv[0]))
    Path(argv[1]).write_text(json.dumps(r, indent=1) + "\n")
    print(summary(r))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
