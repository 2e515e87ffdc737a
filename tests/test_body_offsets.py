"""Body offsets (a shape fitted to a person: Anny's rest vertices moved along their normals) from the
body model through the native dataset, training and checkpoints to a trained avatar."""

import shutil

import numpy as np
import pytest
import torch

from rmavatar.avatar import load_trained
from rmavatar.avatar.run import RunFolder, load_saved_body
from rmavatar.body import load_body_model
from rmavatar.data import load_dataset
from rmavatar.train import train
from rmavatar.utils import UserError

from helpers import tiny_train_config


@pytest.fixture(scope="module")
def anny():
    return load_body_model("anny")


def _offsets(body, seed=0) -> np.ndarray:
    """Smooth-ish offsets: +2 cm on the upper body, -1 cm below, a little noise."""
    v = body.v_template.numpy()
    noise = np.random.default_rng(seed).normal(0, 0.002, len(v))
    return (np.where(v[:, 1] > 0, 0.02, -0.01) + noise).astype(np.float32)


def test_offsets_move_the_rest_surface_along_its_normals_and_pose_linearly(anny):
    d = _offsets(anny)
    moved = load_body_model("anny", offsets=d)
    shift = moved.rest_vertices - anny.rest_vertices
    torch.testing.assert_close(shift, torch.as_tensor(d)[:, None] * anny.rest_normals)
    assert torch.allclose(anny.rest_normals.norm(dim=-1), torch.ones(len(d)), atol=1e-5)
    # normals point out of the body: the moved mesh's volume grows where d > 0
    gen = torch.Generator().manual_seed(1)
    go, bp, tr = torch.randn(3, 3, generator=gen) * 0.4, torch.randn(3, 69, generator=gen) * 0.3, torch.zeros(3, 3)
    posed, posed_moved = anny(None, go, bp, tr).vertices, moved(None, go, bp, tr).vertices
    direction = anny.offset_directions(go, bp)
    torch.testing.assert_close(posed_moved, posed + torch.as_tensor(d)[None, :, None] * direction,
                               atol=2e-6, rtol=0)
    # the joints do not move: a shape on the same skeleton
    torch.testing.assert_close(moved(None, go, bp, tr).joints, anny(None, go, bp, tr).joints)


def _volume(v: np.ndarray, faces: np.ndarray) -> float:
    tri = v[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6)


def test_positive_offsets_grow_the_body(anny):
    faces = anny.faces.numpy()
    grown = load_body_model("anny", offsets=np.full(anny.v_template.shape[0], 0.01, np.float32))
    assert _volume(grown.v_template.numpy(), faces) > 1.05 * _volume(anny.v_template.numpy(), faces)


@pytest.mark.parametrize("bad, message", [
    (np.zeros(5, np.float32), r"one value per Anny vertex"),
    ("nan", r"finite"),
    ("far", r"within \+-0.3 m"),
])
def test_bad_offsets_are_refused(anny, bad, message):
    n = anny.v_template.shape[0]
    if isinstance(bad, str):
        bad = np.full(n, np.nan if bad == "nan" else 0.5, np.float32)
    with pytest.raises(UserError, match=message):
        load_body_model("anny", offsets=bad)
    with pytest.raises(UserError, match="for the Anny body"):
        load_body_model("smpl:SMPL_NEUTRAL.pkl", offsets=np.zeros(n, np.float32))


@pytest.fixture(scope="module")
def shaped_subject(tmp_path_factory, tiny_subject, anny):
    """tiny_subject with body offsets in its smpl.npz (as a capture writes them)."""
    out = tmp_path_factory.mktemp("shaped") / "subject"
    shutil.copytree(tiny_subject, out)
    with np.load(out / "smpl.npz") as z:
        arrays = dict(z)
    np.savez(out / "smpl.npz", **arrays, body_offsets=_offsets(anny))
    return out


def test_a_dataset_carries_its_offsets_to_its_body(shaped_subject, tiny_subject, anny, capsys):
    ds = load_dataset(str(shaped_subject))
    np.testing.assert_array_equal(ds.body_offsets, _offsets(anny))
    assert load_dataset(str(tiny_subject)).body_offsets is None
    body = ds.body_model()
    torch.testing.assert_close(body.offsets, torch.as_tensor(_offsets(anny)))
    other = ds.body_model("anny:female")  # not the body they were fitted on: left out, said so
    assert other.offsets is None and "body offsets" in capsys.readouterr().out


def test_bad_offsets_in_a_dataset_name_the_file(shaped_subject, tmp_path):
    out = tmp_path / "bad"
    shutil.copytree(shaped_subject, out)
    with np.load(out / "smpl.npz") as z:
        arrays = dict(z)
    arrays["body_offsets"] = arrays["body_offsets"][:, None]
    np.savez(out / "smpl.npz", **arrays)
    with pytest.raises(UserError, match=r"smpl.npz.*'body_offsets' must be \[V\]"):
        load_dataset(str(out))


def test_training_on_offsets_keeps_them_in_the_run(shaped_subject, tmp_path, anny):
    cfg = tiny_train_config(shaped_subject, 2, size=32, sh_degree=0)
    train(cfg, tmp_path / "run", progress=False)
    saved = RunFolder(tmp_path / "run").read_checkpoint().body
    np.testing.assert_array_equal(np.asarray(saved["offsets"]), _offsets(anny))
    trained = load_trained(tmp_path / "run")
    moved = load_body_model("anny", offsets=_offsets(anny))
    torch.testing.assert_close(trained.body.v_template, moved.v_template)
    # the avatar's Gaussians sit on the moved mesh: its rest frames are the moved body's
    assert not torch.allclose(trained.avatar.rest_centroids, load_trained_plain_centroids(anny, trained))
    # a checkpoint with offsets refuses a body without them
    with pytest.raises(UserError, match="with body offsets"):
        load_saved_body({**saved, "offsets": None}, "the run")
    resumed = train(None, tmp_path / "run", resume=True, overrides={"optim.iters": 3}, progress=False)
    assert resumed.iteration == 3


def load_trained_plain_centroids(anny, trained) -> torch.Tensor:
    """The rest centroids the trained avatar's binding faces have on the preset's own shape."""
    tri = anny.v_template[anny.faces[trained.avatar.binding_faces]]
    return tri.mean(1)
