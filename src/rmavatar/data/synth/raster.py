"""A z-buffered, supersampled triangle-mesh rasterizer (Numba, parallel over screen tiles).

It renders the synthetic subject's ground truth. It shares no code with the Gaussian rasterizer on
purpose, so that a bug there cannot hide in the images we measure it against.

Conventions (the same as the Gaussian rasterizer's): OpenCV pinhole camera, ``viewmat`` maps world to
camera (x right, y down, z forward), ``u = fx x / z + cx``; pixel ``(row i, col j)`` covers
``[j, j+1) x [i, i+1)`` in continuous pixel coordinates, so its centre is at ``(j + 0.5, i + 0.5)``.
With ``ss`` x ``ss`` supersampling the samples sit at ``j + (k + 0.5) / ss``; for odd ``ss`` the middle
sample is the pixel centre.

The rasterizer returns fragments (face id, perspective-correct barycentrics, depth) per sample;
attributes are interpolated from them with :func:`interpolate` and box-filtered down with
:func:`resolve`, so anti-aliasing is the mean over the samples of a pixel and the soft mask is coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

_TILE = 16  # samples per tile side: small enough to balance work over threads, large enough to bin cheaply


@dataclass
class Fragments:
    """Per-sample rasterization result on the supersampled grid ``[H*ss, W*ss]``.

    ``face_id`` int32 (-1 where no triangle covers the sample), ``bary`` float32 ``[Hs, Ws, 3]``
    perspective-correct barycentric weights of the face's three vertices, ``depth`` float32 camera z
    (``inf`` where empty), ``ss`` the supersampling factor.
    """

    face_id: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    ss: int

    @property
    def covered(self) -> np.ndarray:
        """Bool ``[Hs, Ws]``: samples covered by any triangle."""
        return self.face_id >= 0


def world_to_camera(verts: np.ndarray, viewmat: np.ndarray) -> np.ndarray:
    """Transform points ``[V,3]`` by a 4x4 world->camera matrix; returns ``[V,3]`` float64."""
    verts = np.asarray(verts, dtype=np.float64)
    viewmat = np.asarray(viewmat, dtype=np.float64)
    return verts @ viewmat[:3, :3].T + viewmat[:3, 3]


@numba.njit(cache=True, inline="always")
def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@numba.njit(cache=True, inline="always")
def _edge_canonical(ia, ib, ax, ay, bx, by, px, py):
    # Evaluate a shared edge with its vertices in index order, so the two triangles that share it get
    # bit-identical values of opposite sign: a sample exactly on the edge then goes to exactly one.
    if ia < ib:
        return _edge(ax, ay, bx, by, px, py)
    return -_edge(bx, by, ax, ay, px, py)


@numba.njit(cache=True, inline="always")
def _owns_tie(ia, ib, ax, ay, bx, by):
    # Tie rule on the canonical (index-ordered) direction; the opposite triangle sees the reversed
    # direction, so exactly one of the two owns samples lying on the edge.
    if ia < ib:
        dx = bx - ax
        dy = by - ay
        return dy > 0 or (dy == 0 and dx < 0)
    dx = ax - bx
    dy = ay - by
    return not (dy > 0 or (dy == 0 and dx < 0))


@numba.njit(cache=True)
def _bin(sx, sy, sz, faces, ws, hs, near, tiles_x, tiles_y):
    nf = faces.shape[0]
    ntiles = tiles_x * tiles_y
    bbox = np.full((nf, 4), -1, dtype=np.int64)  # tile x0, x1, y0, y1 (inclusive); -1 = culled
    counts = np.zeros(ntiles + 1, dtype=np.int64)
    for f in range(nf):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        if sz[i0] <= near or sz[i1] <= near or sz[i2] <= near:
            continue  # the subject is always well in front of the camera; no clipping needed
        xmin = min(sx[i0], min(sx[i1], sx[i2]))
        xmax = max(sx[i0], max(sx[i1], sx[i2]))
        ymin = min(sy[i0], min(sy[i1], sy[i2]))
        ymax = max(sy[i0], max(sy[i1], sy[i2]))
        c0 = max(int(np.ceil(xmin)), 0)
        c1 = min(int(np.floor(xmax)), ws - 1)
        r0 = max(int(np.ceil(ymin)), 0)
        r1 = min(int(np.floor(ymax)), hs - 1)
        if c0 > c1 or r0 > r1:
            continue
        tx0, tx1, ty0, ty1 = c0 // _TILE, c1 // _TILE, r0 // _TILE, r1 // _TILE
        bbox[f, 0], bbox[f, 1], bbox[f, 2], bbox[f, 3] = tx0, tx1, ty0, ty1
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    lists = np.empty(offsets[-1], dtype=np.int64)
    for f in range(nf):  # ascending face order per tile keeps the result independent of threads
        if bbox[f, 0] < 0:
            continue
        for ty in range(bbox[f, 2], bbox[f, 3] + 1):
            for tx in range(bbox[f, 0], bbox[f, 1] + 1):
                t = ty * tiles_x + tx
                lists[fill[t]] = f
                fill[t] += 1
    return offsets, lists


@numba.njit(cache=True, parallel=True)
def _raster(sx, sy, sz, faces, ws, hs, offsets, lists, tiles_x, tiles_y, face_id, bary, depth):
    for t in numba.prange(tiles_x * tiles_y):
        tx = t % tiles_x
        ty = t // tiles_x
        tc0 = tx * _TILE
        tr0 = ty * _TILE
        tc1 = min(tc0 + _TILE, ws) - 1
        tr1 = min(tr0 + _TILE, hs) - 1
        for k in range(offsets[t], offsets[t + 1]):
            f = lists[k]
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            x0, y0, x1, y1, x2, y2 = sx[i0], sy[i0], sx[i1], sy[i1], sx[i2], sy[i2]
            area = _edge(x0, y0, x1, y1, x2, y2)
            if area == 0.0:
                continue
            # Double-sided: make the winding positive by swapping the last two vertices.
            if area < 0:
                i1, i2 = i2, i1
                x1, y1, x2, y2 = x2, y2, x1, y1
                area = -area
            z0, z1, z2 = sz[i0], sz[i1], sz[i2]
            c0 = max(int(np.ceil(min(x0, min(x1, x2)))), tc0)
            c1 = min(int(np.floor(max(x0, max(x1, x2)))), tc1)
            r0 = max(int(np.ceil(min(y0, min(y1, y2)))), tr0)
            r1 = min(int(np.floor(max(y0, max(y1, y2)))), tr1)
            own0 = _owns_tie(i1, i2, x1, y1, x2, y2)
            own1 = _owns_tie(i2, i0, x2, y2, x0, y0)
            own2 = _owns_tie(i0, i1, x0, y0, x1, y1)
            for r in range(r0, r1 + 1):
                py = float(r)
                for c in range(c0, c1 + 1):
                    px = float(c)
                    e0 = _edge_canonical(i1, i2, x1, y1, x2, y2, px, py)
                    if e0 < 0 or (e0 == 0 and not own0):
                        continue
                    e1 = _edge_canonical(i2, i0, x2, y2, x0, y0, px, py)
                    if e1 < 0 or (e1 == 0 and not own1):
                        continue
                    e2 = _edge_canonical(i0, i1, x0, y0, x1, y1, px, py)
                    if e2 < 0 or (e2 == 0 and not own2):
                        continue
                    # Screen-space weights -> perspective-correct ones via 1/z interpolation.
                    l0 = e0 / area
                    l1 = e1 / area
                    l2 = e2 / area
                    w0 = l0 / z0
                    w1 = l1 / z1
                    w2 = l2 / z2
                    inv_z = w0 + w1 + w2
                    z = 1.0 / inv_z
                    if z < depth[r, c]:
                        depth[r, c] = z
                        face_id[r, c] = f
                        # Weights belong to the face's own vertex order, undo the winding swap.
                        b0 = w0 * z
                        b1 = w1 * z
                        b2 = w2 * z
                        bary[r, c, 0] = b0
                        if faces[f, 1] == i1:
                            bary[r, c, 1] = b1
                            bary[r, c, 2] = b2
                        else:
                            bary[r, c, 1] = b2
                            bary[r, c, 2] = b1


def rasterize(
    verts_cam: np.ndarray,
    faces: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    ss: int = 3,
    near: float = 1e-3,
) -> Fragments:
    """Rasterize a triangle mesh seen by an OpenCV pinhole camera.

    verts_cam [V,3] camera-space positions (OpenCV: z forward), faces [F,3] vertex indices,
    K [3,3] intrinsics for the ``width`` x ``height`` image, ``ss`` samples per pixel side.
    Triangles are double-sided; a triangle with a vertex at ``z <= near`` is skipped (no clipping).
    Returns :class:`Fragments` on the ``[height*ss, width*ss]`` sample grid.
    """
    if ss < 1:
        raise ValueError(f"ss must be >= 1, got {ss}")
    verts_cam = np.asarray(verts_cam, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    K = np.asarray(K, dtype=np.float64)
    z = verts_cam[:, 2]
    zs = np.where(z > near, z, np.inf)
    u = K[0, 0] * verts_cam[:, 0] / zs + K[0, 1] * verts_cam[:, 1] / zs + K[0, 2]
    v = K[1, 1] * verts_cam[:, 1] / zs + K[1, 2]
    # Sample (r, c) sits at pixel coordinate ((c + 0.5) / ss, (r + 0.5) / ss): in sample units the
    # samples are the integer lattice.
    sx = np.ascontiguousarray(u * ss - 0.5)
    sy = np.ascontiguousarray(v * ss - 0.5)
    sz = np.ascontiguousarray(z)
    ws, hs = width * ss, height * ss
    tiles_x = (ws + _TILE - 1) // _TILE
    tiles_y = (hs + _TILE - 1) // _TILE
    offsets, lists = _bin(sx, sy, sz, faces, ws, hs, near, tiles_x, tiles_y)
    face_id = np.full((hs, ws), -1, dtype=np.int32)
    bary = np.zeros((hs, ws, 3), dtype=np.float32)
    depth = np.full((hs, ws), np.inf, dtype=np.float64)
    _raster(sx, sy, sz, faces, ws, hs, offsets, lists, tiles_x, tiles_y, face_id, bary, depth)
    return Fragments(face_id=face_id, bary=bary, depth=depth.astype(np.float32), ss=ss)


def interpolate(frags: Fragments, faces: np.ndarray, attrs: np.ndarray) -> np.ndarray:
    """Interpolate per-vertex attributes ``attrs [V,C]`` at every covered sample.

    Returns float32 ``[Hs, Ws, C]``, zero where no triangle covers the sample.
    """
    attrs = np.asarray(attrs, dtype=np.float32)
    if attrs.ndim == 1:
        attrs = attrs[:, None]
    out = np.zeros(frags.face_id.shape + (attrs.shape[1],), dtype=np.float32)
    hit = frags.covered
    corners = np.asarray(faces)[frags.face_id[hit]]  # [M,3]
    w = frags.bary[hit]  # [M,3]
    out[hit] = np.einsum("mk,mkc->mc", w, attrs[corners])
    return out


def resolve(samples: np.ndarray, ss: int) -> np.ndarray:
    """Box-filter a supersampled buffer ``[H*ss, W*ss, ...]`` down to ``[H, W, ...]`` (mean)."""
    hs, ws = samples.shape[:2]
    h, w = hs // ss, ws // ss
    return samples.reshape((h, ss, w, ss) + samples.shape[2:]).mean(axis=(1, 3))
