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
from rmavatar.avatar.run import CHECKPOINT_VERSION, RunFolder, read_checkpoint
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
    with lzma.open(FIXTURE / "checkpoints" / "last.pt.xz") as src, open(RunFolder(run).checkpoint, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return run


def test_a_v1_checkpoint_is_migrated(run_v1):
    raw = torch.load(RunFolder(run_v1).checkpoint, map_location="cpu", weights_only=True)
    assert raw["version"] == 1 and "seed" in raw["avatar"]["config"] and "betas" not in raw
    ckpt = read_checkpoint(RunFolder(run_v1).checkpoint)
    assert CHECKPOINT_VERSION == 9
    assert "seed" not in ckpt.avatar["config"] and ckpt.betas is None
    # v2 -> v3: the on/off rectifier switch became the design's name
    assert raw["avatar"]["config"]["rectifier"] is True and raw["config"]["model"]["rectifier"] is True
    assert ckpt.avatar["config"]["rectifier"] == ckpt.config["model"]["rectifier"] == "paper"
    assert ckpt.poses is None  # v3 -> v4: trained without pose refinement
    # v4 -> v5: pose refinement's settings have their own section, as this run was trained (none)
    # (v6 -> v7 and v8 -> v9: and the pose-refinement defaults of then for the settings it lacks)
    assert ckpt.config["poses"] == {"smooth": 0, "fits": (), "first_pass": 0.0, "held_fits": (), "fit_mask": 1.0,
                                    "fit_lr_rotation": 2e-2, "fit_lr_translation": 5e-4, "fit_steps": 30,
                                    "held_fit_steps": 30, "held_fit_scales": (4, 2, 1), "smooth_held": False,
                                    "held_fit_prior": 0.01, "held_fit_anchor": "start"}
    # v5 -> v6: LPIPS on the whole frame, as every run before the person's window was trained
    assert ckpt.config["loss"]["lpips_region"] == "frame" and "lpips_region" not in raw["config"]["loss"]
    # everything else is carried over untouched
    assert ckpt.iteration == raw["iteration"] == 1
    for name, t in raw["avatar"]["state_dict"].items():
        assert torch.equal(ckpt.avatar["state_dict"][name], t), name
    assert ckpt.optimizer["state"].keys() == raw["optimizer"]["state"].keys()


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
    ckpt = read_checkpoint(RunFolder(run_v1).checkpoint)
    assert cfg.model.sh_degree == 0 and cfg.model.rectifier and cfg.optim.iters == 1
    # the old "model" section is a subset of the avatar's config: the rest keeps the defaults it had
    saved = ckpt.avatar["config"]
    for key, value in saved.items():
        got = getattr(cfg.model, key)
        assert (tuple(got) if isinstance(got, (list, tuple)) else got) == \
            (tuple(value) if isinstance(value, (list, tuple)) else value), key


def test_a_checkpoint_from_the_future_is_refused(run_v1, tmp_path):
    payload = torch.load(RunFolder(run_v1).checkpoint, map_location="cpu", weights_only=True)
    payload["version"] = CHECKPOINT_VERSION + 1
    path = tmp_path / "future.pt"
    torch.save(payload, path)
    with pytest.raises(UserError, match="a newer rmavatar wrote it"):
        read_checkpoint(path)


FIXTURE_V4 = Path(__file__).parent / "fixtures" / "run_v4"


def test_a_v4_run_with_pose_refinement_loads_and_resumes_as_that_version_resumed_it(tmp_path):
    """``fixtures/run_v4``: a real run folder made by rmavatar at main 279ac62 (checkpoint version 4, pose
    refinement's settings in "optim") with

        synthesize(DATA, SynthConfig(size=48, seed=0, train=4, test=1, novel_pose=1, ss=1, pose_noise=5.0))
        cfg = TrainConfig(); cfg.data.path = DATA; cfg.data.size = 48; cfg.optim.iters = 2
        cfg.density.enabled = False; cfg.model.sh_degree = 0; cfg.log.tensorboard = False
        cfg.optim.refine_poses = True; cfg.optim.pose_warmup = 0.0; cfg.optim.pose_pass = 0.0
        cfg.optim.pose_sweeps = (); cfg.threads = 1; train(cfg, RUN)

    its checkpoint xz-compressed (the dataset is made again here: the same config makes the same data),
    and ``expected_resume.npz.xz`` what that version's ``train(None, RUN, resume=True, overrides=[(4,
    "optim", "iters")])`` ended with. Today's code migrates it (v4 -> v5), reads its RUN/config.yaml, and
    resumes it to the same values.

    Same values, not same bits: the bits depend on the CPU's code paths (MKL, oneDNN and numba pick
    them per CPU). On the machine that made the expected arrays, today's code gives the same bits; the
    tolerance is a twentieth of what the two resumed steps moved each tensor, tens of times what forcing
    generic (SSE) code paths changes, and far below what a resume that lost the Gaussians' optimiser state or
    the pose corrections would change."""
    import io

    from rmavatar.data.synth import SynthConfig, synthesize
    from rmavatar.train import train

    data = (tmp_path / "data").resolve()
    synthesize(data, SynthConfig(size=48, seed=0, train=4, test=1, novel_pose=1, ss=1, pose_noise=5.0),
               progress=False)
    run = RunFolder(tmp_path / "run")
    shutil.copytree(FIXTURE_V4, run.path, ignore=shutil.ignore_patterns("*.xz"))
    with lzma.open(FIXTURE_V4 / "checkpoints" / "last.pt.xz") as src:
        raw = torch.load(src, map_location="cpu", weights_only=True)
    assert raw["version"] == 4 and raw["config"]["optim"]["refine_poses"] is True
    old = raw["data_spec"]  # the run moves with its data: every place that names it, as written
    raw["data_spec"], raw["config"]["data"]["path"] = str(data), str(data)
    torch.save(raw, run.checkpoint)
    for path in (run.config, run.marker):
        path.write_text(path.read_text().replace(old, str(data)))

    ckpt = run.read_checkpoint()
    assert ckpt.config["poses"]["refine"] is True and "refine_poses" not in ckpt.config["optim"]
    assert ckpt.config["poses"]["held_fit_lr_translation"] == ckpt.config["poses"]["held_fit_lr_rotation"] / 40
    assert load_config(run.config, as_trained=True).poses.refine is True
    trained = load_trained(run.path)
    assert trained.iteration == 2 and trained.training_poses is not None
    train(None, run.path, resume=True, overrides={"optim.iters": 4}, progress=False)
    done = run.read_checkpoint()
    with lzma.open(FIXTURE_V4 / "expected_resume.npz.xz") as src:
        expected = dict(np.load(io.BytesIO(src.read())))
    def compared(avatar: dict, poses: dict) -> dict:
        return {"means": avatar["state_dict"]["means"], "sh_dc": avatar["state_dict"]["sh_dc"], "delta": poses["delta"]}

    start, got = compared(raw["avatar"], raw["poses"]), compared(done.avatar, done.poses)
    assert done.iteration == 4
    for key, value in got.items():
        moved = np.abs(expected[key] - start[key].numpy()).max()
        assert moved > 0, key
        np.testing.assert_allclose(value.numpy(), expected[key], rtol=0, atol=moved / 20, err_msg=key)
