"""Config round trips, CLI overrides, run-folder ownership, checkpoint IO and the small loop helpers."""

import json
import math
import random

import numpy as np
import pytest
import torch

from rmavatar.avatar.run import MARKER, Checkpoint, RunFolder, body_signature, check_body, read_checkpoint
from rmavatar.commands.train import add_arguments, config_from_args
from rmavatar.train import checkpoint as ck
from rmavatar.train.config import TrainConfig, load_config, save_config
from rmavatar.train.optim import position_lr
from rmavatar.render import composite
from rmavatar.train.frames import FrameSampler
from rmavatar.train.report import NonFiniteGuard, finite_flag
from rmavatar.utils import UserError


def test_defaults_are_the_papers():
    c = TrainConfig()
    assert c.optim.adam_eps == 1e-15
    assert (c.optim.lr_position, c.optim.lr_position_final) == (0.008, 1e-5)
    assert (c.optim.lr_scaling, c.optim.lr_rotation, c.optim.lr_opacity) == (0.017, 0.001, 0.05)
    assert (c.optim.lr_color, c.optim.sh_rest_divisor, c.optim.lr_rectifier) == (0.0025, 20.0, 1e-4)
    assert (c.loss.rgb, c.loss.ssim, c.loss.lpips, c.loss.pos, c.loss.scaling, c.loss.offset) == (
        1.5, 0.2, 0.05, 0.01, 1.0, 1.0)
    assert (c.density.start, c.density.every, c.density.stop, c.density.reset_every) == (10_000, 500, 35_000, 5_000)
    assert c.optim.iters == 50_000


def test_yaml_round_trip_and_errors(tmp_path):
    c = TrainConfig()
    c.data.size = 64
    c.model.rectifier = False
    c.loss.offset = 0.0
    c.optim.lr_position_final = 2e-6
    save_config(c, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == c
    (tmp_path / "partial.yaml").write_text("optim:\n  iters: 300\n  lr_position_final: 1e-6\nbackground: black\n")
    p = load_config(tmp_path / "partial.yaml")
    assert p.optim.iters == 300 and p.optim.lr_position_final == 1e-6 and p.background == "black"
    assert p.loss == TrainConfig().loss
    (tmp_path / "bad.yaml").write_text("optim:\n  iterz: 3\n")
    with pytest.raises(UserError, match="iterz"):
        load_config(tmp_path / "bad.yaml")
    (tmp_path / "bad2.yaml").write_text("optim:\n  iters: lots\n")
    with pytest.raises(UserError, match="optim.iters"):
        load_config(tmp_path / "bad2.yaml")
    (tmp_path / "bad3.yaml").write_text("background: green\n")
    with pytest.raises(UserError, match="background"):
        load_config(tmp_path / "bad3.yaml")


def _parse(argv):
    import argparse

    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args(argv)


def test_cli_flags_override_config_file(tmp_path):
    c = TrainConfig()
    c.optim.iters = 123
    c.seed = 5
    save_config(c, tmp_path / "c.yaml")
    args = _parse(["data", "--out", "run", "--config", str(tmp_path / "c.yaml"), "--iters", "77",
                   "--no-rectifier", "--no-offset-loss", "--no-scaling-loss", "--bg", "random", "--size", "64"])
    cfg = config_from_args(args)
    assert cfg.optim.iters == 77 and cfg.seed == 5  # flag wins, file value kept otherwise
    assert cfg.model.rectifier is False and cfg.loss.offset == 0 and cfg.loss.scaling == 0
    assert cfg.background == "random" and cfg.data.size == 64 and cfg.data.path == "data"


def test_position_lr_is_log_linear():
    assert position_lr(0, 100, 0.008, 1e-5) == pytest.approx(0.008)
    assert position_lr(100, 100, 0.008, 1e-5) == pytest.approx(1e-5)
    assert position_lr(50, 100, 0.008, 1e-5) == pytest.approx(math.sqrt(0.008 * 1e-5))


def test_sampler_is_a_seeded_shuffle_and_resumes_exactly():
    s = FrameSampler(7, seed=3)
    seq = [s.next() for _ in range(14)]
    assert sorted(seq[:7]) == list(range(7)) and sorted(seq[7:]) == list(range(7))
    assert seq[:7] != seq[7:]  # a new permutation per epoch
    s2 = FrameSampler(7, seed=3)
    for _ in range(9):
        s2.next()
    s3 = FrameSampler(7, seed=3)
    s3.load_state_dict(s2.state_dict())
    assert [s3.next() for _ in range(5)] == seq[9:14]


def test_target_composite():
    img = torch.rand(4, 5, 3)
    mask = torch.zeros(4, 5)
    mask[1:3, 2:4] = 1.0
    mask[0, 0] = 0.25
    bg = torch.tensor([1.0, 0.5, 0.0])
    t = composite(img, mask, bg)
    assert torch.equal(t[1, 2], img[1, 2])
    assert torch.equal(t[3, 4], bg)
    assert torch.allclose(t[0, 0], 0.25 * img[0, 0] + 0.75 * bg)


def _checkpoint(**fields) -> Checkpoint:
    """A checkpoint of placeholder contents with ``fields`` set."""
    empty = dict(iteration=0, config={}, data_spec="", body={}, betas=None, avatar={}, optimizer={}, density={},
                 sampler={}, rng={}, poses=None, saved_at=0.0)
    return Checkpoint(**{**empty, **fields})


def test_run_dir_ownership(tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    with pytest.raises(UserError, match="someone else"):
        RunFolder(foreign).prepare("/data/a", resume=False)
    assert (foreign / "thesis.tex").read_text() == "precious" and not (foreign / MARKER).exists()
    run = tmp_path / "run"
    with pytest.raises(UserError, match="no run to resume"):
        RunFolder(run).prepare("/data/a", resume=True)
    RunFolder(run).prepare("/data/a", resume=False)
    assert json.loads((run / MARKER).read_text())["data"] == "/data/a"
    RunFolder(run).prepare("/data/a", resume=False)  # no checkpoint yet: starting over is fine
    RunFolder(run).prepare("/data/b", resume=False)  # ... even with other data (a failed start)
    assert json.loads((run / MARKER).read_text())["data"] == "/data/b"
    with pytest.raises(UserError, match="no checkpoint"):
        RunFolder(run).prepare("/data/b", resume=True)
    ck.save_checkpoint(RunFolder(run).checkpoint, _checkpoint(iteration=3))
    with pytest.raises(UserError, match="--resume"):
        RunFolder(run).prepare("/data/b", resume=False)
    with pytest.raises(UserError, match="another dataset"):
        RunFolder(run).prepare("/data/a", resume=False)
    with pytest.raises(UserError, match="another dataset"):
        RunFolder(run).prepare("/data/a", resume=True)
    RunFolder(run).prepare("/data/b", resume=True)


def test_checkpoint_io_and_rng(tmp_path):
    g = torch.Generator().manual_seed(4)
    torch.manual_seed(1)
    np.random.seed(2)
    random.seed(3)
    state = ck.capture_rng(g)
    path = tmp_path / "c" / "last.pt"
    ck.save_checkpoint(path, _checkpoint(iteration=7, rng=state, optimizer={"t": torch.arange(3)}))
    expect = (torch.rand(2), np.random.rand(2), random.random(), torch.rand(2, generator=g))
    torch.manual_seed(9)
    np.random.seed(9)
    random.seed(9)
    g.manual_seed(9)
    loaded = read_checkpoint(path)
    assert loaded.iteration == 7 and torch.equal(loaded.optimizer["t"], torch.arange(3))
    ck.restore_rng(loaded.rng, g)
    got = (torch.rand(2), np.random.rand(2), random.random(), torch.rand(2, generator=g))
    assert torch.equal(got[0], expect[0]) and np.array_equal(got[1], expect[1])
    assert got[2] == expect[2] and torch.equal(got[3], expect[3])
    assert [p.name for p in path.parent.iterdir()] == ["last.pt"]  # no temp files left behind
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match="not a readable"):
        read_checkpoint(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(UserError, match="not an rmavatar checkpoint"):
        read_checkpoint(tmp_path / "other.pt")
    payload = _checkpoint(iteration=2).to_payload()
    del payload["sampler"]
    torch.save(payload, tmp_path / "torn.pt")
    with pytest.raises(UserError, match="incomplete rmavatar checkpoint"):
        read_checkpoint(tmp_path / "torn.pt")


def test_body_signature_mismatch_is_a_clear_error():
    class Body:
        def __init__(self, spec, nv, faces):
            self.spec, self.v_template, self.faces = spec, torch.zeros(nv, 3), faces

    a = Body("anny:female", 4, torch.tensor([[0, 1, 2], [0, 2, 3]]))
    b = Body("smpl:/x", 4, torch.tensor([[0, 1, 2], [1, 2, 3]]))
    check_body(body_signature(a), a, "ckpt")
    with pytest.raises(UserError, match="incompatible"):
        check_body(body_signature(a), b, "ckpt")


@pytest.mark.parametrize("poison", [None, math.nan, math.inf, -math.inf, 3e38])
def test_finite_flag_and_its_float_twin(poison):
    a, b = torch.ones(5), torch.full((2, 3), -2.0)
    if poison is not None:
        b[1, 2] = poison
    if poison == 3e38:  # finite, but the sum overflows: also skipped
        a[:] = 3e38
    ok, bad = finite_flag(a, b, torch.tensor(0.5))
    expect_ok = poison is None
    assert ok.dtype == torch.bool and bool(ok) is expect_ok
    assert bad.dtype == torch.float32 and float(bad) == (0.0 if expect_ok else 1.0)


def test_non_finite_guard_counts_skips_and_the_longest_streak():
    guard = NonFiniteGuard(torch.device("cpu"), max_bad_steps=10)
    pattern = [1, 1, 0, 1, 1, 1, 0, 0, 1]
    for b in pattern:
        guard.update(torch.tensor(float(b)))
    skipped, longest = guard.counters()
    assert float(skipped) == 6 and float(longest) == 3 and float(guard.run) == 1
