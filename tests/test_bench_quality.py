"""bench quality: each variant flips exactly the switch the paper's ablation names, a tiny run of two
variants produces a complete, well-formed result and table, and several seeds aggregate to the mean and
sample standard deviation."""

import argparse
import json

import numpy as np
import pytest

from rmavatar.bench.quality import VARIANTS, aggregate, format_table, parse_seeds, run_quality, variant_config
from rmavatar.commands import main
from rmavatar.train.config import ABLATIONS
from rmavatar.utils import UserError


def test_variants_flip_one_switch_each():
    full = variant_config("full", "d", 64, 10, 0, 0, 1, "cpu")
    assert full.model.rectifier and full.loss.offset == 1.0 and full.loss.scaling == 1.0
    assert not variant_config("no_rectifier", "d", 64, 10, 0, 0, 1, "cpu").model.rectifier
    for name, key in (("no_offset_loss", "offset"), ("no_scaling_loss", "scaling")):
        ablated = variant_config(name, "d", 64, 10, 0, 0, 1, "cpu")
        assert getattr(ablated.loss, key) == 0.0 and ablated.model.rectifier == "paper"  # the paper's ablation
    assert full.model.rectifier == "paper"
    local = variant_config("local_rectifier", "d", 64, 10, 0, 0, 1, "cpu")
    assert local.model.rectifier == "local" and local.loss == full.loss
    with pytest.raises(UserError):
        variant_config("w/o everything", "d", 64, 10, 0, 0, 1, "cpu")
    assert set(VARIANTS) == {"full", "no_rectifier", "no_offset_loss", "no_scaling_loss",
                             "local_rectifier"} == set(ABLATIONS)


def test_tiny_quality_run(tmp_path):
    from rmavatar.data.synth import SynthConfig, synthesize

    data = tmp_path / "data"
    synthesize(data, SynthConfig(size=48, train=6, test=3, novel_pose=3, ss=1), progress=False)
    res = run_quality(tmp_path / "work", ["full", "no_rectifier"], str(data), 48, 8, 0, 0, 1, "cpu",
                      progress=False)
    assert set(res["variants"]) == {"full", "no_rectifier"}
    for row in res["runs"]["0"].values():
        assert row["iterations"] == 8 and row["iters_per_second"] > 0 and row["gaussians"] > 1000
        for split in ("test", "novel_pose"):
            assert 5.0 < row[split]["psnr"] < 60.0
    assert res["seeds"] == [0] and set(res["runs"]["0"]) == {"full", "no_rectifier"}
    for name, agg in res["variants"].items():  # one seed: the mean is the run's value, no spread
        assert agg["seeds"] == 1 and agg["test"]["psnr"]["std"] is None
        assert agg["test"]["psnr"]["mean"] == res["runs"]["0"][name]["test"]["psnr"]
    table = format_table(res)
    assert table.count("\n") == 5 and "| no_rectifier |" in table and "±" not in table
    json.dumps(res)  # serialisable


def _row(rng):
    return {"iterations": 10, "train_seconds": float(rng.uniform(10, 20)), "iters_per_second": float(rng.uniform(1, 2)),
            "gaussians": int(rng.integers(1000, 2000)),
            **{split: {"psnr": float(rng.uniform(25, 35)), "ssim": float(rng.uniform(0.9, 1)),
                       "lpips": float(rng.uniform(0, 0.1))} for split in ("test", "novel_pose")}}


def test_aggregate_matches_numpy():
    rng = np.random.default_rng(3)
    runs = {str(s): {"full": _row(rng), "no_rectifier": _row(rng)} for s in (0, 1, 2)}
    del runs["2"]["no_rectifier"]  # a variant missing for one seed is aggregated over the others
    agg = aggregate(runs)
    assert agg["full"]["seeds"] == 3 and agg["no_rectifier"]["seeds"] == 2
    for variant, seeds in (("full", "012"), ("no_rectifier", "01")):
        for split in ("test", "novel_pose"):
            for metric in ("psnr", "ssim", "lpips"):
                values = np.array([runs[s][variant][split][metric] for s in seeds])
                got = agg[variant][split][metric]
                assert got["mean"] == pytest.approx(values.mean(), rel=1e-12)
                assert got["std"] == pytest.approx(values.std(ddof=1), rel=1e-12)
        g = np.array([runs[s][variant]["gaussians"] for s in seeds], float)
        assert agg[variant]["gaussians"]["std"] == pytest.approx(g.std(ddof=1), rel=1e-12)
    table = format_table({"seeds": [0, 1, 2], "variants": agg})
    m, sd = agg["full"]["novel_pose"]["psnr"]["mean"], agg["full"]["novel_pose"]["psnr"]["std"]
    assert f"{m:.2f} ± {sd:.2f}" in table and "over 3" in table


def test_seed_lists():
    assert parse_seeds("0") == [0] and parse_seeds("0,1,2") == [0, 1, 2]
    for bad in ("0,,1", "a", "1,1"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_seeds(bad)


def test_unwritable_json_fails_before_training(tmp_path, capsys):
    assert main(["bench", "quality", "--json", str(tmp_path / "missing" / "q.json"), "--work",
                 str(tmp_path / "w")]) == 2
    assert "cannot write --json" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()
