"""SMPL from the user's own model file (.pkl or .npz), without chumpy.

The official ``.pkl`` files are python-2 pickles holding chumpy objects and old scipy.sparse classes. A
pickle is code, so :class:`_BodyModelUnpickler` resolves only an allow-list of classes (numpy arrays and
dtypes, scipy sparse matrices under their old and new module paths, stand-ins for chumpy arrays, a few
harmless builtins) and refuses anything else, naming the file and the class.
"""

from __future__ import annotations

import importlib
import pickle
import warnings
from pathlib import Path

import numpy as np
import torch

from rmavatar.body.base import SMPL_PARENTS, BodyModel, BodyOutput, check_pose_inputs
from rmavatar.body.lbs import axis_angle_to_matrix, lbs
from rmavatar.utils import UserError
from rmavatar.utils.errors import load_error

REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")

# File names tried in a folder, per gender (official SMPL releases and the common renamed copies).
_GENDER_FILES = {
    "neutral": ("SMPL_NEUTRAL", "basicmodel_neutral_lbs_10_207_0_v1.1.0", "basicModel_neutral_lbs_10_207_0_v1.0.0"),
    "male": ("SMPL_MALE", "basicmodel_m_lbs_10_207_0_v1.1.0", "basicModel_m_lbs_10_207_0_v1.0.0"),
    "female": ("SMPL_FEMALE", "basicmodel_f_lbs_10_207_0_v1.1.0", "basicModel_f_lbs_10_207_0_v1.0.0"),
}


class _ChumpyStandIn:
    """Takes the place of a chumpy object; keeps only its array value."""

    def __setstate__(self, state):
        if isinstance(state, dict) and "x" in state:  # chumpy.ch.Ch: the array is state['x']
            self.value = np.asarray(_plain(state["x"]))
        elif isinstance(state, dict) and "a" in state and "idxs" in state:  # chumpy.reordering.Select
            source = np.asarray(_plain(state["a"])).reshape(-1)
            value = source[np.asarray(state["idxs"], dtype=np.int64)]
            if "preferred_shape" in state:
                value = value.reshape(tuple(state["preferred_shape"]))
            self.value = value
        else:
            keys = sorted(state) if isinstance(state, dict) else type(state).__name__
            raise pickle.UnpicklingError(f"unsupported chumpy object (state {keys})")


class _SparseStandIn:
    """Takes the place of a scipy.sparse matrix class of any scipy version; rebuilt by :func:`_plain`."""

    def __init__(self, *args, **kwargs):
        self.__dict__["_args"] = args

    def __setstate__(self, state):
        self.__dict__.update(state if isinstance(state, dict) else {})


_SPARSE_MODULES = {"scipy.sparse", "scipy.sparse.csc", "scipy.sparse.csr", "scipy.sparse.coo",
                   "scipy.sparse._csc", "scipy.sparse._csr", "scipy.sparse._coo",
                   "scipy.sparse.compressed", "scipy.sparse._compressed"}  # fmt: skip
_SPARSE_CLASSES = {"csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array"}
_CHUMPY_MODULES = {"chumpy", "chumpy.ch", "chumpy.ch_ops", "chumpy.reordering"}
_NUMPY_NAMES = {"_reconstruct", "scalar", "ndarray", "dtype", "_frombuffer"}
_NUMPY_MODULES = {"numpy", "numpy.core.multiarray", "numpy._core.multiarray", "numpy.core.numeric",
                  "numpy._core.numeric"}  # fmt: skip
_BUILTINS = {("builtins", "object"), ("builtins", "set"), ("builtins", "frozenset"), ("builtins", "slice"),
             ("copyreg", "_reconstructor"),
             ("_codecs", "encode")}  # fmt: skip  (bytes in protocol-2 pickles written by Python 3)


_PY2_MODULES = {"__builtin__": "builtins", "copy_reg": "copyreg"}


class _BodyModelUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        module = _PY2_MODULES.get(module, module)
        if module in _CHUMPY_MODULES:
            return _ChumpyStandIn
        if module in _SPARSE_MODULES and name in _SPARSE_CLASSES:
            return _SparseStandIn
        if module in _NUMPY_MODULES and name in _NUMPY_NAMES:
            if name in ("ndarray", "dtype"):
                return getattr(np, name)
            for path in ("numpy._core.multiarray", "numpy.core.multiarray"):
                try:
                    return getattr(importlib.import_module(path), name)
                except (ImportError, AttributeError):
                    continue
        if (module, name) in _BUILTINS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load class {module}.{name}: not part of a body-model file")


def _plain(value):
    """Stand-ins -> numpy arrays / scipy sparse matrices; anything else as it is."""
    if isinstance(value, _ChumpyStandIn):
        return value.value
    if isinstance(value, _SparseStandIn):
        import scipy.sparse

        d = value.__dict__
        shape = tuple(d.get("_shape", d.get("shape", ())))
        fmt = d.get("format", "csc")
        if fmt in ("csc", "csr"):
            cls = scipy.sparse.csc_matrix if fmt == "csc" else scipy.sparse.csr_matrix
            return cls((np.asarray(d["data"]), np.asarray(d["indices"]), np.asarray(d["indptr"])), shape=shape)
        if fmt == "coo":
            rows, cols = (np.asarray(d["row"]), np.asarray(d["col"])) if "row" in d else d["coords"]
            return scipy.sparse.coo_matrix((np.asarray(d["data"]), (rows, cols)), shape=shape)
        raise pickle.UnpicklingError(f"unsupported sparse matrix format {fmt!r}")
    return value


def read_smpl_file(path: str | Path) -> dict[str, np.ndarray]:
    """Read an SMPL ``.pkl`` (python-2 / chumpy) or ``.npz`` file -> dict of float/int numpy arrays."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"SMPL model file {path} does not exist")
    if path.suffix == ".npz":
        raw = {}
        try:
            with np.load(path, allow_pickle=False) as data:
                for key in REQUIRED_KEYS:
                    if key in data.files:
                        raw[key] = data[key]
        except ValueError as exc:  # an object array would need allow_pickle, which could run code
            raise UserError(f"{path}: {load_error(exc)}") from None
        except Exception as exc:
            raise UserError(f"cannot read SMPL model file {path}: {exc}") from exc
    elif path.suffix == ".pkl":
        try:
            with open(path, "rb") as fh, warnings.catch_warnings():
                warnings.simplefilter("ignore")
                raw = _BodyModelUnpickler(fh, encoding="latin1").load()
        except pickle.UnpicklingError as exc:
            raise UserError(f"{path} is not an SMPL model file: {exc}") from exc
        except Exception as exc:
            raise UserError(f"cannot read {path} as an SMPL model pickle: {type(exc).__name__}: {exc}") from exc
        if not isinstance(raw, dict):
            raise UserError(f"{path} is not an SMPL model file: it holds a {type(raw).__name__}, not a dict")
        raw = {k: _plain(v) for k, v in raw.items() if k in REQUIRED_KEYS}
    else:
        raise UserError(f"SMPL model file {path} must be .pkl or .npz")
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise UserError(f"{path} is not an SMPL model file: missing {', '.join(missing)}")
    out = {}
    for key, value in raw.items():
        if hasattr(value, "toarray"):
            value = value.toarray()
        out[key] = np.asarray(value)
    V = out["v_template"].shape[0] if out["v_template"].ndim == 2 else -1
    checks = {
        "v_template": out["v_template"].shape == (V, 3),
        "f": out["f"].ndim == 2 and out["f"].shape[1] == 3,
        "shapedirs": out["shapedirs"].ndim == 3 and out["shapedirs"].shape[:2] == (V, 3),
        "posedirs": out["posedirs"].shape == (V, 3, 207),
        "J_regressor": out["J_regressor"].shape == (24, V),
        "weights": out["weights"].shape == (V, 24),
        "kintree_table": out["kintree_table"].shape == (2, 24),
    }
    bad = [f"{k} {out[k].shape}" for k, ok in checks.items() if not ok]
    if bad:
        raise UserError(
            f"{path} is not an SMPL model (24 joints, 207 pose blend shapes) or is damaged: unexpected shapes "
            + ", ".join(bad)
        )
    parents = out["kintree_table"][0].astype(np.int64)
    if tuple(int(p) for p in parents[1:]) != SMPL_PARENTS[1:]:
        raise UserError(f"{path}: its kinematic tree is not SMPL's (parents {parents.tolist()})")
    return out


def find_smpl_file(path: str | Path, gender: str | None) -> Path:
    """A file as given, or in a folder the file of ``gender`` (neutral when None)."""
    path = Path(path).expanduser()
    if path.is_file():
        return path
    if not path.is_dir():
        raise UserError(f"SMPL model path {path} does not exist")
    gender = gender or "neutral"
    for stem in _GENDER_FILES[gender]:
        for suffix in (".pkl", ".npz"):
            for candidate in (path / (stem + suffix), path / (stem.lower() + suffix)):
                if candidate.is_file():
                    return candidate
    wanted = ", ".join(s + ".pkl/.npz" for s in _GENDER_FILES[gender][:1])
    raise UserError(f"no {gender} SMPL model in folder {path} (looked for {wanted} and the official names)")


class SmplBody(BodyModel):
    """SMPL (24 joints, 10 or 300 shape components, pose blend shapes, LBS). ``gender``, ``file``."""

    def __init__(self, data: dict[str, np.ndarray], file: Path, gender: str | None = None):
        super().__init__()
        self.file = Path(file)
        self.gender = gender
        self.spec = f"smpl:{self.file.resolve()}"
        f32 = lambda a: torch.tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        self.num_betas = int(data["shapedirs"].shape[2])
        self.register_buffer("v_template", f32(data["v_template"]), persistent=False)
        self.register_buffer("shapedirs", f32(data["shapedirs"]), persistent=False)  # [V,3,S]
        V = data["v_template"].shape[0]
        # [207, V*3] so pose features [B,207] @ posedirs gives offsets
        self.register_buffer("posedirs", f32(data["posedirs"].reshape(V * 3, 207).T), persistent=False)
        self.register_buffer("J_regressor", f32(data["J_regressor"]), persistent=False)
        self.register_buffer("weights", f32(data["weights"]), persistent=False)
        self.register_buffer("faces", torch.tensor(data["f"].astype(np.int64)), persistent=False)
        self.register_buffer("binding_faces", torch.arange(len(data["f"])), persistent=False)

    def joint_weights(self) -> torch.Tensor:
        return self.weights

    @classmethod
    def from_path(cls, path: str | Path, gender: str | None = None) -> "SmplBody":
        file = find_smpl_file(path, gender)
        return cls(read_smpl_file(file), file, gender)

    def forward(self, betas, global_orient, body_pose, transl=None, check_values=True, hand_pose=None) -> BodyOutput:
        """SMPL parameters -> ``vertices [B,6890,3]``, ``joints [B,24,3]``; betas may have fewer columns.
        SMPL has no fingers: ``hand_pose`` is ignored."""
        dtype, device = self.v_template.dtype, self.v_template.device
        betas, global_orient, body_pose, transl = check_pose_inputs(
            betas, global_orient, body_pose, transl, self.num_betas, dtype, device, check_values
        )
        B = global_orient.shape[0]
        v = self.v_template[None]
        if betas is not None:
            n = betas.shape[1]
            v = v + torch.einsum("vds,bs->bvd", self.shapedirs[..., :n], betas)
        joints = torch.einsum("jv,bvd->bjd", self.J_regressor, v)
        R = axis_angle_to_matrix(torch.cat([global_orient, body_pose], 1).reshape(B, 24, 3))
        eye = torch.eye(3, dtype=dtype, device=device)
        pose_feature = (R[:, 1:] - eye).reshape(B, 207)
        v = v + (pose_feature @ self.posedirs).reshape(B, -1, 3)
        vertices, posed_joints, _ = lbs(v, joints, SMPL_PARENTS, R, self.weights)
        return BodyOutput(vertices=vertices + transl[:, None], joints=posed_joints + transl[:, None])
