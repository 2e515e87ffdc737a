"""Render the dressed subject in one pose: rasterize body + shells, texture and shade every sample,
box-filter to pixels, composite over the background."""

from __future__ import annotations

import numpy as np

from rmavatar.data.synth import texture as tx
from rmavatar.data.synth.raster import rasterize, resolve, world_to_camera
from rmavatar.data.synth.subject import (
    GarmentState,
    Subject,
    pose_shell,
    vertex_normals,
)

# Light: a key light from the camera's upper left plus ambient, fixed in camera space so every
# view of the turning person is lit alike (as a camera-mounted light would).
_LIGHT_DIR = np.array([-0.45, -0.55, -0.70])
_AMBIENT = 0.42
_DIFFUSE = 0.62


def posed_mesh(subject: Subject, verts: np.ndarray, root_rot: np.ndarray, state: GarmentState):
    """Assemble body + tunic + hair for one pose.

    Returns (verts [N,3], normals [N,3], faces [F,3], canon [N,3], aux [N,3], extra [N,2] (hem weight,
    edge weight), face_material [F]).
    """
    verts = np.asarray(verts, dtype=np.float64)
    normals = vertex_normals(verts, subject.faces)
    tv = pose_shell(subject.tunic, verts, normals, root_rot, state)
    hv = pose_shell(subject.hair, verts, normals, root_rot, None)
    parts_v = [verts, tv, hv]
    parts_f = [subject.faces, subject.tunic.faces, subject.hair.faces]
    offsets = np.cumsum([0] + [len(v) for v in parts_v])
    all_v = np.concatenate(parts_v)
    all_f = np.concatenate([f + o for f, o in zip(parts_f, offsets)])
    all_n = vertex_normals(all_v, all_f)
    canon = np.concatenate([subject.canon, subject.tunic.canon, subject.hair.canon])
    aux = np.concatenate([subject.aux, subject.tunic.aux, subject.hair.aux])
    zeros = np.zeros((len(verts), 2))
    extra = np.concatenate([zeros, np.stack([subject.tunic.hem, subject.tunic.edge], 1),
                            np.zeros((len(hv), 2))])  # fmt: skip
    mat = np.concatenate([subject.face_material, np.full(len(subject.tunic.faces), subject.tunic.material),
                          np.full(len(subject.hair.faces), subject.hair.material)])  # fmt: skip
    return all_v, all_n, all_f, canon, aux, extra, mat


def render(subject: Subject, verts: np.ndarray, root_rot: np.ndarray, state: GarmentState, K: np.ndarray,
           viewmat: np.ndarray, width: int, height: int, ss: int = 3,
           background=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Render one frame. ``verts [V,3]`` posed body (world), ``root_rot [3,3]`` the global orientation,
    ``state`` the tunic's pose state, camera ``K [3,3]``, ``viewmat [4,4]`` (world->camera, OpenCV).

    Returns (image [H,W,3] float32 in 0..1 composited over ``background``, mask [H,W] float32 coverage).
    """
    v, n, f, canon, aux, extra, mat = posed_mesh(subject, verts, root_rot, state)
    vc = world_to_camera(v, viewmat)
    nc = n @ np.asarray(viewmat, dtype=np.float64)[:3, :3].T
    frags = rasterize(vc, f, K, width, height, ss=ss)
    hit = frags.covered
    fid = frags.face_id[hit]
    w = frags.bary[hit]

    def lerp(attr):
        return np.einsum("mk,mkc->mc", w, np.asarray(attr, dtype=np.float32)[f[fid]])

    q = lerp(canon)
    a = lerp(aux)
    e = lerp(extra)
    nrm = lerp(nc)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
    pos = lerp(vc)
    view = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    facing = (nrm * view).sum(1)
    inside = facing > 0  # the normal points away from the camera: we see a surface's back side
    nrm[inside] *= -1
    m = mat[fid]

    albedo = np.zeros((len(q), 3), dtype=np.float32)
    pal, lm, seed = subject.palette, subject.landmarks, subject.seed
    for mid in np.unique(m):
        sel = m == mid
        qs = q[sel]
        if mid == tx.SKIN:
            col = tx.skin(qs, pal, seed)
        elif mid == tx.HEAD:
            col = tx.head(qs, lm, pal, seed)
        elif mid == tx.EYE:
            left = qs[:, 0] > 0.5 * (lm.eye_l[0] + lm.eye_r[0])
            col = np.where(left[:, None], tx.eye(qs, lm.eye_l, pal), tx.eye(qs, lm.eye_r, pal))
        elif mid == tx.MOUTH:
            col = np.broadcast_to(np.array([0.30, 0.08, 0.08], np.float32), (len(qs), 3))
        elif mid == tx.LASH:
            col = np.broadcast_to(np.array([0.10, 0.06, 0.05], np.float32), (len(qs), 3))
        elif mid == tx.UNDERSHIRT:
            col = tx.undershirt(qs, lm, pal, seed)
        elif mid == tx.TROUSERS:
            col = tx.trousers(qs, a[sel], lm, pal, seed)
        elif mid == tx.SHOES:
            col = tx.shoes(qs, lm, pal, seed)
        elif mid == tx.TUNIC:
            col = tx.tunic(qs, a[sel], e[sel, 1], lm, pal, seed, inside[sel])
        elif mid == tx.HAIR:
            col = tx.hair_shell(qs, pal, seed)
        else:  # pragma: no cover - every material id is handled above
            raise ValueError(f"unknown material {mid}")
        albedo[sel] = col

    light = _LIGHT_DIR / np.linalg.norm(_LIGHT_DIR)
    lambert = np.clip(nrm @ light, 0.0, None)
    # A little rim darkening towards grazing angles reads as soft occlusion on the limbs' sides.
    rim = 0.85 + 0.15 * np.clip(-facing * np.where(inside, -1, 1), 0.0, 1.0)
    shade = (_AMBIENT + _DIFFUSE * lambert) * rim
    shade = np.where(inside, shade * 0.7, shade)
    col = np.clip(albedo * shade[:, None], 0.0, 1.0)

    hs, ws = frags.face_id.shape
    samples = np.empty((hs, ws, 3), dtype=np.float32)
    samples[:] = np.asarray(background, dtype=np.float32)
    samples[hit] = col
    image = resolve(samples, ss).astype(np.float32)
    mask = resolve(hit.astype(np.float32), ss).astype(np.float32)
    return image, mask

