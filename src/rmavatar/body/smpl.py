"""SMPL, SMPL-H and SMPL-X from the user's own model file (.pkl or .npz), without chumpy.

The kind is read from the file's joint count: SMPL has 24 joints; SMPL-H 52 (SMPL's first 22, then each
hand's 15 finger joints in MANO's order, left hand first); SMPL-X 55 (the 22, jaw, left and right eye,
then the hands). All three are driven by the same SMPL-format parameters (:class:`SmplBody`).

The official ``.pkl`` files are python-2 pickles holding chumpy objects and old scipy.sparse classes. A
pickle is code, so :class:`_BodyModelUnpickler` resolves only an allow-list of classes (numpy arrays and
dtypes, scipy sparse matrices under their old and new module paths, stand-ins for chumpy arrays, a few
harmless builtins) and refuses anything else, naming the file and the class.
"""

from __future__ import annotations

import importlib
import pickle
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rmavatar.body.base import (
    FINGERS,
    HAND_ANCESTORS,
    HAND_JOINT_NAMES,
    HAND_PARENTS,
    SMPL_PARENTS,
    BodyModel,
    BodyOutput,
    check_hand_pose,
    check_pose_inputs,
    fingertip_vertex,
    hand_points,
)
from rmavatar.body.lbs import axis_angle_to_matrix, lbs
from rmavatar.utils import UserError
from rmavatar.utils.errors import load_error

REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
# Each hand's mean pose (axis-angle [45], MANO's relaxed hand) in SMPL-H and SMPL-X files.
HAND_MEAN_KEYS = ("hands_meanl", "hands_meanr")


@dataclass(frozen=True)
class ModelKind:
    """A kind of model file: its ``name``, kinematic tree, the joint where the left hand's 15 finger joints
    start (the right hand's follow; None: no fingers) and how many face joints (SMPL-X's jaw and eyes)
    lie between the 22 body joints and the hands."""

    name: str
    parents: tuple[int, ...]
    first_finger: int | None = None
    face_joints: int = 0


def _hand_parents(first: int, wrist: int) -> tuple[int, ...]:
    """MANO's tree of one hand whose joints start at ``first``: every finger's first joint on the wrist."""
    return tuple(wrist if k % 3 == 0 else first + k - 1 for k in range(15))


# By joint count. SMPL-H and SMPL-X have SMPL's first 22 joints; SMPL's hand joints 22 / 23 are not theirs.
KINDS = {
    24: ModelKind("SMPL", SMPL_PARENTS),
    52: ModelKind("SMPL-H", SMPL_PARENTS[:22] + _hand_parents(22, 20) + _hand_parents(37, 21), 22),
    55: ModelKind("SMPL-X", SMPL_PARENTS[:22] + (15, 15, 15) + _hand_parents(25, 20) + _hand_parents(40, 21),
                  25, 3),  # fmt: skip
}

# File names tried in a folder, per gender, regardless of case: SMPL's first (the official releases and
# the common renamed copies), so a folder that also holds other kinds still gives SMPL; then SMPL-X's,
# SMPL-H's (the MANO site's SMPLH_female.pkl) and AMASS's SMPL-H layout (female/model.npz).
_GENDER_FILES = {
    gender: (f"SMPL_{gender.upper()}", f"basicmodel_{short}_lbs_10_207_0_v1.1.0",
             f"basicModel_{short}_lbs_10_207_0_v1.0.0", f"SMPLX_{gender.upper()}", f"SMPLH_{gender.upper()}",
             f"{gender}/model")  # fmt: skip
    for gender, short in (("neutral", "neutral"), ("male", "m"), ("female", "f"))
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
    """Read an SMPL, SMPL-H or SMPL-X ``.pkl`` (python-2 / chumpy) or ``.npz`` file -> dict of numpy arrays:
    :data:`REQUIRED_KEYS` and, where the file has them, :data:`HAND_MEAN_KEYS`; UserError naming the file
    unless its layout is one of :data:`KINDS`."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"SMPL model file {path} does not exist")
    if path.suffix == ".npz":
        raw = _read_npz(path)
    elif path.suffix == ".pkl":
        raw = _read_pkl(path)
    else:
        raise UserError(f"SMPL model file {path} must be .pkl or .npz")
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise UserError(f"{path} is not an SMPL model file: missing {', '.join(missing)}")
    out = {k: np.asarray(v.toarray() if hasattr(v, "toarray") else v) for k, v in raw.items()}
    _check_layout(path, out)
    return out


def _read_npz(path: Path) -> dict:
    raw = {}
    try:
        # only the arrays we use are read: official files also hold object arrays (joint2num), which would
        # need allow_pickle, which could run code
        with np.load(path, allow_pickle=False) as data:
            for key in REQUIRED_KEYS + HAND_MEAN_KEYS:
                if key in data.files:
                    raw[key] = data[key]
    except ValueError as exc:
        raise UserError(f"{path}: {load_error(exc)}") from None
    except Exception as exc:
        raise UserError(f"cannot read SMPL model file {path}: {exc}") from exc
    return raw


def _read_pkl(path: Path) -> dict:
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
    return {k: _plain(v) for k, v in raw.items() if k in REQUIRED_KEYS + HAND_MEAN_KEYS}


def _check_layout(path: Path, out: dict[str, np.ndarray]) -> None:
    """UserError naming the file unless its arrays have the shapes and kinematic tree of one of KINDS."""
    tree = out["kintree_table"]
    kind = KINDS.get(tree.shape[1]) if tree.ndim == 2 and tree.shape[0] == 2 else None
    if kind is None:
        raise UserError(
            f"{path} is not an SMPL model file of a known kind (SMPL: 24 joints, SMPL-H: 52, SMPL-X: 55) or is "
            f"damaged: kintree_table {tree.shape}"
        )
    J, P = len(kind.parents), 9 * (len(kind.parents) - 1)
    V = out["v_template"].shape[0] if out["v_template"].ndim == 2 else -1
    checks = {
        "v_template": out["v_template"].shape == (V, 3),
        "f": out["f"].ndim == 2 and out["f"].shape[1] == 3,
        "shapedirs": out["shapedirs"].ndim == 3 and out["shapedirs"].shape[:2] == (V, 3),
        "posedirs": out["posedirs"].shape == (V, 3, P),
        "J_regressor": out["J_regressor"].shape == (J, V),
        "weights": out["weights"].shape == (V, J),
        **{key: out[key].size == 45 for key in HAND_MEAN_KEYS if key in out},
    }
    bad = [f"{k} {out[k].shape}" for k, ok in checks.items() if not ok]
    if bad:
        raise UserError(
            f"{path} is not an {kind.name} model ({J} joints, {P} pose blend shapes) or is damaged: unexpected "
            "shapes " + ", ".join(bad)
        )
    parents = tree[0].astype(np.int64)
    if tuple(int(p) for p in parents[1:]) != kind.parents[1:]:
        raise UserError(f"{path}: its kinematic tree is not {kind.name}'s (parents {parents.tolist()})")


def find_smpl_file(path: str | Path, gender: str | None) -> Path:
    """A file as given, or in a folder the file of ``gender`` (neutral when None): see _GENDER_FILES."""
    path = Path(path).expanduser()
    if path.is_file():
        return path
    if not path.is_dir():
        raise UserError(f"SMPL model path {path} does not exist")
    gender = gender or "neutral"
    by_name = {p.name.lower(): p for p in path.iterdir() if p.is_file()}
    for stem in _GENDER_FILES[gender]:
        for suffix in (".pkl", ".npz"):
            exact = path / (stem + suffix)
            found = exact if exact.is_file() else by_name.get((stem + suffix).lower())
            if found is not None:
                return found
    wanted = ", ".join(f"{prefix}_{gender.upper()}.pkl/.npz" for prefix in ("SMPL", "SMPLX", "SMPLH"))
    raise UserError(f"no {gender} SMPL model in folder {path} (looked for {wanted} and the official names)")


def _shape_components(kind: ModelKind, count: int) -> int:
    """How many of the file's ``count`` shapedirs components are shape. SMPL-X files hold shape, then
    expression components: 300 + 100 (SMPL-X 1.1) or 10 + 10 (1.0), split as the smplx package splits them."""
    if kind.name != "SMPL-X":
        return count
    return 300 if count >= 300 else min(count, 10)


def _weight_columns(kind: ModelKind, hands: bool) -> list[int]:
    """The column of :meth:`SmplBody.joint_weights` each of the file's joints counts for: its own for
    the 22 body joints (and SMPL's hands), the head's for SMPL-X's jaw and eyes; a finger joint's own
    column of HAND_PARENTS with ``hands``, else its SMPL ancestor's (``HAND_ANCESTORS``, as Anny's)."""
    columns = list(range(len(kind.parents)))
    if kind.first_finger is None:
        return columns
    columns[22 : kind.first_finger] = [15] * kind.face_joints
    for j in range(24, len(HAND_PARENTS)):
        columns[kind.first_finger + j - 24] = j if hands else HAND_ANCESTORS[j]
    return columns


class SmplBody(BodyModel):
    """SMPL, SMPL-H or SMPL-X (``kind``, from the file) driven by SMPL-format parameters; ``gender``, ``file``.

    SMPL-H / SMPL-X: ``body_pose``'s first 21 joints drive their 21 body joints; SMPL's hand joints
    (``body_pose[:, 63:69]``) have no counterpart and are ignored. ``hand_pose`` drives the 30 finger
    joints (zero: flat hands, as in MANO's and AMASS's poses); None gives ``relaxed_hand_pose``, the
    file's mean hands (flat where the file has none). SMPL-X's jaw and eyes stay at rest, its expression
    at zero. ``joints`` 22 / 23 are each hand's middle finger's first joint (as Anny's).
    """

    def __init__(self, data: dict[str, np.ndarray], file: Path, gender: str | None = None):
        super().__init__()
        self.file = Path(file)
        self.gender = gender
        self.spec = f"smpl:{self.file.resolve()}"
        self.kind = KINDS[data["kintree_table"].shape[1]]
        f32 = lambda a: torch.tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        self.num_betas = _shape_components(self.kind, data["shapedirs"].shape[2])
        V, P = data["v_template"].shape[0], data["posedirs"].shape[2]
        # the file's mean shape at rest (flat hands); v_template is what forward gives at zero pose
        self.register_buffer("template", f32(data["v_template"]), persistent=False)
        self.register_buffer("shapedirs", f32(data["shapedirs"][..., : self.num_betas]), persistent=False)  # [V,3,S]
        # [P, V*3] so pose features [B,P] @ posedirs gives offsets
        self.register_buffer("posedirs", f32(data["posedirs"].reshape(V * 3, P).T), persistent=False)
        self.register_buffer("J_regressor", f32(data["J_regressor"]), persistent=False)
        self.register_buffer("weights", f32(data["weights"]), persistent=False)
        self.register_buffer("faces", torch.tensor(data["f"].astype(np.int64)), persistent=False)
        self.register_buffer("binding_faces", torch.arange(len(data["f"])), persistent=False)
        if self.kind.first_finger is None:
            self.register_buffer("relaxed_hand_pose", None, persistent=False)
            self.register_buffer("v_template", self.template, persistent=False)
        else:
            self._init_fingers(data)

    def _init_fingers(self, data: dict[str, np.ndarray]) -> None:
        """The relaxed hands, the joints that stand for SMPL's 24 and for the hand points, the fingertip
        vertices, and v_template with the relaxed hands."""
        first = self.kind.first_finger

        def joint(side: int, name: str) -> int:
            return first + 15 * side + HAND_JOINT_NAMES.index(name)

        if all(key in data for key in HAND_MEAN_KEYS):
            relaxed = np.concatenate([data[key].reshape(45) for key in HAND_MEAN_KEYS])
        else:
            relaxed = np.zeros(90)
        self.register_buffer("relaxed_hand_pose", torch.tensor(relaxed, dtype=torch.float32), persistent=False)
        smpl_joints = [*range(22), joint(0, "middle1"), joint(1, "middle1")]
        self.register_buffer("smpl_joints", torch.tensor(smpl_joints), persistent=False)
        points = [[20 + side] + [joint(side, f"{f}{k}") for f in FINGERS for k in (1, 2, 3)] for side in (0, 1)]
        self.register_buffer("hand_point_joints", torch.tensor(points).reshape(-1), persistent=False)
        rest_joints = data["J_regressor"] @ data["v_template"]
        tips = [fingertip_vertex(data["v_template"], data["weights"][:, last], rest_joints[last],
                                 rest_joints[last] - rest_joints[joint(side, f"{f}2")])
                for side in (0, 1) for f in FINGERS for last in [joint(side, f"{f}3")]]  # fmt: skip
        if None in tips:
            raise UserError(f"{self.file} is not an {self.kind.name} model or is damaged: no vertex follows "
                            "the last joint of every finger (skinning weight > 0.5)")  # fmt: skip
        self.register_buffer("fingertip_vertices", torch.tensor(tips), persistent=False)
        with torch.no_grad():
            zero = torch.zeros(1, 3)
            canonical = self.forward(None, zero, torch.zeros(1, 69), zero).vertices[0]
        self.register_buffer("v_template", canonical, persistent=False)

    def joint_weights(self, hands: bool = False) -> torch.Tensor:
        """``[V,24]``: the file's skinning weights with each joint counted for the SMPL joint it stands for
        (see _weight_columns), or with ``hands`` ``[V,54]``: the finger joints apart (SMPL: zero)."""
        columns = torch.tensor(_weight_columns(self.kind, hands), device=self.weights.device)
        out = self.weights.new_zeros(self.weights.shape[0], 54 if hands else 24)
        return out.index_add_(1, columns, self.weights)

    @classmethod
    def from_path(cls, path: str | Path, gender: str | None = None) -> "SmplBody":
        file = find_smpl_file(path, gender)
        return cls(read_smpl_file(file), file, gender)

    def forward(self, betas, global_orient, body_pose, transl=None, check_values=True, hand_pose=None) -> BodyOutput:
        """SMPL-format parameters -> ``vertices [B,V,3]``, ``joints [B,24,3]`` and, for SMPL-H / SMPL-X,
        ``hand_points [B,42,3]``; betas may have fewer columns. SMPL has no fingers: ``hand_pose`` is ignored."""
        dtype, device = self.template.dtype, self.template.device
        betas, global_orient, body_pose, transl = check_pose_inputs(
            betas, global_orient, body_pose, transl, self.num_betas, dtype, device, check_values
        )
        if self.kind.first_finger is None:
            vertices, joints = self._skin(betas, torch.cat([global_orient, body_pose], 1))
            return BodyOutput(vertices=vertices + transl[:, None], joints=joints + transl[:, None])
        B = global_orient.shape[0]
        hand_pose = check_hand_pose(hand_pose, B, dtype, device, check_values)
        if hand_pose is None:
            hand_pose = self.relaxed_hand_pose.expand(B, -1)
        face = global_orient.new_zeros(B, 3 * self.kind.face_joints)
        vertices, joints = self._skin(betas, torch.cat([global_orient, body_pose[:, :63], face, hand_pose], 1))
        vertices, joints = vertices + transl[:, None], joints + transl[:, None]
        return BodyOutput(vertices=vertices, joints=joints[:, self.smpl_joints],
                          hand_points=self._hand_points(joints, vertices))  # fmt: skip

    def _skin(self, betas: torch.Tensor | None, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape and pose blend shapes, then LBS on the file's own tree: ``pose [B,3J]`` (axis-angle of
        every joint of the file) -> vertices ``[B,V,3]`` and all J posed joints ``[B,J,3]``."""
        B = pose.shape[0]
        v = self.template[None]
        if betas is not None:
            n = betas.shape[1]
            v = v + torch.einsum("vds,bs->bvd", self.shapedirs[..., :n], betas)
        joints = torch.einsum("jv,bvd->bjd", self.J_regressor, v)
        R = axis_angle_to_matrix(pose.reshape(B, -1, 3))
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        pose_feature = (R[:, 1:] - eye).reshape(B, -1)
        v = v + (pose_feature @ self.posedirs).reshape(B, -1, 3)
        vertices, posed_joints, _ = lbs(v, joints, self.kind.parents, R, self.weights)
        return vertices, posed_joints

    def _hand_points(self, joints: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
        """``[B,42,3]`` in MediaPipe's order: the wrist and finger joints, a vertex at each fingertip."""
        return hand_points(joints[:, self.hand_point_joints].reshape(-1, 2, 16, 3),
                           vertices[:, self.fingertip_vertices].reshape(-1, 2, 5, 3))
