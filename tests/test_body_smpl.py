"""SMPL from .pkl (python-2 protocol, chumpy stand-ins, old scipy paths) and .npz equals body-models."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.sparse
import torch
from helpers import SMPL_F as F
from helpers import SMPL_V as V
from helpers import random_smpl, save_chumpy_pkl, save_npz

from rmavatar.body import load_body_model
from rmavatar.utils import UserError


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("smpl")
    for nb in (10, 300):
        model = random_smpl(nb, seed=nb)
        save_chumpy_pkl(model, root / f"m{nb}.pkl")
        save_npz(model, root / f"m{nb}.npz")
    return root


def reference(path, betas, go, bp, transl):
    from body_models.smpl.torch import SMPL

    ref = SMPL(model_path=path)
    with torch.no_grad():
        return ref.forward_vertices(
            bp.double().reshape(-1, 23, 3).float(), pelvis_rotation=go, shape=betas, global_translation=transl
        )


@pytest.mark.parametrize("num_betas", [10, 300])
@pytest.mark.parametrize("suffix", ["pkl", "npz"])
def test_forward_equals_body_models(files, num_betas, suffix):
    path = files / f"m{num_betas}.{suffix}"
    body = load_body_model(f"smpl:{path}")
    assert body.num_betas == num_betas and body.faces.shape == (F, 3) and body.v_template.shape == (V, 3)
    gen = torch.Generator().manual_seed(num_betas)
    B = 3
    betas = 2 * torch.randn(B, num_betas, generator=gen)
    go = torch.randn(B, 3, generator=gen)
    bp = 0.5 * torch.randn(B, 69, generator=gen)
    transl = torch.randn(B, 3, generator=gen)
    with torch.no_grad():
        ours = body(betas, go, bp, transl).vertices
    ref = reference(path, betas, go, bp, transl)
    err = (ours - ref).norm(dim=-1).max().item()
    assert err < 1e-5, err


def test_folder_and_gender(tmp_path, files):
    model = random_smpl(10, seed=3)
    save_chumpy_pkl(model, tmp_path / "SMPL_FEMALE.pkl")
    save_npz(random_smpl(10, seed=4), tmp_path / "SMPL_NEUTRAL.npz")
    female = load_body_model(f"smpl:{tmp_path}", gender="female")
    assert female.file.name == "SMPL_FEMALE.pkl"
    assert np.allclose(female.v_template.numpy(), model["v_template"], atol=1e-6)
    assert load_body_model(f"smpl:{tmp_path}").file.name == "SMPL_NEUTRAL.npz"
    # the local rectifier's pose masks read the file's own skinning weights
    np.testing.assert_array_equal(female.joint_weights().numpy(), np.asarray(model["weights"], np.float32))
    with pytest.raises(UserError, match="no male SMPL model"):
        load_body_model(f"smpl:{tmp_path}", gender="male")


class Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo hacked",))


def test_bad_files(tmp_path, files):
    with pytest.raises(UserError, match="does not exist"):
        load_body_model(f"smpl:{tmp_path / 'nope.pkl'}")
    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps({"v_template": Evil()}, protocol=2))
    with pytest.raises(UserError, match=r"evil.pkl is not an SMPL model file: refusing to load class .*system"):
        load_body_model(f"smpl:{evil}")
    notmodel = tmp_path / "list.pkl"
    notmodel.write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(UserError, match="list.pkl is not an SMPL model file"):
        load_body_model(f"smpl:{notmodel}")
    partial = tmp_path / "partial.npz"
    np.savez(partial, v_template=np.zeros((V, 3)))
    with pytest.raises(UserError, match="partial.npz is not an SMPL model file: missing f"):
        load_body_model(f"smpl:{partial}")
    model = random_smpl(10, seed=5)
    model["J_regressor"] = scipy.sparse.csc_matrix(np.zeros((23, V)))
    model["kintree_table"] = model["kintree_table"][:, :23]
    model["weights"] = model["weights"][:, :23]
    wrong = tmp_path / "smplh_like.npz"
    save_npz(model, wrong)
    with pytest.raises(UserError, match="smplh_like.npz is not an SMPL model .*24 joints"):
        load_body_model(f"smpl:{wrong}")


def test_bad_pose_inputs(files):
    body = load_body_model(f"smpl:{files / 'm10.npz'}")
    z3 = torch.zeros(1, 3)
    with pytest.raises(UserError, match=r"body_pose must have shape \[B, 69\].*24 joints"):
        body(None, z3, torch.zeros(1, 72), z3)
    with pytest.raises(UserError, match="global_orient must have shape"):
        body(None, torch.zeros(1, 4), torch.zeros(1, 69), z3)
    bad = torch.zeros(1, 69)
    bad[0, 5] = float("nan")
    with pytest.raises(UserError, match="body_pose contains NaN"):
        body(None, z3, bad, z3)
    with pytest.raises(UserError, match="betas must have shape"):
        body(torch.zeros(1, 11), z3, torch.zeros(1, 69), z3)
