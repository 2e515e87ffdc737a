"""The paper's experiments as one batch, and our numbers printed beside the paper's.

RMAvatar (Peng et al.), §4: Table 1 = PeopleSnapshot, the four InstantAvatar subjects, their test
frames (novel views of the rotation); Table 2 = ZJU-MoCap 377, 386, 387, 392, 393, 394, one camera, the
split of the paper's Table 3 (train 1 in 4); Table 4 = ablations on PeopleSnapshot (w/o GauRec, w/o
OffsetLoss, w/o ScalingLoss, full). Every model is trained for 50,000 iterations with the paper's
settings (rmavatar's defaults). The paper does not state the image resolution, the background or
which frames Table 4 averages: we train and evaluate at the dataset's own resolution unless told
otherwise, score full images over white, and average Table 4 over the PeopleSnapshot subjects run.
Its Table 4 "full model" (32.51 dB) is not the mean of its Table 1 (32.46 dB), so that choice is ours.
"""

from __future__ import annotations

from pathlib import Path

from rmavatar.utils import UserError

PAPER_ITERS = 50_000  # §4.2: "trained for 50,000 iterations"

# (PSNR, SSIM, LPIPS) as printed in the paper's LaTeX tables.
TABLE1 = {  # tab:exp_people, row "Ours"
    "male-3-casual": (34.12, 0.985, 0.013),
    "male-4-casual": (31.23, 0.983, 0.022),
    "female-3-casual": (31.42, 0.980, 0.021),
    "female-4-casual": (33.06, 0.982, 0.013),
}
TABLE2 = {  # tab:exp_zju, row "Ours"
    "377": (32.68, 0.982, 0.015),
    "386": (30.61, 0.955, 0.055),
    "387": (31.01, 0.973, 0.021),
    "392": (34.30, 0.979, 0.024),
    "393": (31.09, 0.969, 0.025),
    "394": (32.70, 0.969, 0.025),
}
TABLE4 = {  # tab:ablation, in the paper's row order
    "no_rectifier": (31.92, 0.974, 0.017),  # w/o GauRec
    "no_offset_loss": (32.48, 0.983, 0.017),  # w/o OffsetLoss
    "no_scaling_loss": (32.45, 0.983, 0.017),  # w/o ScalingLoss
    "full": (32.51, 0.983, 0.017),  # Full model
}
VARIANT_LABELS = {"no_rectifier": "w/o GauRec", "no_offset_loss": "w/o OffsetLoss",
                  "no_scaling_loss": "w/o ScalingLoss", "full": "Full model"}
TABLES = (1, 2, 4)
ZJU_FOLDERS = ("CoreView_{}", "my_{}")  # the original release and the refined ("my_") one


def zju_job_subject(subject: str) -> str:
    return f"zju-{subject}"


def paper_jobs(people_snapshot: str | Path | None, zju: str | Path | None, body: str, *,
               iters: int = PAPER_ITERS, size: int | None = None, tables=TABLES,
               subjects: list[str] | None = None, eval_frames: int | None = None) -> dict:
    """The JOBS.yaml document (a dict) for the paper's tables.

    people_snapshot / zju: folders holding the subjects (``male-3-casual/``...; ``CoreView_377/`` or
    ``my_377/``...); either may be None, and that dataset's tables are left out. tables: which of 1, 2, 4.
    subjects: only these (PeopleSnapshot names or ZJU ids). iters, size: the training budget (the
    paper's 50,000 iterations at the datasets' own resolution by default). eval_frames: score only the
    first N test frames (a quick look; the paper scores all).
    """
    tables = sorted(set(tables))
    bad = [t for t in tables if t not in TABLES]
    if bad or not tables:
        raise UserError(f"--tables: the paper's result tables are 1 (PeopleSnapshot), 2 (ZJU-MoCap) and 4 "
                        f"(ablations on PeopleSnapshot); got {tables}")
    if people_snapshot is None and zju is None:
        raise UserError("give --people-snapshot DIR and/or --zju DIR")
    if subjects:
        unknown = sorted(set(subjects) - set(TABLE1) - set(TABLE2))
        if unknown:
            raise UserError(f"--subjects: unknown subject(s) {', '.join(unknown)}; the paper's are "
                            f"{', '.join(TABLE1)} and ZJU-MoCap {', '.join(TABLE2)}")
    if body.startswith("smpl:"):  # absolute, so the jobs read the same file from any folder
        path = Path(body[5:]).expanduser().resolve()
        if not path.exists():
            raise UserError(f"--body {body}: {path} does not exist (an SMPL .pkl/.npz file, or a folder with "
                            "SMPL_NEUTRAL, SMPL_MALE and SMPL_FEMALE files)")
        body = f"smpl:{path}"
    overrides = {"iters": iters, **({"size": size} if size is not None else {})}
    doc = {"defaults": {"body": body, "splits": ["test"], "overrides": overrides}, "matrix": []}
    if eval_frames is not None:
        doc["defaults"]["eval_frames"] = eval_frames
    ps_variants = (["full"] if 1 in tables else []) + ([v for v in TABLE4 if v != "full"] if 4 in tables else [])
    if 4 in tables and "full" not in ps_variants:
        ps_variants.append("full")
    if people_snapshot is not None and ps_variants:
        wanted = [s for s in TABLE1 if not subjects or s in subjects]
        if wanted:
            root = _folder(people_snapshot, "--people-snapshot")
            missing = [s for s in wanted if not (root / s).is_dir()]
            if missing:
                raise UserError(f"--people-snapshot {root}: no folder for {', '.join(missing)} (the paper uses "
                                f"{', '.join(TABLE1)}; pick some with --subjects)")
            doc["matrix"].append({
                "subjects": [{"name": s, "data": f"peoplesnapshot:{root / s}"} for s in wanted],
                "variants": ps_variants})
    if zju is not None and 2 in tables:
        wanted = [s for s in TABLE2 if not subjects or s in subjects]
        if wanted:
            root = _folder(zju, "--zju")
            found, missing = {}, []
            for s in wanted:
                hits = [root / pattern.format(s) for pattern in ZJU_FOLDERS if (root / pattern.format(s)).is_dir()]
                if hits:
                    found[s] = hits[0]
                else:
                    missing.append(s)
            if missing:
                raise UserError(f"--zju {root}: no CoreView_N or my_N folder for {', '.join(missing)} (the paper "
                                f"uses {', '.join(TABLE2)}; pick some with --subjects)")
            # The ZJU reader converts Rh/Th about the rest pelvis of the body the avatar is trained with.
            doc["matrix"].append({
                "subjects": [{"name": zju_job_subject(s), "data": f"zju:{found[s]}?body={body}"} for s in wanted],
                "variants": ["full"]})
    if not doc["matrix"]:
        raise UserError("nothing to run: the tables and subjects asked for need the other dataset "
                        "(Tables 1 and 4: --people-snapshot; Table 2: --zju)")
    return doc


def _folder(path, option: str) -> Path:
    root = Path(path).expanduser().resolve()
    if not root.is_dir():
        raise UserError(f"{option} {path}: no such folder")
    return root


# ----------------------------------------------------------------------------------------------- tables
def _ours(rows: list[dict], subject: str, variant: str) -> dict | None:
    for r in rows:
        if r["subject"] == subject and r["variant"] == variant and r["split"] == "test" and r["status"] == "ok":
            return r
    return None


def _cell(value, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _row(label: str, ours: tuple | None, paper: tuple) -> str:
    o = ours or (None, None, None)
    return (f"| {label} | {_cell(o[0], 2)} | {paper[0]:.2f} | {_cell(o[1], 3)} | {paper[1]:.3f} | "
            f"{_cell(o[2], 3)} | {paper[2]:.3f} |")


HEADER = ["| {} | PSNR ours | PSNR paper | SSIM ours | SSIM paper | LPIPS ours | LPIPS paper |",
          "|---|---|---|---|---|---|---|"]


def _mean(values: list[tuple]) -> tuple | None:
    if not values:
        return None
    return tuple(sum(v[i] for v in values) / len(values) for i in range(3))


def _metrics(row: dict | None) -> tuple | None:
    if row is None or row["psnr"] is None:
        return None
    return (row["psnr"], row["ssim"], row["lpips"])


def comparison(doc: dict) -> str:
    """Our numbers next to the paper's for each table the batch has rows for (Markdown)."""
    rows = doc["rows"]
    out: list[str] = []
    setting = _setting(doc)
    ps_subjects = [s for s in TABLE1 if any(r["subject"] == s for r in rows)]
    zju_subjects = [s for s in TABLE2 if any(r["subject"] == zju_job_subject(s) for r in rows)]

    def table(title: str, subjects: list[str], paper: dict, to_job) -> None:
        out.extend([f"### {title}", "", HEADER[0].format("subject"), HEADER[1]])
        ours_all = []
        for s in subjects:
            m = _metrics(_ours(rows, to_job(s), "full"))
            out.append(_row(s, m, paper[s]))
            if m is not None:
                ours_all.append(m)
        complete = len(ours_all) == len(subjects)
        out.append(_row(f"mean of {len(subjects)}", _mean(ours_all) if complete else None,
                        _mean([paper[s] for s in subjects])))
        out.append("")

    has_full = any(r["variant"] == "full" for r in rows)
    if ps_subjects and has_full:
        table("Table 1: PeopleSnapshot, test frames", ps_subjects, TABLE1, str)
    if zju_subjects:
        table("Table 2: ZJU-MoCap, test frames", zju_subjects, TABLE2, zju_job_subject)
    ablated = [v for v in TABLE4 if v != "full" and any(r["variant"] == v for r in rows)]
    if ps_subjects and ablated:
        out.extend([f"### Table 4: ablations on PeopleSnapshot (mean over {', '.join(ps_subjects)})", "",
                    HEADER[0].format("variant"), HEADER[1]])
        for v in TABLE4:
            ms = [_metrics(_ours(rows, s, v)) for s in ps_subjects]
            ours = _mean(ms) if all(m is not None for m in ms) else None
            out.append(_row(VARIANT_LABELS[v], ours, TABLE4[v]))
        out += ["", "The paper's Table 4 full model (32.51 dB) is not the mean of its Table 1 (32.46 dB); it does "
                "not say which subjects or frames Table 4 averages. Ours: the mean over the subjects above.", ""]
    if not out:
        return "No job of this batch belongs to the paper's tables.\n"
    failed = [r for r in doc["jobs"] if r["status"] != "ok"]
    notes = [f"Ours: {setting}. A '-' is a job that did not finish"
             + (f" ({', '.join(r['job'] for r in failed)}: see results.md)" if failed else "") + "."]
    return "\n".join(out + notes) + "\n"


def _setting(doc: dict) -> str:
    """The training budget and evaluation setting of the batch's finished jobs, in words."""
    jobs = [r for r in doc["jobs"] if r["status"] == "ok"]
    iters = sorted({r["iterations"] for r in jobs})
    res = sorted({tuple(m["resolution"]) for r in jobs for m in r["splits"].values()})
    bgs = sorted({m["background"] for r in jobs for m in r["splits"].values()})
    partial = any(m["frames"] < m["frames_in_split"] for r in jobs for m in r["splits"].values())
    it = ", ".join(f"{i:,}" for i in iters) or "-"
    rs = ", ".join(f"{w}x{h}" for w, h in res) or "-"
    frames = "ONLY THE FIRST FRAMES of each test split (--eval-frames), " if partial else ""
    return (f"{it} iterations (the paper: {PAPER_ITERS:,}), evaluated at {rs} on a {'/'.join(bgs) or '-'} "
            f"background, full images, {frames}no test-time pose refinement")
