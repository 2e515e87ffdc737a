"""The posed mesh's face table on the CPU as numba kernels, forward and backward, one pass over the faces.

Pose fits build the face table of a mesh with gradients on every step.
As torch operations that is some 25 passes over [F,3..16] tensors forward and as many backward, each
too small to use the CPU well; here each face is one iteration with everything in registers. The
formulas are those of :func:`rmavatar.avatar.geometry.triangle_frames` and :meth:`FaceTable.rows`
(the torch path, which every other device runs and the tests compare these with), the backward written
out step by step in reverse. Gradients of the corners are written per face and summed onto the vertices
by the caller (a scatter that would race across threads here); docs/model.md ("Measured choices") has
what they save.
"""

from __future__ import annotations

import math

import numpy as np

from rmavatar.render._numba import numba


@numba.njit(cache=True, nogil=True)
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@numba.njit(cache=True, nogil=True)
def _cross_grads(a, b, g):
    """The gradients of a x b to a and b, for its gradient g: (b x g, g x a); 3-tuples."""
    return _cross(b[0], b[1], b[2], g[0], g[1], g[2]), _cross(g[0], g[1], g[2], a[0], a[1], a[2])


@numba.njit(cache=True, nogil=True)
def _add(a, b):
    return a[0] + b[0], a[1] + b[1], a[2] + b[2]


@numba.njit(cache=True, nogil=True)
def _frame(vertices, faces, f, eps):
    """Face f's corners' edges and frame: e1, e2, a0, a1, a2 (3-tuples), |e1|, |a0 x e2|, d = a2 . e2."""
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    e1 = (vertices[i1, 0] - vertices[i0, 0], vertices[i1, 1] - vertices[i0, 1], vertices[i1, 2] - vertices[i0, 2])
    e2 = (vertices[i2, 0] - vertices[i0, 0], vertices[i2, 1] - vertices[i0, 1], vertices[i2, 2] - vertices[i0, 2])
    n1 = math.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    s = 1.0 / max(n1, eps)
    a0 = (e1[0] * s, e1[1] * s, e1[2] * s)
    c = _cross(a0[0], a0[1], a0[2], e2[0], e2[1], e2[2])
    nc = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    s = 1.0 / max(nc, eps)
    a1 = (c[0] * s, c[1] * s, c[2] * s)
    a2 = _cross(a0[0], a0[1], a0[2], a1[0], a1[1], a1[2])
    d = a2[0] * e2[0] + a2[1] * e2[1] + a2[2] * e2[2]
    return e1, e2, a0, a1, a2, n1, nc, d


@numba.njit(cache=True, nogil=True)
def _quat_row(R, shepperd, row):
    """row [4] = the row of K (Shepperd's method, rotmat_to_quat) with the largest diagonal entry, for
    R [9] (row-major); returns its index."""
    best, top = 0, -1e300
    for k in range(4):
        value = shepperd[0, 5 * k]
        for m in range(9):
            value += R[m] * shepperd[1 + m, 5 * k]
        if value > top:
            best, top = k, value
    for j in range(4):
        value = shepperd[0, 4 * best + j]
        for m in range(9):
            value += R[m] * shepperd[1 + m, 4 * best + j]
        row[j] = value
    return best


@numba.njit(cache=True, nogil=True)
def _frame_rows(vertices, faces, f, eps, R):
    """R [9] = face f's frame (row-major, columns a0 a1 a2); returns _frame's values."""
    e1, e2, a0, a1, a2, n1, nc, d = _frame(vertices, faces, f, eps)
    for i in range(3):
        R[3 * i] = a0[i]
        R[3 * i + 1] = a1[i]
        R[3 * i + 2] = a2[i]
    return e1, e2, a0, a1, a2, n1, nc, d


@numba.njit(parallel=True, cache=True, nogil=True)
def face_table_forward(vertices, faces, shepperd, left, eps, out, work):
    """out [F,38] = the face table of faces [F,3] of vertices [V,3] (columns of FaceTable); work [F,13]
    float64 scratch."""
    for f in numba.prange(faces.shape[0]):
        R, row = work[f, :9], work[f, 9:13]
        e1, e2, a0, a1, a2, n1, nc, d = _frame_rows(vertices, faces, f, eps, R)
        w = 0.5 * (n1 + abs(d))
        for m in range(9):
            out[f, m] = R[m]
            out[f, 9 + m] = w * R[m]
        for i in range(3):
            out[f, 18 + i] = (vertices[faces[f, 0], i] + vertices[faces[f, 1], i] + vertices[faces[f, 2], i]) / 3.0
        out[f, 21] = w
        _quat_row(R, shepperd, row)
        qn = math.sqrt(row[0] * row[0] + row[1] * row[1] + row[2] * row[2] + row[3] * row[3])
        s = 1.0 / max(qn, eps)
        if row[0] < 0:
            s = -s
        for j in range(16):
            value = 0.0
            for k in range(4):
                value += row[k] * s * left[k, j]
            out[f, 22 + j] = value


@numba.njit(parallel=True, cache=True, nogil=True)
def face_table_backward(vertices, faces, shepperd, left, eps, g, g_corners, work):
    """g_corners [F,3,3] = the gradient of each face's three corners from the table's gradient g [F,38];
    work [F,26] float64 scratch."""
    for f in numba.prange(faces.shape[0]):
        R, row, gR, gq = work[f, :9], work[f, 9:13], work[f, 13:22], work[f, 22:26]
        e1, e2, a0, a1, a2, n1, nc, d = _frame_rows(vertices, faces, f, eps, R)
        w = 0.5 * (n1 + abs(d))
        gw = g[f, 21]
        for m in range(9):
            gR[m] = g[f, m] + w * g[f, 9 + m]
            gw += R[m] * g[f, 9 + m]
        # L = L(sign unit(row)), row = K[best], K = [1, R] @ shepperd: back to R through its 9 rows
        best = _quat_row(R, shepperd, row)
        qn = math.sqrt(row[0] * row[0] + row[1] * row[1] + row[2] * row[2] + row[3] * row[3])
        qnc = max(qn, eps)
        sign = -1.0 if row[0] < 0 else 1.0
        dot = 0.0
        for k in range(4):  # gq = sign left gL, the gradient of unit(row), and its dot with unit(row)
            value = 0.0
            for j in range(16):
                value += g[f, 22 + j] * left[k, j]
            gq[k] = sign * value
            dot += row[k] / qnc * gq[k]
        radial = dot if qn > eps else 0.0
        for k in range(4):
            g_row = (gq[k] - row[k] / qnc * radial) / qnc
            for m in range(9):
                gR[m] += g_row * shepperd[1 + m, 4 * best + k]
        ga0, ga1, ga2 = (gR[0], gR[3], gR[6]), (gR[1], gR[4], gR[7]), (gR[2], gR[5], gR[8])
        # w = (|e1| + |a2 . e2|) / 2
        g_d = 0.5 * gw * (1.0 if d > 0 else (-1.0 if d < 0 else 0.0))
        ge2 = (g_d * a2[0], g_d * a2[1], g_d * a2[2])
        ga2 = (ga2[0] + g_d * e2[0], ga2[1] + g_d * e2[1], ga2[2] + g_d * e2[2])
        # a2 = a0 x a1
        ta, tb = _cross_grads(a0, a1, ga2)
        ga0, ga1 = _add(ga0, ta), _add(ga1, tb)
        # a1 = unit(c), c = a0 x e2
        ncc = max(nc, eps)
        dot = (a1[0] * ga1[0] + a1[1] * ga1[1] + a1[2] * ga1[2]) if nc > eps else 0.0
        gc = ((ga1[0] - a1[0] * dot) / ncc, (ga1[1] - a1[1] * dot) / ncc, (ga1[2] - a1[2] * dot) / ncc)
        ta, tb = _cross_grads(a0, e2, gc)
        ga0, ge2 = _add(ga0, ta), _add(ge2, tb)
        # a0 = unit(e1), and |e1| itself in w
        n1c = max(n1, eps)
        dot = (a0[0] * ga0[0] + a0[1] * ga0[1] + a0[2] * ga0[2]) if n1 > eps else 0.0
        norm_grad = 0.5 * gw / n1 if n1 > 0 else 0.0
        for i in range(3):
            ge1 = (ga0[i] - a0[i] * dot) / n1c + norm_grad * e1[i]
            gm = g[f, 18 + i] / 3.0
            g_corners[f, 0, i] = gm - ge1 - ge2[i]
            g_corners[f, 1, i] = gm + ge1
            g_corners[f, 2, i] = gm + ge2[i]
