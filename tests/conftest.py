"""Fixtures shared by the test modules. Plain helpers (fixture datasets, motions, SMPL files, cameras,
configs) are in ``helpers.py``; these fixtures hand out the factories and the shared tiny trained run."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch
from helpers import synth_subject, tiny_train_config

from rmavatar.commands import main

TRAINED_RUN_SIZE = 32  # the trained_run's image size
TRAINED_RUN_ITERS = 10


def _seed_global_generators() -> None:
    torch.manual_seed(0)
    np.random.seed(0)
    random.seed(0)


# One process runs every test, so what a test or a fixture draws from the global generators (torch,
# numpy, random) would otherwise depend on which tests ran before it. Each module's fixtures and each
# test start from the same state (pytest sets up a module's fixtures before its tests' autouse ones).
@pytest.fixture(scope="module", autouse=True)
def _same_global_generators_per_module():
    _seed_global_generators()


@pytest.fixture(autouse=True)
def _same_global_generators():
    _seed_global_generators()


@pytest.fixture(scope="session")
def make_train_config():
    """helpers.tiny_train_config: ``make_train_config(data, iters, size=, sh_degree=, ...)`` -> TrainConfig
    with no tensorboard, no densification, on the CPU."""
    return tiny_train_config


@pytest.fixture(scope="session")
def make_synth_subject():
    """helpers.synth_subject: ``make_synth_subject(out, size=, seed=, train=, ...)`` writes
    ``SynthConfig(...)``'s subject to ``out`` without a progress bar and returns the folder."""
    return synth_subject


@pytest.fixture(scope="session")
def tiny_subject(tmp_path_factory):
    """The synthetic subject the trained_run learns (``rmavatar synth``: 32x32, 8 train, 2 test and 2
    novel-pose frames, 1 sample per pixel, seed 0); read-only."""
    root = tmp_path_factory.getbasetemp() / "rmavatar_trained_run"
    subject = root / "subject"
    root.mkdir(exist_ok=True)
    assert main(["synth", str(subject), "--size", str(TRAINED_RUN_SIZE), "--train", "8", "--test", "2",
                 "--novel-pose", "2", "--ss", "1", "--quiet"]) == 0
    return subject


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory, tiny_subject):
    """RUN folder of a tiny avatar trained with the real trainer on tiny_subject (10 iterations at 32x32,
    no densification, SH degree 1, CPU), shared by every module using it; read-only."""
    root = tmp_path_factory.getbasetemp() / "rmavatar_trained_run"
    run = root / "run"
    if (run / "checkpoints" / "last.pt").is_file():
        return run
    from rmavatar.train import train

    cfg = tiny_train_config(tiny_subject, TRAINED_RUN_ITERS, size=TRAINED_RUN_SIZE, sh_degree=1)
    train(cfg, run, progress=False)
    return run
