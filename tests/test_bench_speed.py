"""bench speed: a tiny run of the full code path writes a complete report whose ratios are all positive
and finite (no timing assertions: the machine is shared), the reference step's rectifier is the same MLP,
and bad arguments fail before any measuring."""

import json
import math
from types import SimpleNamespace

import torch

from rmavatar.commands import main

STAGES = {"body_forward", "mesh_embedding", "rectifier", "rasterizer_forward", "rasterizer_backward", "losses",
          "optimizer"}


def _ratios(node, path=""):
    """(path, value) of every number whose key names a ratio, anywhere in the report."""
    if isinstance(node, dict):
        for k, v in node.items():
            if "ratio" in k and not isinstance(v, (dict, str)):
                yield f"{path}.{k}", v
            yield from _ratios(v, f"{path}.{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _ratios(v, f"{path}[{i}]")


def test_tiny_speed_run(tmp_path, capsys):
    out = tmp_path / "speed.json"
    rc = main(["bench", "speed", "--json", str(out), "--size", "32", "--gaussians", "500",
               "--render-sizes", "32", "48", "--raster-reference", "100x16", "--render-reference-size", "8",
               "--repeats", "1", "--warmup", "0", "--steps", "1", "--threads", "1"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "training step" in printed and "render 48x48" in printed and "load average" in printed
    rep = json.loads(out.read_text())
    assert rep["benchmark"] == "speed"
    for section in ("rasterizer", "training_step", "rendering"):
        assert rep[section]["time_s"] > 0 and math.isfinite(rep[section]["time_s"])
    ratios = dict(_ratios(rep))
    assert {".rasterizer.ratio", ".rasterizer.ratio_per_gaussian_pixel", ".training_step.ratio",
            ".training_step.rectifier_stage_ratio", ".rendering.ratio"} <= set(ratios)
    for where, value in ratios.items():
        assert isinstance(value, float) and math.isfinite(value) and value > 0, where

    r = rep["rasterizer"]
    assert (r["rmavatar"]["n"], r["rmavatar"]["size"]) == (500, 32)
    assert (r["reference"]["n"], r["reference"]["size"]) == (100, 16) == (
        r["rmavatar_at_reference_config"]["n"], r["rmavatar_at_reference_config"]["size"])

    s = rep["training_step"]
    for variant in (s["rmavatar"], s["reference"]):
        assert set(variant["stages_s"]) == STAGES and variant["size"] == 32 and variant["gaussians"] > 20_000
        assert variant["step_s"] > 0 and len(variant["rounds"]) == 2
        assert all(set(r["stages"]) == STAGES for r in variant["rounds"])

    v = rep["rendering"]
    assert [row["size"] for row in v["rmavatar"]] == [32, 48]
    assert all(row["fps"] > 0 for row in v["rmavatar"])
    assert v["reference"]["size"] == v["rmavatar_at_reference_size"]["size"] == 8
    assert v["gaussians"] > 20_000

    m = rep["machine"]
    assert m["cpu_count"] >= 1 and m["torch"] == torch.__version__ and m["numba"]
    assert m["torch_threads"] == 1
    assert len(m["load_average_start"]) == 3 and len(m["load_average_end"]) == 3


def test_reference_step_uses_the_plain_mlp_with_the_same_weights():
    from rmavatar.avatar import Rectifier
    from rmavatar.bench.speed import _naive_rectifier

    torch.manual_seed(0)
    rect = Rectifier()
    torch.nn.init.normal_(rect.l5.weight, std=0.1)  # non-trivial outputs
    mu, pose = torch.randn(300, 3), torch.randn(69) * 0.3
    fused = rect(mu, pose)
    _naive_rectifier(SimpleNamespace(avatar=SimpleNamespace(rectifier=rect)))
    assert rect.forward == rect.reference_forward
    plain = rect(mu, pose)
    for a, b in zip(fused, plain):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    plain[0].sum().backward()  # trained through autograd
    assert rect.l1.weight.grad is not None


def test_bad_arguments_fail_before_measuring(tmp_path, capsys):
    assert main(["bench", "speed", "--repeats", "0"]) == 2
    assert "--repeats" in capsys.readouterr().err
    assert main(["bench", "speed", "--raster-reference", "lots"]) == 2
    assert "lots" in capsys.readouterr().err
    assert main(["bench", "speed", "--json", str(tmp_path / "missing" / "s.json")]) == 2
    assert "cannot write --json" in capsys.readouterr().err


def test_op_counter_counts_operations_views_and_syncs():
    """The proxy behind `bench step`'s operation and sync counts, on ops whose kind is known: views and
    metadata changes are not operations; a host read, a boolean-mask index and nonzero are syncs; the
    profiler annotations torch.optim wraps around step() are nothing."""
    import torch

    from rmavatar.bench.counting import OpCounter

    a, b = torch.rand(4, 3), torch.rand(4, 3)
    with OpCounter() as c:
        d = a + b
        d.view(12), d.t(), d.detach()
        d.sum().item()
        a[a > 0.5]
        torch.nonzero(a)
    assert (c.ops, c.syncs) == (6, 3)
    assert c.views == 3
    assert set(c.syncs_by_name) == {"aten::_local_scalar_dense", "aten::index.Tensor", "aten::nonzero"}
    p = torch.nn.Parameter(torch.rand(3))
    p.grad = torch.ones(3)
    opt = torch.optim.SGD([p], lr=0.1)
    with OpCounter() as c:
        opt.step()
    assert (c.ops, c.syncs, dict(c.by_name)) == (1, 0, {"aten::add_.Tensor": 1})


def test_tiny_avatar_bench_times_the_default_design_on_anny(capsys, tmp_path):
    """``rmavatar bench avatar`` builds its avatars as training does (the default design is the local
    rectifier, which needs the body's skinning weights: built from a bare mesh it could not run), and
    writes what it prints to ``--json``."""
    out = tmp_path / "avatar.json"
    assert main(["bench", "avatar", "--gaussians", "30000", "--repeats", "1", "--threads", "1",
                 "--json", str(out)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert json.loads(out.read_text()) == rep
    assert rep["body"] == "anny:neutral" and rep["rectifier"] == "local" and rep["gaussians"] == 30000
    for name in ("no_rectifier", "rectifier_float32", "rectifier_bfloat16"):
        assert rep[name]["wall_median_s"] > 0 and math.isfinite(rep[name]["cpu_median_s"]), name
