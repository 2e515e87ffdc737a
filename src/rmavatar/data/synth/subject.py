"""The synthetic subject: the Anny body dressed with materials, a loose tunic and a hair cap.

The body is posed by the body model's LBS. Two shells are laid over it, each a piece of the body surface
(clipped along clean cut lines, subdivided once) pushed out along the posed normals:

- the **tunic** (torso down to the hips, short sleeves): its offset grows towards a flared hem and holds
  folds, and the hem swings with the torso twist, the thighs push it when they move, the folds' phase
  and depth follow the hips and spine. None of this is in the LBS body, so an avatar must learn it as
  a pose-dependent correction (the rectifier's job). Offsets stay within about 5 cm of the body.
- the **hair cap**: a rigid 5-12 mm shell over the scalp (LBS explains it; it gives the head volume).

Shell vertices are fixed linear combinations of body vertices (a sparse matrix), so posing them costs
one sparse product per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from rmavatar.data.synth import texture as tx

# Anny bone-name prefixes -> body group, for the dominant-skinning-weight classification.
_GROUPS = {
    "upperleg": "leg", "lowerleg": "leg", "foot": "foot", "toe": "foot", "root": "torso",
    "pelvis": "torso", "spine": "torso", "clavicle": "torso", "shoulder": "torso", "upperarm": "upperarm",
    "lowerarm": "lowerarm", "wrist": "lowerarm", "finger": "lowerarm", "metacarpal": "lowerarm",
    "neck": "head", "head": "head", "eye": "head",
}  # fmt: skip
_GROUP_NAMES = ("torso", "leg", "foot", "upperarm", "lowerarm", "head")

# SMPL joint indices used below.
PELVIS, HIP_L, HIP_R, KNEE_L, KNEE_R, ANKLE_L, ANKLE_R = 0, 1, 2, 4, 5, 7, 8
NECK, SHOULDER_L, SHOULDER_R, ELBOW_L, ELBOW_R, WRIST_L, WRIST_R = 12, 16, 17, 18, 19, 20, 21


@dataclass
class Shell:
    """A surface laid over the body: ``weights`` sparse [S,V] (shell base = weights @ body vertices),
    ``faces [Fs,3]`` (indices into the shell's S vertices), per-vertex canonical data ``canon [S,3]``,
    ``aux [S,3]``, ``hem [S]`` (0 at the waist .. 1 at the hem; drives swing and flare), ``edge [S]``
    (0..1 towards any cut: hem band and cuffs), ``theta [S]`` (angle around the torso axis, 0 = front),
    ``radius [S]`` (distance from the torso axis), ``material`` (one id for all faces)."""

    weights: sp.csr_matrix
    faces: np.ndarray
    canon: np.ndarray
    aux: np.ndarray
    hem: np.ndarray
    edge: np.ndarray
    theta: np.ndarray
    radius: np.ndarray
    material: int


@dataclass
class Subject:
    """Everything needed to render the dressed body in any pose.

    ``faces [F,3]`` the body's triangles, ``canon [V,3]`` canonical (zero-pose) vertices, ``aux [V,3]``
    radial direction from the nearest bone axis, ``face_material [F]``, ``tunic`` and ``hair`` shells,
    ``landmarks``, ``palette``, ``seed`` (texture noise), ``axis [2]`` the torso axis (x, z) in canonical
    space.
    """

    body: object
    faces: np.ndarray
    canon: np.ndarray
    aux: np.ndarray
    face_material: np.ndarray
    tunic: Shell
    hair: Shell
    landmarks: tx.Landmarks
    palette: tx.Palette
    seed: int
    axis: np.ndarray


def _segment_radial(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest points of ``p [N,3]`` on segment a-b: (distance [N], radial unit [N,3], t [N] in 0..1)."""
    d = b - a
    t = np.clip((p - a) @ d / (d @ d), 0.0, 1.0)
    r = p - (a + t[:, None] * d)
    n = np.linalg.norm(r, axis=1)
    return n, r / np.maximum(n, 1e-9)[:, None], t


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``[V,3]`` (outward for counter-clockwise faces)."""
    v = np.asarray(verts, dtype=np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _clip(W: sp.csr_matrix, faces: np.ndarray, phi: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Keep the part of a triangle set (vertices ``W [S,V]`` @ body vertices) where the per-vertex field
    ``phi [S] >= 0``, cutting faces along the zero level (linear interpolation on edges).
    Returns (weights [S',V] sparse, faces [Fs,3])."""
    index: dict[tuple[int, int], int] = {}
    rows: list[tuple[int, int, float]] = []

    def vert(i: int, j: int) -> int:
        key = (i, i) if i == j else (min(i, j), max(i, j))
        if key not in index:
            index[key] = len(index)
            k = index[key]
            if i == j:
                rows.append((k, i, 1.0))
            else:
                s = phi[i] / (phi[i] - phi[j])  # where phi crosses 0 from i to j
                rows.append((k, i, 1.0 - s))
                rows.append((k, j, s))
        return index[key]

    out = []
    for f in faces:
        pos = phi[f] >= 0
        n = int(pos.sum())
        if n == 0:
            continue
        if n == 3:
            out.append([vert(f[0], f[0]), vert(f[1], f[1]), vert(f[2], f[2])])
            continue
        # Rotate the cyclic order so that the odd vertex out comes first (orientation is kept).
        odd = int(np.nonzero(pos if n == 1 else ~pos)[0][0])
        a, b, c = f[odd], f[(odd + 1) % 3], f[(odd + 2) % 3]
        if n == 1:
            out.append([vert(a, a), vert(a, b), vert(a, c)])
        else:
            ab, ac = vert(a, b), vert(a, c)
            out.append([ab, vert(b, b), vert(c, c)])
            out.append([ab, vert(c, c), ac])
    r, c, w = zip(*rows)
    C = sp.csr_matrix((w, (r, c)), shape=(len(index), len(phi)))
    return (C @ W).tocsr(), np.asarray(out, dtype=np.int64).reshape(-1, 3)


def _subdivide(W: sp.csr_matrix, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """One step of midpoint subdivision (each triangle -> 4), on the weight representation."""
    S = W.shape[0]
    mids: dict[tuple[int, int], int] = {}
    pairs = []

    def mid(i: int, j: int) -> int:
        key = (min(i, j), max(i, j))
        if key not in mids:
            mids[key] = S + len(mids)
            pairs.append(key)
        return mids[key]

    out = []
    for a, b, c in faces:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        out += [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
    pairs = np.asarray(pairs, dtype=np.int64)
    r = np.repeat(np.arange(len(pairs)), 2)
    A = sp.csr_matrix((np.full(2 * len(pairs), 0.5), (r, pairs.ravel())), shape=(len(pairs), S))
    return sp.vstack([W, A @ W]).tocsr(), np.asarray(out, dtype=np.int64)


def build_subject(body, seed: int) -> Subject:
    """Dress the body (an Anny :class:`~rmavatar.body.base.BodyModel` with ``face_part``,
    ``part_names``, ``skin_weights`` and ``bone_names``). ``seed`` picks the colours and noise."""
    rng = np.random.default_rng([seed, 7])
    faces = body.faces.cpu().numpy().astype(np.int64)
    canon = body.v_template.cpu().numpy().astype(np.float64)
    J = _rest_joints(body)
    part = _part_selector(body)
    vgroup, fgroup = _body_groups(body, faces)
    axis = np.array([J[PELVIS, 0], J[PELVIS, 2]])
    lm = _landmarks(faces, canon, vgroup, J, part, axis)
    aux = _radial_directions(canon, vgroup, J, axis)
    mat = _face_materials(faces, canon, fgroup, part, lm.hem_y, lm.ground_y)
    tunic = _tunic(faces, canon, vgroup, fgroup, J, lm, axis)
    hair = _hair(faces, canon, part("head"), lm, seed)
    return Subject(body=body, faces=faces, canon=canon, aux=aux, face_material=mat, tunic=tunic, hair=hair,
                   landmarks=lm, palette=tx.make_palette(rng), seed=seed, axis=axis)  # fmt: skip


def _rest_joints(body) -> np.ndarray:
    """The body's joints [J,3] (float64) at zero pose and shape, i.e. in the canonical rest pose."""
    import torch

    with torch.no_grad():
        z = torch.zeros(1, 3)
        return body(None, z, torch.zeros(1, 69), z).joints[0].cpu().numpy().astype(np.float64)


def _part_selector(body):
    """Returns ``part(*names)``: the boolean mask [F] of the body's faces in any of the named parts."""
    part_names = list(body.part_names)
    face_part = body.face_part.cpu().numpy()
    return lambda *names: np.isin(face_part, [part_names.index(n) for n in names])


def _body_groups(body, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dominant body group (index into _GROUP_NAMES) per vertex from the skinning weights, and per face
    the most common of its vertices' groups; returns (vgroup [V], fgroup [F])."""
    W = body.skin_weights.cpu().numpy()
    group_of_bone = []
    for name in body.bone_names:
        g = next((g for prefix, g in _GROUPS.items() if name.startswith(prefix)), "torso")
        group_of_bone.append(_GROUP_NAMES.index(g))
    G = np.zeros((W.shape[0], len(_GROUP_NAMES)))
    for b, g in enumerate(group_of_bone):
        G[:, g] += W[:, b]
    vgroup = G.argmax(1)
    fgroup = np.asarray([np.bincount(vgroup[f], minlength=len(_GROUP_NAMES)).argmax() for f in faces])
    return vgroup, fgroup


def _landmarks(faces: np.ndarray, canon: np.ndarray, vgroup: np.ndarray, J: np.ndarray, part,
               axis: np.ndarray) -> tx.Landmarks:
    """The canonical landmarks the textures and the tunic are laid out from (eyes, mouth, head, hem,
    waist, chest, ground, ...); returns them."""
    centre_of = lambda names: canon[faces[part(*names)]].reshape(-1, 3).mean(0)  # noqa: E731
    eye_l, eye_r = centre_of(["eye_front.L", "eye_back.L"]), centre_of(["eye_front.R", "eye_back.R"])
    eye_pts = canon[faces[part("eye_front.L", "eye_back.L")]].reshape(-1, 3)
    eye_radius = float(np.linalg.norm(eye_pts - eye_l, axis=1).max())
    mouth_pts = canon[faces[part("mouth_cavity")]].reshape(-1, 3)
    mouth = mouth_pts[mouth_pts[:, 2] > mouth_pts[:, 2].max() - 0.006].mean(0)  # the lips' line
    head_pts = canon[faces[part("head")]].reshape(-1, 3)
    head_centre = 0.5 * (head_pts.min(0) + head_pts.max(0))
    ground_y = float(canon[:, 1].min())
    near_mid = np.abs(canon[:, 0] - J[PELVIS, 0]) < 0.015
    crotch_y = float(canon[near_mid & (canon[:, 1] > J[KNEE_L, 1]) & (canon[:, 1] < J[PELVIS, 1]), 1].min())
    hem_y = crotch_y + 0.06
    waist_y = float(J[3, 1] + 0.02)
    torso_front = canon[(vgroup == 0) & (np.abs(canon[:, 1] - (J[9, 1] + 0.03)) < 0.02), 2].max()
    chest = np.array([J[PELVIS, 0], J[9, 1] + 0.02, torso_front])
    return tx.Landmarks(eye_l=eye_l, eye_r=eye_r, eye_radius=eye_radius, mouth=mouth, head_centre=head_centre,
                        neck_y=float(J[NECK, 1]), neck=J[NECK], pelvis=J[PELVIS], hem_y=hem_y, waist_y=waist_y,
                        chest=chest, ground_y=ground_y, foot_x=float(abs(J[ANKLE_L, 0] - J[PELVIS, 0])))  # fmt: skip


def _radial_directions(canon: np.ndarray, vgroup: np.ndarray, J: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Per vertex the unit radial direction [V,3] from the nearest bone axis: legs and arms their
    segments, the torso (and the rest) a vertical axis through ``axis`` (x, z)."""
    aux = np.zeros_like(canon)
    torso_r = canon - np.array([axis[0], 0.0, axis[1]])
    torso_r[:, 1] = 0
    aux[:] = torso_r / np.maximum(np.linalg.norm(torso_r, axis=1, keepdims=True), 1e-9)
    limbs = [(1, [(HIP_L, KNEE_L), (KNEE_L, ANKLE_L)], 1), (1, [(HIP_R, KNEE_R), (KNEE_R, ANKLE_R)], -1),
             (3, [(SHOULDER_L, ELBOW_L)], 1), (3, [(SHOULDER_R, ELBOW_R)], -1),
             (4, [(ELBOW_L, WRIST_L)], 1), (4, [(ELBOW_R, WRIST_R)], -1)]  # fmt: skip
    for g, segments, side in limbs:
        sel = (vgroup == g) & (np.sign(canon[:, 0] - axis[0]) == side)
        best = np.full(sel.sum(), np.inf)
        for a, b in segments:
            d, r, _ = _segment_radial(canon[sel], J[a], J[b])
            closer = d < best
            best[closer] = d[closer]
            aux[np.nonzero(sel)[0][closer]] = r[closer]
    return aux


def _face_materials(faces: np.ndarray, canon: np.ndarray, fgroup: np.ndarray, part, hem_y: float,
                    ground_y: float) -> np.ndarray:
    """Material id (texture.SKIN, TROUSERS, ...) per face [F]; returns it."""
    mat = np.full(len(faces), tx.SKIN, dtype=np.int64)
    fy = canon[faces, 1].mean(1)
    mat[fgroup == 0] = np.where(fy[fgroup == 0] > hem_y - 0.02, tx.UNDERSHIRT, tx.TROUSERS)
    mat[fgroup == 1] = tx.TROUSERS
    mat[(fgroup == 1) & (fy < ground_y + 0.10)] = tx.SHOES
    mat[fgroup == 2] = tx.SHOES
    mat[part("foot.L", "foot.R")] = tx.SHOES
    mat[part("head")] = tx.HEAD
    mat[part("hand.L", "hand.R")] = tx.SKIN
    mat[part("eye_front.L", "eye_back.L", "eye_front.R", "eye_back.R")] = tx.EYE
    mat[part("mouth_cavity", "tongue")] = tx.MOUTH
    mat[part("eye_cavity.L", "eye_cavity.R")] = tx.LASH
    return mat


def _tunic(faces, canon, vgroup, fgroup, J, lm: tx.Landmarks, axis) -> Shell:
    # Subdivide the candidate faces first, so the cuts follow the field at twice the mesh resolution.
    cand = faces[np.isin(fgroup, [0, 1, 3])]
    used, local = np.unique(cand, return_inverse=True)
    W0 = sp.csr_matrix((np.ones(len(used)), (np.arange(len(used)), used)), shape=(len(used), len(canon)))
    W, f = _subdivide(W0, local.reshape(-1, 3))
    p = W @ canon
    # Cut lines: the hem (a horizontal plane above the crotch), short sleeves (planes across the upper
    # arms), a scooped neckline (an ellipse around the neck, deeper at the front).
    y = p[:, 1]
    phi = y - lm.hem_y
    for s, e in ((SHOULDER_L, ELBOW_L), (SHOULDER_R, ELBOW_R)):
        d = J[e] - J[s]
        t = (p - J[s]) @ d / (d @ d)
        phi = np.minimum(phi, (0.45 - t) * np.linalg.norm(d))
    # The neck hole: an ellipse in x and in front of the neck (open behind it), its lower edge a line
    # just under the neck at the back dropping to a scoop at the front.
    phi = np.minimum(phi, -tx.neck_hole(p, J[NECK]))
    W, f = _clip(W, f, phi)
    q = W @ canon
    rel = q - np.array([axis[0], 0.0, axis[1]])
    theta = np.arctan2(rel[:, 0], rel[:, 2])
    radius = np.hypot(rel[:, 0], rel[:, 2])
    sleeve = np.zeros(len(q))
    for s, e in ((SHOULDER_L, ELBOW_L), (SHOULDER_R, ELBOW_R)):
        d = J[e] - J[s]
        t = (q - J[s]) @ d / (d @ d)
        sleeve = np.maximum(sleeve, np.clip((t - 0.05) / 0.40, 0.0, 1.0))
    hem = np.clip((lm.waist_y - q[:, 1]) / (lm.waist_y - lm.hem_y), 0.0, 1.0) * (sleeve == 0)
    aux = rel.copy()
    aux[:, 1] = 0
    aux /= np.maximum(np.linalg.norm(aux, axis=1, keepdims=True), 1e-9)
    return Shell(weights=W, faces=f, canon=q, aux=aux, hem=hem, edge=np.maximum(hem, sleeve), theta=theta,
                 radius=radius, material=tx.TUNIC)  # fmt: skip


def _hair(faces, canon, head_faces, lm: tx.Landmarks, seed: int) -> Shell:
    cx = 0.5 * (lm.eye_l[0] + lm.eye_r[0])
    eye_y = 0.5 * (lm.eye_l[1] + lm.eye_r[1])
    ang = np.arctan2(canon[:, 0] - cx, canon[:, 2] - lm.head_centre[2])
    hairline = eye_y + 0.06 - 0.075 * tx.smoothstep(0.6, 2.2, np.abs(ang)) + 0.012 * np.cos(6 * ang)
    used, local = np.unique(faces[head_faces], return_inverse=True)
    W0 = sp.csr_matrix((np.ones(len(used)), (np.arange(len(used)), used)), shape=(len(used), len(canon)))
    W, f = _clip(W0, local.reshape(-1, 3), (canon[:, 1] - hairline)[used])
    q = W @ canon
    thick = 0.004 + 0.009 * tx.fbm(q * 25.0, 2, seed + 11) * tx.smoothstep(0.0, 0.03, q[:, 1] - eye_y - 0.05)
    return Shell(weights=W, faces=f, canon=q, aux=np.zeros_like(q), hem=thick, edge=np.zeros(len(q)),
                 theta=np.zeros(len(q)), radius=np.zeros(len(q)), material=tx.HAIR)  # fmt: skip


@dataclass
class GarmentState:
    """Pose features that drive the tunic (all from ``body_pose`` only, so an avatar's pose-conditioned
    correction can in principle predict them): hip flexion / abduction per side, spine twist, sway."""

    flex_l: float
    flex_r: float
    abd_l: float
    abd_r: float
    twist: float
    sway: float


def garment_state(body_pose: np.ndarray) -> GarmentState:
    bp = np.asarray(body_pose, dtype=np.float64).reshape(23, 3)
    spine = bp[2] + bp[5] + bp[8]  # spine1, spine2, spine3 (SMPL joints 3, 6, 9)
    # SMPL axes: leg forward = negative rotation about x; left leg outward = positive about z.
    return GarmentState(flex_l=-bp[0, 0], flex_r=-bp[1, 0], abd_l=bp[0, 2], abd_r=-bp[1, 2],
                        twist=spine[1], sway=spine[2])  # fmt: skip


def pose_shell(shell: Shell, verts: np.ndarray, normals: np.ndarray, root_rot: np.ndarray,
               state: GarmentState | None) -> np.ndarray:
    """Posed shell vertices ``[S,3]`` from posed body ``verts [V,3]``, ``normals [V,3]``, the root's
    world rotation ``root_rot [3,3]`` (global_orient) and the tunic's pose state (None: rigid offset
    ``shell.hem`` metres, as used by the hair cap)."""
    base = shell.weights @ verts
    n = shell.weights @ normals
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    if state is None:
        return base + n * shell.hem[:, None]
    h, th, r = shell.hem, shell.theta, shell.radius
    s = state
    # Flare and folds along the normal (folds only push outwards, so the tunic never enters the body).
    asym = abs(s.flex_l - s.flex_r) + abs(s.abd_l - s.abd_r) + 2.0 * abs(s.twist)
    amp = h * (0.003 + 0.010 * np.tanh(3.0 * asym))
    phase = 5.0 * s.twist + 3.0 * (s.flex_l - s.flex_r) + 2.0 * (s.abd_l - s.abd_r)
    folds = amp * (0.5 + 0.5 * np.sin(8.0 * th + phase + 6.0 * h))
    d_n = 0.010 + 0.018 * h**1.5 + folds
    # Hem swing in the pelvis frame: it lags the torso twist and follows the hip sway; the thighs push
    # the front (flexion) or back (extension) of the hem on their side.
    alpha = h * (-1.2 * s.twist + 0.6 * s.sway)
    tang = np.stack([np.cos(th), np.zeros_like(th), -np.sin(th)], 1) * (alpha * r)[:, None]
    left = tx.smoothstep(-0.03, 0.05, r * np.sin(th))
    right = tx.smoothstep(-0.03, 0.05, -r * np.sin(th))
    front = np.clip(np.cos(th), 0.0, 1.0)
    back = np.clip(-np.cos(th), 0.0, 1.0)
    push = np.zeros_like(base)
    for side, flex, abd in ((left, s.flex_l, s.abd_l), (right, s.flex_r, s.abd_r)):
        fwd = 0.07 * max(flex, 0.0) * front - 0.05 * max(-flex, 0.0) * back
        push[:, 2] += h * side * fwd
        push[:, 1] += h * side * 0.3 * np.abs(fwd)
        push[:, 0] += h * side * 0.05 * abd * np.sign(np.sin(th))
    offset = (tang + push) @ root_rot.T
    return base + n * d_n[:, None] + offset
