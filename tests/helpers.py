"""Helpers shared by several test modules (not a test module: pytest collects nothing here).

Test modules import from here (``from helpers import ...``; pytest puts tests/ on sys.path), never from
one another. The fixtures built on these are in ``conftest.py``.

- fixture datasets in the PeopleSnapshot and ZJU-MoCap layouts (``make_peoplesnapshot``, ``make_zju``,
  ``add_zju_frame``), drawing from the one shared generator ``RNG``;
- a random model with SMPL's array shapes (``random_smpl``) and its ``.npz`` file (``save_npz``);
- a motion that swings the arms and walks (``dance``);
- the fixed camera of the tiny native datasets (``front_camera``);
- a tiny synthetic subject (``synth_subject``) and a tiny training config (``tiny_train_config``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image

# One generator for test_data.py and the fixture-dataset helpers below (betas of make_peoplesnapshot):
# they draw from it in turn, as they did when both lived in test_data.py.
RNG = np.random.default_rng(0)

SMPL_V, SMPL_F = 6890, 13776  # SMPL's vertex and face counts


# ----------------------------------------------------------------------------------------------- small tools
def rodrigues(r):
    """Axis-angle [3] -> rotation matrix [3,3], written out (independent of scipy)."""
    r = np.asarray(r, np.float64)
    theta = np.linalg.norm(r)
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * Kx @ Kx


def save_png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


# ----------------------------------------------------------------------------------------------- PeopleSnapshot
def make_peoplesnapshot(root, frames_by_split, size=(6, 4), mask_kind="npy", total=None):
    """A subject folder in InstantAvatar's layout; returns per-split betas."""
    w, h = size
    root.mkdir(parents=True)
    K = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=np.eye(4), height=h, width=w)
    frames = sorted({i for f in frames_by_split.values() for i in f}) if total is None else range(total)
    for i in frames:
        img = np.full((h, w, 3), i % 256, np.uint8)
        save_png(root / "images" / f"image_{i:04d}.png", img)
        m = np.zeros((h, w), np.uint8)
        m[:, : w // 2] = 1
        if mask_kind == "npy":
            (root / "masks").mkdir(exist_ok=True)
            np.save(root / "masks" / f"mask_{i:04d}.npy", m)
        else:
            soft = m * 255
            soft[0, 0] = 128
            save_png(root / "masks" / f"mask_{i:04d}.png", soft)
    (root / "poses").mkdir()
    betas = {}
    for split, fr in frames_by_split.items():
        n = len(fr)
        betas[split] = RNG.normal(size=(1, 10)).astype(np.float32)
        transl = np.zeros((n, 3), np.float32)
        transl[:, 0] = fr  # the frame number, to check the row order
        np.savez(root / "poses" / f"anim_nerf_{split}.npz", betas=betas[split],
                 global_orient=np.tile([math.pi, 0, 0], (n, 1)), body_pose=np.zeros((n, 69)), transl=transl)
    return betas


# ----------------------------------------------------------------------------------------------- ZJU-MoCap
def make_zju(root, num_frames, w=8, h=6, D=None, n_cams=2):
    root.mkdir(parents=True)
    Ks = [np.array([[40.0 + c, 0, w / 2], [0, 40.0 + c, h / 2], [0, 0, 1]]) for c in range(n_cams)]
    Rs = [rodrigues([0, 0.3 * c, 0]) for c in range(n_cams)]
    Ts = [np.array([[100.0 * c], [-200.0], [3000.0]]) for c in range(n_cams)]  # millimetres
    Ds = [np.zeros((5, 1)) if D is None else np.asarray(D, float).reshape(5, 1) for _ in range(n_cams)]
    ims = []
    for i in range(num_frames):
        paths = [f"Camera_B{c + 1}/{i:06d}.jpg" for c in range(n_cams)]
        ims.append({"ims": np.array(paths)})
    np.save(root / "annots.npy", {"cams": {"K": Ks, "D": Ds, "R": Rs, "T": Ts}, "ims": np.array(ims)},
            allow_pickle=True)
    (root / "new_params").mkdir()
    return Ks, Rs, Ts


def add_zju_frame(root, i, w=8, h=6, n_cams=2, image=None, cams=None):
    for c in range(n_cams) if cams is None else cams:
        img = np.full((h, w, 3), 200, np.uint8) if image is None else image
        p = root / f"Camera_B{c + 1}" / f"{i:06d}.jpg"
        p.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(p, quality=95)
        m1 = np.zeros((h, w), np.uint8)
        m1[:, : w // 2] = 1  # mask/: left half, label 1
        m2 = np.zeros((h, w), np.uint8)
        m2[: h // 2] = 255  # mask_cihp/: top half, label 255
        save_png(root / "mask" / f"Camera_B{c + 1}" / f"{i:06d}.png", m1)
        save_png(root / "mask_cihp" / f"Camera_B{c + 1}" / f"{i:06d}.png", m2)
    np.save(root / "new_params" / f"{i}.npy", {
        "poses": np.concatenate([[0, 0, 0], np.full(69, 0.01 * i)])[None],
        "Rh": np.array([[0.1 * i, 0.2, 0.0]]), "Th": np.array([[0.0, 0.5, float(i)]]),
        "shapes": np.full((1, 10), 0.1)}, allow_pickle=True)


# ----------------------------------------------------------------------------------------------- SMPL files
def random_smpl(num_betas: int, seed: int) -> dict:
    """A random model with SMPL's array shapes and sparsity (weights on <= 4 joints, sparse regressor)."""
    import scipy.sparse

    from rmavatar.body.base import SMPL_PARENTS

    V, F = SMPL_V, SMPL_F
    rng = np.random.default_rng(seed)
    parents = np.array(SMPL_PARENTS, dtype=np.int64)
    joints = np.zeros((24, 3))
    for j in range(1, 24):
        joints[j] = joints[parents[j]] + rng.normal(0, 0.15, 3)
    owner = rng.integers(0, 24, V)
    v_template = joints[owner] + rng.normal(0, 0.05, (V, 3))
    weights = np.zeros((V, 24))
    rows = np.arange(V)[:, None]
    others = np.stack([owner, np.maximum(parents[owner], 0), *rng.integers(0, 24, (2, V))], 1)  # <= 4 joints
    weights[rows, others] = rng.random((V, 4))
    weights /= weights.sum(1, keepdims=True)
    J_regressor = np.zeros((24, V))
    for j in range(24):
        idx = rng.choice(np.nonzero(owner == j)[0], 20, replace=False)
        w = rng.random(20)
        J_regressor[j, idx] = w / w.sum()
    kintree = np.stack([parents, np.arange(24)]).astype(np.uint32)
    kintree[0, 0] = 4294967295  # as in the official files
    return {
        "v_template": v_template,
        "f": rng.integers(0, V, (F, 3)).astype(np.uint32),
        "shapedirs": rng.normal(0, 0.01, (V, 3, num_betas)),
        "posedirs": rng.normal(0, 0.01, (V, 3, 207)),
        "J_regressor": scipy.sparse.csc_matrix(J_regressor),
        "weights": weights,
        "kintree_table": kintree,
        "bs_type": "lrotmin",
        "bs_style": "lbs",
    }


def save_npz(model: dict, path) -> None:
    arrays = {k: v for k, v in model.items() if not isinstance(v, str)}
    arrays["J_regressor"] = model["J_regressor"].toarray()
    np.savez(path, **arrays)


# ----------------------------------------------------------------------------------------------- motion
def dance(n=6, drift=3.0):
    """A y-up motion (AIST++ layout: poses (N,72), trans) that swings the arms and walks ``drift`` m."""
    t = np.arange(n) / n
    poses = np.zeros((n, 72), np.float32)
    poses[:, 1] = 1.2  # turned away from +z
    poses[:, 16 * 3 + 2] = -0.3 - 0.8 * np.sin(2 * np.pi * t)
    poses[:, 17 * 3 + 2] = 0.3 + 0.8 * np.sin(2 * np.pi * t)
    poses[:, 1 * 3] = 0.6 * np.sin(2 * np.pi * t)
    trans = np.stack([drift * t, 0.9 + 0.0 * t, 0.5 * drift * t], 1).astype(np.float32)
    return poses, trans


# ----------------------------------------------------------------------------------------------- tiny datasets and runs
def front_camera(size: int, fx: float, cx: float | None = None) -> dict:
    """One fixed camera looking at the Anny body (SMPL axes: y up, facing +z) from 3.2 m in front, for
    square ``size`` images: {"K", "viewmat"} as float32, principal point (cx, size / 2), cx default size / 2."""
    viewmat = np.diag([1.0, -1.0, -1.0, 1.0]).astype(np.float32)  # camera looks along world -z
    viewmat[:3, 3] = -viewmat[:3, :3] @ np.array([0.0, -0.4, 3.2], np.float32)
    cx = size / 2 if cx is None else cx
    K = np.array([[fx, 0, cx], [0, fx, size / 2], [0, 0, 1]], np.float32)
    return {"K": K, "viewmat": viewmat}


def synth_subject(out, **config) -> Path:
    """The synthetic subject of ``SynthConfig(**config)`` written to ``out`` (no progress bar); returns out."""
    from rmavatar.data.synth import SynthConfig, synthesize

    synthesize(out, SynthConfig(**config), progress=False)
    return Path(out)


def tiny_train_config(data, iters: int, *, size: int | None = None, sh_degree: int | None = None,
                      density: bool | None = False, device: str | None = "cpu", threads: int | None = None,
                      preview_every: int | None = None):
    """A TrainConfig for a short test run on ``data``: ``iters`` iterations, no tensorboard, by default no
    densification and on the CPU. Each of size (data.size), sh_degree (model.sh_degree), density
    (density.enabled), device, threads and preview_every (log.preview_every) is set only when not None,
    else TrainConfig's default stays."""
    from rmavatar.train import TrainConfig

    cfg = TrainConfig()
    cfg.data.path = str(data)
    if size is not None:
        cfg.data.size = size
    cfg.optim.iters = iters
    if density is not None:
        cfg.density.enabled = density
    cfg.log.tensorboard = False
    if preview_every is not None:
        cfg.log.preview_every = preview_every
    if sh_degree is not None:
        cfg.model.sh_degree = sh_degree
    if threads is not None:
        cfg.threads = threads
    if device is not None:
        cfg.device = device
    return cfg


# ----------------------------------------------------------------------------------------------- SMPL-H / SMPL-X files
# The official kinematic trees, written out (not taken from rmavatar): SMPL's first 22 joints, then
# SMPL-H's two hands (15 joints each, MANO order) or SMPL-X's jaw, eyes and two hands.
SMPLH_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19,
                 20, 22, 23, 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35,
                 21, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50)  # fmt: skip
SMPLX_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
                 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
                 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53)  # fmt: skip


def random_smplx(kind: str, num_components: int, seed: int, per_joint: int = 20, hands_mean: bool = True) -> dict:
    """A tiny random SMPL-H (``kind`` "smplh", 52 joints) or SMPL-X ("smplx", 55) model with the official
    files' keys: ``per_joint`` vertices per joint, each following its joint with weight > 0.5 (and up to
    three others a little), ``num_components`` shapedirs columns (SMPL-X: shape then expression),
    ``hands_meanl/r`` and ``hands_componentsl/r`` (unless not ``hands_mean``), SMPL-X's ``joint2num``."""
    import scipy.sparse

    parents = np.array(SMPLH_PARENTS if kind == "smplh" else SMPLX_PARENTS, dtype=np.int64)
    J = len(parents)
    V = J * per_joint
    rng = np.random.default_rng(seed)
    joints = np.zeros((J, 3))
    for j in range(1, J):
        joints[j] = joints[parents[j]] + rng.normal(0, 0.15 if j < 22 else 0.03, 3)
    owner = np.repeat(np.arange(J), per_joint)
    v_template = joints[owner] + rng.normal(0, 0.02, (V, 3))
    weights = np.zeros((V, J))
    rows = np.arange(V)[:, None]
    others = np.stack([np.maximum(parents[owner], 0), *rng.integers(0, J, (2, V))], 1)
    weights[rows, others] = rng.random((V, 3))
    weights[np.arange(V), owner] = 3.0 + rng.random(V)  # more than the three others together: > 0.5
    weights /= weights.sum(1, keepdims=True)
    J_regressor = np.zeros((J, V))
    for j in range(J):
        w = rng.random(10)
        J_regressor[j, j * per_joint : j * per_joint + 10] = w / w.sum()
    kintree = np.stack([parents, np.arange(J)]).astype(np.uint32)
    kintree[0, 0] = 4294967295
    model = {
        "v_template": v_template,
        "f": rng.integers(0, V, (2 * V, 3)).astype(np.uint32),
        "shapedirs": rng.normal(0, 0.01, (V, 3, num_components)),
        "posedirs": rng.normal(0, 0.01, (V, 3, 9 * (J - 1))),
        "J_regressor": scipy.sparse.csc_matrix(J_regressor),
        "weights": weights,
        "kintree_table": kintree,
        "bs_type": "lrotmin",
        "bs_style": "lbs",
    }
    if hands_mean:
        for side in "lr":
            model[f"hands_mean{side}"] = rng.normal(0, 0.3, 45)
            model[f"hands_components{side}"] = rng.normal(0, 0.3, (45, 45))
    if kind == "smplx":
        model["joint2num"] = {f"joint{j}": j for j in range(J)}
    return model


class _Ch:  # stands for chumpy.ch.Ch: its pickled state holds the array under 'x'
    def __init__(self, x):
        self.x = x

    def __getstate__(self):
        return {"x": self.x, "_dirty_vars": set(), "_itr": None}


class _CscMatrix:  # stands for python-2-era scipy.sparse.csc.csc_matrix
    def __init__(self, m):
        self.__dict__.update(data=m.data, indices=m.indices, indptr=m.indptr, _shape=m.shape, format="csc",
                             maxprint=50)  # fmt: skip


def save_chumpy_pkl(model: dict, path) -> None:
    """``model`` as the official python-2-era ``.pkl`` holds it: protocol 2, chumpy arrays for
    v_template / shapedirs / posedirs and an old-path scipy sparse J_regressor (classes faked under their
    old module paths while pickling)."""
    import pickle
    import sys
    import types

    data = {k: _Ch(v) if k in ("v_template", "shapedirs", "posedirs") else v for k, v in model.items()}
    data["J_regressor"] = _CscMatrix(model["J_regressor"])
    fakes = {"chumpy.ch": ("Ch", _Ch), "scipy.sparse.csc": ("csc_matrix", _CscMatrix)}
    saved = {name: sys.modules.get(name) for name in ("chumpy", "chumpy.ch", "scipy.sparse.csc")}
    saved_names = {cls: (cls.__module__, cls.__qualname__) for _, cls in fakes.values()}
    try:
        sys.modules.setdefault("chumpy", types.ModuleType("chumpy"))
        for module_name, (name, cls) in fakes.items():
            module = types.ModuleType(module_name)
            setattr(module, name, cls)
            sys.modules[module_name] = module
            cls.__module__, cls.__qualname__ = module_name, name
        with open(path, "wb") as fh:
            pickle.dump(data, fh, protocol=2)
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
        for cls, (module_name, qualname) in saved_names.items():
            cls.__module__, cls.__qualname__ = module_name, qualname
