"""rmavatar batch without Ray: JOBS.yaml parsing and validation, overrides, fingerprints, the results
tables, the paper's numbers (checked against the paper's LaTeX), the reproduce plan, the storage check
and the message when Ray is missing."""

import csv
import json
import re
import sys
from pathlib import Path

import pytest
import yaml

from rmavatar.batch.jobs import load_jobs, parse_jobs
from rmavatar.batch.paper import TABLE1, TABLE2, TABLE4, comparison, paper_jobs
from rmavatar.batch.results import by_variant, rows_of, write_results
from rmavatar.batch.worker import ROOT_MARKER, run_job
from rmavatar.commands import main
from rmavatar.train.config import ABLATIONS, TrainConfig, apply_overrides
from rmavatar.utils import UserError

SEED = Path(__file__).resolve().parents[2] / "shared" / "seed" / "000_cd0819d3a1483dc2.txt"


def jobs_of(text: str, base="/base"):
    return parse_jobs(yaml.safe_load(text), base=base, where="J.yaml")


# --- JOBS.yaml ---------------------------------------------------------------------------------------
def test_matrix_and_jobs_expand_with_overrides_in_order():
    jobs = jobs_of("""
defaults:
  splits: [test, novel_pose]
  overrides: {iters: 100, size: 64, density.max_gaussians: 500, optim: {lr_rectifier: 0.0005}}
matrix:
  subjects:
    - {name: s0, data: d/s0}
    - {name: s1, data: "native:d/s1", body: "anny:female", overrides: {iters: 200}}
  variants:
    - full
    - no_rectifier
    - {name: long, overrides: {iters: 300, seed: 4}, splits: [test]}
jobs:
  - {name: m3c, data: "peoplesnapshot:/abs/m3c?x=1", body: "smpl:models/smpl", overrides: {no_scaling_loss: true}}
""")
    assert [j.name for j in jobs] == ["m3c", "s0-full", "s0-no_rectifier", "s0-long", "s1-full",
                                      "s1-no_rectifier", "s1-long"]
    by = {j.name: j for j in jobs}
    # relative paths are the file's folder's; kind and options survive
    assert by["s0-full"].data == "/base/d/s0" and by["s1-full"].data == "native:/base/d/s1"
    assert by["m3c"].data == "peoplesnapshot:/abs/m3c?x=1" and by["m3c"].body == "smpl:/base/models/smpl"
    assert by["s1-full"].body == "anny:female" and by["s0-full"].body is None
    c = {n: j.config for n, j in by.items()}
    assert c["s0-full"]["optim"]["iters"] == 100 and c["s1-full"]["optim"]["iters"] == 200  # subject wins
    assert c["s1-long"]["optim"]["iters"] == 300 and c["s1-long"]["seed"] == 4  # variant wins over subject
    assert c["s0-full"]["data"]["size"] == 64 and c["s0-full"]["density"]["max_gaussians"] == 500
    assert c["s0-full"]["optim"]["lr_rectifier"] == 0.0005  # nested mappings work too
    assert c["s0-full"]["model"]["rectifier"] and not c["s0-no_rectifier"]["model"]["rectifier"]
    assert c["m3c"]["loss"]["scaling"] == 0.0 and c["m3c"]["loss"]["offset"] == 1.0
    assert by["s0-long"].splits == ["test"] and by["s0-full"].splits == ["test", "novel_pose"]
    assert by["m3c"].splits == ["test", "novel_pose"]  # defaults
    assert (by["s1-long"].subject, by["s1-long"].variant) == ("s1", "long")
    assert (by["m3c"].subject, by["m3c"].variant) == ("m3c", "default")
    assert c["s0-full"]["data"]["path"] == "/base/d/s0"


def test_bare_variants_are_the_papers_ablations():
    jobs = jobs_of("matrix: {subjects: [{name: a, data: x}], variants: [full, no_rectifier, no_offset_loss, "
                   "no_scaling_loss]}")
    for job in jobs:
        want = apply_overrides(TrainConfig(), ABLATIONS[job.variant])
        assert job.config["model"] == {**want.model.__dict__}
        assert job.config["loss"] == {**want.loss.__dict__}
    assert len({j.fingerprint() for j in jobs}) == 4


def test_fingerprint_ignores_runtime_settings_only():
    base = "jobs: [{name: a, data: x, overrides: {%s}}]"
    fp = lambda o: jobs_of(base % o)[0].fingerprint()  # noqa: E731
    assert fp("") == fp("log.checkpoint_every: 7") == fp("log.tensorboard: false")
    assert fp("") != fp("iters: 10") and fp("") != fp("no_offset_loss: true")
    a, b = jobs_of("jobs: [{name: a, data: x, splits: [test]}]")[0], jobs_of(
        "jobs: [{name: a, data: x, splits: [test, novel_pose]}]")[0]
    assert a.fingerprint() != b.fingerprint()
    assert a.fingerprint() != jobs_of("jobs: [{name: a, data: x, eval_frames: 3}]")[0].fingerprint()


def test_yaml_entry_reads_back_as_the_same_job(tmp_path):
    jobs = jobs_of("""
defaults: {overrides: {iters: 12, loss.offset: 0.5}, eval_frames: 3}
matrix: {subjects: [{name: s, data: d, body: anny}], variants: [no_rectifier]}
""")
    (tmp_path / "again.yaml").write_text(yaml.safe_dump({"jobs": [j.yaml_entry() for j in jobs]}))
    again = load_jobs(tmp_path / "again.yaml")
    assert [(j.name, j.subject, j.variant, j.data, j.body, j.splits, j.eval_frames, j.config) for j in again] == \
        [(j.name, j.subject, j.variant, j.data, j.body, j.splits, 3, j.config) for j in jobs]
    assert again[0].fingerprint() == jobs[0].fingerprint()


@pytest.mark.parametrize("text, match", [
    ("[1, 2]", "expected a mapping with jobs"),
    ("{}", "no jobs"),
    ("jobz: []", r"unknown key\(s\) jobz"),
    ("jobs: [{data: x}]", r"jobs\[0\]: name must be"),
    ("jobs: [{name: a}]", "job 'a': data: must be a dataset spec"),
    ("jobs: [{name: 'a b', data: x}]", "name must be"),
    ("jobs: [{name: results.md, data: x}]", "name must be"),
    ("jobs: [{name: a, data: x}, {name: a, data: y}]", "name 'a' is used twice"),
    ("jobs: [{name: a, data: x, splits: []}]", "splits: must be a non-empty list"),
    ("jobs: [{name: a, data: x, splits: [test, test]}]", "distinct split names"),
    ("jobs: [{name: a, data: x, eval_frames: 0}]", "eval_frames: must be a whole number >= 1"),
    ("defaults: {eval_frames: two}\njobs: [{name: a, data: x}]", "eval_frames: must be a whole number"),
    ("jobs: [{name: a, data: x, body: smplx:m}]", "body: must be anny"),
    ("jobs: [{name: a, data: x, color: red}]", r"job 'a': unknown key\(s\) color"),
    ("jobs: [{name: a, data: x, overrides: {optim.iterz: 3}}]", r"job 'a': overrides.optim: unknown key\(s\) iterz"),
    ("jobs: [{name: a, data: x, overrides: {optm.iters: 3}}]", "job 'a': overrides: unknown key 'optm.iters'"),
    ("jobs: [{name: a, data: x, overrides: {iters: lots}}]", "job 'a': overrides.optim.iters: expected an integer"),
    ("jobs: [{name: a, data: x, overrides: {iters: 0}}]", r"job 'a': optim.iters \(--iters\) must be >= 1"),
    ("jobs: [{name: a, data: x, overrides: {no_rectifier: 1}}]", "overrides.no_rectifier: expected true/false"),
    ("jobs: [{name: a, data: x, overrides: {optim: 3}}]", "'optim' is a config section"),
    ("jobs: [{name: a, data: x, overrides: {device: cuda}}]", "overrides.device: set by the batch"),
    ("jobs: [{name: a, data: x, overrides: {threads: 4}}]", "set by the batch, not an override: use --cpus"),
    ("jobs: [{name: a, data: x, overrides: {model.body: anny}}]", "use the job's body: field"),
    ("matrix: {subjects: [{name: s, data: x}], variants: [w/o everything]}", "unknown variant 'w/o everything'"),
    ("matrix: {subjects: [], variants: [full]}", "subjects: must be a non-empty list"),
    ("matrix: {subjects: [{name: s, data: x}], variants: [{overrides: {}}]}", r"variants\[0\]: a variant needs a name"),
    ("matrix: {subjects: [{name: s, data: x, overrides: {loss.offset: -1}}]}",
     "job 's-default' .*loss.offset must be >= 0"),
])
def test_bad_jobs_files_name_the_job_and_key(text, match):
    with pytest.raises(UserError, match=match):
        jobs_of(text)


def test_load_jobs_file_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_jobs(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("jobs: [\n")
    with pytest.raises(UserError, match="not valid YAML"):
        load_jobs(tmp_path / "bad.yaml")


def test_batch_command_validates_before_anything_runs(tmp_path, capsys):
    (tmp_path / "j.yaml").write_text("jobs: [{name: a, data: x}, {name: b, data: y, overrides: {iterz: 1}}]\n")
    assert main(["batch", str(tmp_path / "j.yaml"), "--out", str(tmp_path / "root")]) == 2
    err = capsys.readouterr().err
    assert "job 'b'" in err and "iterz" in err and "Traceback" not in err
    assert not (tmp_path / "root").exists()


def test_missing_ray_says_what_to_install(tmp_path, capsys, monkeypatch):
    (tmp_path / "j.yaml").write_text("jobs: [{name: a, data: x}]\n")
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    assert main(["batch", str(tmp_path / "j.yaml"), "--out", str(tmp_path / "root")]) == 2
    assert "pip install 'rmavatar[cluster]'" in capsys.readouterr().err
    assert not (tmp_path / "root").exists()


def test_a_foreign_root_is_refused(tmp_path, capsys):
    (tmp_path / "j.yaml").write_text("jobs: [{name: a, data: x}]\n")
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "mine.txt").write_text("keep me")
    assert main(["batch", str(tmp_path / "j.yaml"), "--out", str(tmp_path / "root")]) == 2
    assert "holds no rmavatar batch" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "root").iterdir()) == ["mine.txt"]


# --- the storage contract ------------------------------------------------------------------------------
def test_a_worker_that_cannot_see_root_fails_the_job_and_writes_nothing(tmp_path):
    job = jobs_of("jobs: [{name: a, data: x}]")[0].to_dict()
    root = tmp_path / "root"
    root.mkdir()
    (root / ROOT_MARKER).write_text(json.dumps({"format": "rmavatar-batch", "session": "other"}))
    res = run_job(job, str(root), "mine", 1, 1, "cpu")
    assert res["status"] == "failed" and "not visible on node" in res["error"]
    assert "filesystem every node mounts at the same path" in res["error"]
    assert sorted(p.name for p in root.iterdir()) == [ROOT_MARKER]
    res = run_job(job, str(tmp_path / "nowhere"), "mine", 1, 1, "cpu")
    assert res["status"] == "failed" and "not visible" in res["error"]
    assert not (tmp_path / "nowhere").exists()


# --- results tables ------------------------------------------------------------------------------------
def _result(job, variant, status="ok", psnr=30.0, splits=("test",), **kw):
    base = {"job": job, "subject": job.split("-")[0], "variant": variant, "status": status, "attempts": 1,
            "error": None if status == "ok" else "boom | bad", "iterations": 100 if status == "ok" else None,
            "gaussians": 1000, "train_seconds": 10.0, "eval_seconds": 1.0, **kw}
    if status == "ok":
        base["splits"] = {s: {"psnr": psnr + i, "ssim": 0.9, "lpips": 0.1, "frames": 5, "frames_in_split": 5,
                              "resolution": [64, 64],
                              "background": "white"} for i, s in enumerate(splits)}
    return base


def test_results_rows_means_and_files(tmp_path):
    results = [_result("a-full", "full", psnr=30.0, splits=("test", "novel_pose")),
               _result("b-full", "full", psnr=32.0, splits=("test", "novel_pose")),
               _result("a-norect", "norect", psnr=29.0), _result("c-norect", "norect", status="failed")]
    rows = rows_of(results)
    assert [(r["job"], r["split"]) for r in rows] == [("a-full", "test"), ("a-full", "novel_pose"),
                                                     ("b-full", "test"), ("b-full", "novel_pose"),
                                                     ("a-norect", "test"), ("c-norect", None)]
    means = {(g["variant"], g["split"]): g for g in by_variant(rows)}
    assert means[("full", "test")]["psnr"] == pytest.approx(31.0) and means[("full", "test")]["jobs"] == 2
    assert means[("full", "novel_pose")]["psnr"] == pytest.approx(32.0)
    assert means[("norect", "test")]["jobs"] == 1  # the failed job is not in the mean
    doc = write_results(tmp_path, results, {"wall_seconds": 12.0, "ran": 4, "skipped": 0})
    with open(tmp_path / "results.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 6 and table[5]["status"] == "failed" and table[5]["error"] == "boom | bad"
    assert float(table[0]["psnr"]) == 30.0
    assert json.loads((tmp_path / "results.json").read_text())["rows"] == doc["rows"]
    md = (tmp_path / "results.md").read_text()
    assert "| c-norect | - | failed (see below) |" in md and "- **c-norect**: boom | bad" in md
    assert "| full | test | 2 | 31.00 |" in md and "12 s" in md


# --- the paper -----------------------------------------------------------------------------------------
def _latex_rows(tex: str, label: str) -> list[list[str]]:
    """The data rows (cells) of the LaTeX table labelled ``label``."""
    start = tex.rindex(r"\begin{tabular}", 0, tex.index(f"\\label{{{label}}}"))
    body = tex[start:tex.index(r"\end{tabular}", start)]
    body = re.sub(r"\\textbf\{([^}]*)\}", r"\1", body)
    body = re.sub(r"\\(toprule|midrule|bottomrule)", "", body)
    rows = []
    for line in body.replace(r"\hline", r"\\").split(r"\\"):
        cells = [c.strip() for c in line.replace("\n", " ").split("&")]
        if len(cells) > 1 and re.fullmatch(r"[\d.]+(-\d+)?", cells[-1]):
            rows.append(cells)
    return rows


def test_paper_numbers_are_the_papers_latex():
    if not SEED.is_file():
        pytest.skip(f"the paper's LaTeX is not at {SEED}")
    tex = SEED.read_text()
    ours = {r[0]: [float(x) for x in r[1:]] for r in _latex_rows(tex, "tab:exp_people")}["Ours"]
    assert ours == [v for s in ("male-3-casual", "male-4-casual", "female-3-casual", "female-4-casual")
                    for v in TABLE1[s]]
    ours = {r[0]: [float(x) for x in r[1:]] for r in _latex_rows(tex, "tab:exp_zju")}["Ours"]
    assert ours == [v for s in ("377", "386", "387", "392", "393", "394") for v in TABLE2[s]]
    rows = {r[0]: tuple(float(x) for x in r[1:]) for r in _latex_rows(tex, "tab:ablation")}
    assert rows == {"w/o GauRec": TABLE4["no_rectifier"], "w/o OffsetLoss": TABLE4["no_offset_loss"],
                    "w/o ScalingLoss": TABLE4["no_scaling_loss"], "Full model": TABLE4["full"]}
    assert "trained for 50,000 iterations" in tex
    # the subjects and splits we run are the paper's Table 3 split (rmavatar.data.zju.SPLITS)
    from rmavatar.data.zju import SPLITS

    split_rows = _latex_rows(tex.replace("|", "&"), "tab:zju_split")
    table3 = {}
    for r in split_rows:
        for i in range(0, len(r), 3):
            table3[r[i]] = (r[i + 1], r[i + 2])
    assert {s: (f"1-{a}", f"{a + 1}-{b}") for s, (a, b) in SPLITS.items()} == table3


def _dataset_folders(tmp_path):
    ps, zju = tmp_path / "ps", tmp_path / "zju"
    for s in TABLE1:
        (ps / s).mkdir(parents=True)
    for s in TABLE2:
        (zju / (f"my_{s}" if s == "394" else f"CoreView_{s}")).mkdir(parents=True)
    (tmp_path / "SMPL_NEUTRAL.npz").write_bytes(b"")
    return ps, zju


def test_reproduce_plan_is_the_papers(tmp_path):
    ps, zju = _dataset_folders(tmp_path)
    body = f"smpl:{tmp_path / 'SMPL_NEUTRAL.npz'}"
    jobs = parse_jobs(paper_jobs(ps, zju, body))
    assert len(jobs) == 4 * 4 + 6
    for job in jobs:
        assert job.config["optim"]["iters"] == 50_000 and job.splits == ["test"] and job.body == body
        assert job.config["data"]["size"] is None
        assert job.config == parse_jobs({"jobs": [job.yaml_entry()]})[0].config
    by = {j.name: j for j in jobs}
    assert set(by) == {f"{s}-{v}" for s in TABLE1 for v in TABLE4} | {f"zju-{s}-full" for s in TABLE2}
    assert by["zju-394-full"].data == f"zju:{zju / 'my_394'}?body={body}"
    assert by["male-3-casual-no_rectifier"].data == f"peoplesnapshot:{ps / 'male-3-casual'}"
    assert not by["female-4-casual-no_rectifier"].config["model"]["rectifier"]
    assert by["female-4-casual-no_offset_loss"].config["loss"]["offset"] == 0.0
    assert by["female-4-casual-no_scaling_loss"].config["loss"]["scaling"] == 0.0
    # one dataset alone, some tables, some subjects, a budget
    only = parse_jobs(paper_jobs(None, zju, "anny", iters=7, size=64, subjects=["377", "392"]))
    assert [j.name for j in only] == ["zju-377-full", "zju-392-full"]
    assert only[0].config["optim"]["iters"] == 7 and only[0].config["data"]["size"] == 64
    assert only[0].eval_frames is None and jobs[0].eval_frames is None
    assert parse_jobs(paper_jobs(None, zju, "anny", eval_frames=5))[0].eval_frames == 5
    t1 = parse_jobs(paper_jobs(ps, zju, "anny", tables=[1]))
    assert [j.name for j in t1] == [f"{s}-full" for s in TABLE1]
    t4 = parse_jobs(paper_jobs(ps, None, "anny", tables=[4], subjects=["male-4-casual"]))
    assert [j.variant for j in t4] == ["no_rectifier", "no_offset_loss", "no_scaling_loss", "full"]


@pytest.mark.parametrize("kwargs, match", [
    ({"people_snapshot": None, "zju": None}, "give --people-snapshot"),
    ({"tables": [3]}, "tables are 1"),
    ({"subjects": ["male-9"]}, "unknown subject"),
    ({"body": "smpl:/nowhere/smpl"}, "does not exist"),
    ({"zju": None, "tables": [2]}, "nothing to run"),
])
def test_reproduce_plan_errors(tmp_path, kwargs, match):
    ps, zju = _dataset_folders(tmp_path)
    args = {"people_snapshot": ps, "zju": zju, "body": "anny", **kwargs}
    with pytest.raises(UserError, match=match):
        paper_jobs(args.pop("people_snapshot"), args.pop("zju"), args.pop("body"), **args)
    (ps / "male-4-casual").rmdir()
    with pytest.raises(UserError, match="no folder for male-4-casual"):
        paper_jobs(ps, None, "anny")


def test_comparison_pairs_our_numbers_with_the_papers():
    def res(subject, variant, psnr, status="ok"):
        r = _result(f"{subject}-{variant}", variant, status=status, psnr=psnr)
        r["subject"] = subject
        return r

    results = [res(s, v, 30.0 + i + 0.5 * j) for i, s in enumerate(["male-3-casual", "male-4-casual"])
               for j, v in enumerate(TABLE4)]
    results += [res("zju-377", "full", 29.0), res("zju-386", "full", 0, status="failed")]
    doc = {"rows": rows_of(results), "jobs": results}
    text = comparison(doc)
    assert "### Table 1" in text and "### Table 2" in text and "### Table 4" in text
    full = {r["subject"]: r["psnr"] for r in doc["rows"] if r["variant"] == "full"}
    assert f"| male-3-casual | {full['male-3-casual']:.2f} | 34.12 | 0.900 | 0.985 | 0.100 | 0.013 |" in text
    assert "| mean of 2 | " in text and f"| {(34.12 + 31.23) / 2:.2f} |" in text
    assert "| 377 | 29.00 | 32.68 |" in text and "| 386 | - | 30.61 |" in text
    assert "| mean of 2 | - |" in text  # ZJU: one job failed, no mean of ours
    norect = (30.0 + 31.0) / 2  # variant index 0 on both subjects
    assert f"| w/o GauRec | {norect:.2f} | 31.92 |" in text
    assert "zju-386-full" in text  # named as not finished
    assert "100 iterations (the paper: 50,000)" in text and "64x64" in text
