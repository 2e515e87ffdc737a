"""bench quality: each variant flips exactly the switch the paper's ablation names, and a tiny run of two
variants produces a complete, well-formed result and table."""

import json

import pytest

from rmavatar.bench.quality import VARIANTS, format_table, run_quality, variant_config
from rmavatar.commands import main
from rmavatar.train.config import ABLATIONS
from rmavatar.utils import UserError


def test_variants_flip_one_switch_each():
    full = variant_config("full", "d", 64, 10, 0, 0, 1, "cpu")
    assert full.model.rectifier and full.loss.offset == 1.0 and full.loss.scaling == 1.0
    assert not variant_config("no_rectifier", "d", 64, 10, 0, 0, 1, "cpu").model.rectifier
    assert variant_config("no_offset_loss", "d", 64, 10, 0, 0, 1, "cpu").loss.offset == 0.0
    assert variant_config("no_scaling_loss", "d", 64, 10, 0, 0, 1, "cpu").loss.scaling == 0.0
    with pytest.raises(UserError):
        variant_config("w/o everything", "d", 64, 10, 0, 0, 1, "cpu")
    assert set(VARIANTS) == {"full", "no_rectifier", "no_offset_loss", "no_scaling_loss"} == set(ABLATIONS)


def test_tiny_quality_run(tmp_path):
    from rmavatar.data.synth import SynthConfig, synthesize

    data = tmp_path / "data"
    synthesize(data, SynthConfig(size=48, train=6, test=3, novel_pose=3, ss=1), progress=False)
    res = run_quality(tmp_path / "work", ["full", "no_rectifier"], str(data), 48, 8, 0, 0, 1, "cpu",
                      progress=False)
    assert set(res["variants"]) == {"full", "no_rectifier"}
    for row in res["variants"].values():
        assert row["iterations"] == 8 and row["iters_per_second"] > 0 and row["gaussians"] > 1000
        for split in ("test", "novel_pose"):
            assert 5.0 < row[split]["psnr"] < 60.0
    table = format_table(res)
    assert table.count("\n") == 3 and "| no_rectifier |" in table
    json.dumps(res)  # serialisable


def test_unwritable_json_fails_before_training(tmp_path, capsys):
    assert main(["bench", "quality", "--json", str(tmp_path / "missing" / "q.json"), "--work",
                 str(tmp_path / "w")]) == 2
    assert "cannot write --json" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()
