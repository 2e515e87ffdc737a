"""A trained avatar read back from its run folder, including runs written before the checkpoint format
changed: ``fixtures/run_v1`` is a real run folder made by rmavatar 0.1.0 (commit e3ca08c) with

    synthesize(DATA, SynthConfig(size=48, seed=0, train=4, test=1, novel_pose=1, ss=1))
    cfg = TrainConfig(); cfg.data.path = DATA; cfg.data.size = 48; cfg.optim.iters = 1
    cfg.density.enabled = False; cfg.model.sh_degree = 0; cfg.log.tensorboard = False
    train(cfg, RUN)

its checkpoint xz-compressed (the dataset is not kept), and ``expected.npz`` the image that version
rendered of the dataset's first test frame (its pose and camera are stored beside it).
"""

import lzma
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from rmavatar.avatar import load_trained
from rmavatar.avatar.trained import CHECKPOINT_VERSION, checkpoint_path, read_checkpoint
from rmavatar.body import PoseSequence
from rmavatar.render import Camera
from rmavatar.train.config import load_config
from rmavatar.utils import UserError

from devices import DEVICES

FIXTURE = Path(__file__).parent / "fixtures" / "run_v1"


@pytest.fixture(scope="module")
def run_v1(tmp_path_factory):
    run = tmp_path_factory.mktemp("v1") / "run"
    shutil.copytree(FIXTURE, run, ignore=shutil.ignore_patterns("*.xz", "expected.npz"))
    with lzma.open(FIXTURE / "checkpoints" / "last.pt.xz") as src, open(checkpoint_path(run), "wb") as dst:
        shutil.copyfileobj(src, dst)
    return run


def test_a_v1_checkpoint_is_migrated(run_v1):
    raw = torch.load(checkpoint_path(run_v1), map_location="cpu", weights_only=True)
    assert raw["version"] == 1 and "seed" in raw["avatar"]["config"] and "betas" not in raw
    payload = read_checkpoint(checkpoint_path(run_v1))
    assert payload["version"] == CHECKPOINT_VERSION == 4
    assert "seed" not in payload["avatar"]["config"] and payload["betas"] is None
    # v2 -> v3: the on/off rectifier switch became the design's name
    assert raw["avatar"]["config"]["rectifier"] is True and raw["config"]["model"]["rectifier"] is True
    assert payload["avatar"]["config"]["rectifier"] == payload["config"]["model"]["rectifier"] == "paper"
    assert payload["poses"] is None  # v3 -> v4: trained without pose refinement
    # everything else is carried over untouched
    assert payload["iteration"] == raw["iteration"] == 1
    for name, t in raw["avatar"]["state_dict"].items():
        assert torch.equal(payload["avatar"]["state_dict"][name], t), name
    assert payload["optimizer"]["state"].keys() == raw["optimizer"]["state"].keys()


@pytest.mark.parametrize("device", DEVICES)
def test_a_v1_run_renders_the_same_image(run_v1, device):
    expected = np.load(FIXTURE / "expected.npz")
    trained = load_trained(run_v1, device=device)
    assert trained.iteration == 1 and trained.size == 48 and trained.betas is None
    assert trained.training_poses is None
    assert trained.avatar.config.sh_degree == 0 and trained.avatar.rectifier is not None
    poses = PoseSequence.from_arrays(expected["global_orient"], expected["body_pose"], expected["transl"])
    with torch.no_grad():
        gs = trained.avatar(trained.vertices(poses)[0], poses.body_pose[0])  # the avatar's own forward, as eval
    image = trained.render(gs, Camera(expected["K"], expected["viewmat"], 48, 48), (1.0, 1.0, 1.0))
    want = torch.from_numpy(expected["image"])
    assert float((want - 1).abs().max()) > 0.5  # the body is in the picture
    assert image.device.type == device
    # On CUDA gsplat draws it (float32): the image tolerance of tests/test_render.py's gsplat comparison.
    torch.testing.assert_close(image.cpu(), want, atol=1e-6 if device == "cpu" else 1e-4, rtol=0)


def test_a_v1_config_yaml_still_loads(run_v1):
    cfg = load_config(run_v1 / "config.yaml")
    payload = read_checkpoint(checkpoint_path(run_v1))
    assert cfg.model.sh_degree == 0 and cfg.model.rectifier and cfg.optim.iters == 1
    # the old "model" section is a subset of the avatar's config: the rest keeps the defaults it had
    saved = payload["avatar"]["config"]
    for key, value in saved.items():
        got = getattr(cfg.model, key)
        assert (tuple(got) if isinstance(got, (list, tuple)) else got) == \
            (tuple(value) if isinstance(value, (list, tuple)) else value), key


def test_a_checkpoint_from_the_future_is_refused(run_v1, tmp_path):
    payload = torch.load(checkpoint_path(run_v1), map_location="cpu", weights_only=True)
    payload["version"] = CHECKPOINT_VERSION + 1
    path = tmp_path / "future.pt"
    torch.save(payload, path)
    with pytest.raises(UserError, match="a newer rmavatar wrote it"):
        read_checkpoint(path)
