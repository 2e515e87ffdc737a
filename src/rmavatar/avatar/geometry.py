"""Triangle frames, the posed mesh's face table and quaternion helpers (quaternions are w, x, y, z,
Hamilton product).

All functions are batched over leading dimensions and differentiable.
"""

from __future__ import annotations

import numpy as np
import torch

from rmavatar.render.project import UNIT_EPS, quat_to_rotmat, unit_backward, unit_forward  # quat_to_rotmat: API
from rmavatar.utils.device import constant

# Below this length a vector is treated as zero: a degenerate triangle then gets a zero scale w
# (its Gaussians collapse onto its centroid) instead of NaNs.
_EPS = UNIT_EPS


class _UnitRows(torch.autograd.Function):
    """v / max(|v|, eps) along the last dimension, with the backward written out
    (:func:`rmavatar.render.project.unit_backward`: 6 operations where autograd records about 11)."""

    @staticmethod
    def forward(ctx, v, eps):
        u, n, nc = unit_forward(v, eps)
        ctx.save_for_backward(u, n, nc)
        ctx.eps = eps
        return u

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        u, n, nc = ctx.saved_tensors
        return unit_backward(g, u, n, nc, ctx.eps), None

    @staticmethod
    def reference(v: torch.Tensor, eps: float) -> torch.Tensor:
        """The same under plain autograd (for tests)."""
        return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


def unit_rows(v: torch.Tensor, eps: float = _EPS) -> torch.Tensor:
    """Rows of ``v`` [...,k] scaled to unit length (a row shorter than ``eps`` is divided by ``eps``)."""
    return _UnitRows.apply(v, eps)


def triangle_frames(
    vertices: torch.Tensor, faces: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Local frame of every triangle of a batch of meshes (docs/model.md).

    For face (v0, v1, v2): a0 = normalize(v1 - v0); a1 = normalize(a0 x (v2 - v0)) (the normal);
    a2 = a0 x a1 (in the triangle's plane); R = [a0 a1 a2] as columns (a proper rotation);
    w = (|v1 - v0| + |a2 . (v2 - v0)|) / 2, the mean of one edge and its perpendicular height;
    M = centroid.

    vertices [B,V,3] (or [V,3]), faces [F,3] long -> R [B,F,3,3], w [B,F], M [B,F,3]
    (without the batch dimension when vertices has none).
    """
    if vertices.shape[-1] != 3 or vertices.dim() not in (2, 3):
        raise ValueError(f"vertices must be [B,V,3] or [V,3], got {tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F,3], got {tuple(faces.shape)}")
    # [B,F,3,3]: corner, xyz; index_select, whose backward (index_add) is faster on CPU than indexing's
    # (docs/model.md, "Measured choices")
    tri = vertices.index_select(-2, faces.reshape(-1)).unflatten(-2, faces.shape)
    e1, e2 = (tri[..., 1:, :] - tri[..., :1, :]).unbind(-2)  # both edges from v0 in one operation
    n1 = torch.linalg.vector_norm(e1, dim=-1, keepdim=True)
    a0 = e1 / n1.clamp_min(_EPS)
    a1 = unit_rows(torch.linalg.cross(a0, e2, dim=-1))
    a2 = torch.linalg.cross(a0, a1, dim=-1)
    R = torch.stack((a0, a1, a2), dim=-1)
    w = 0.5 * (n1.squeeze(-1) + (a2 * e2).sum(-1).abs())
    M = tri.mean(-2)
    return R, w, M


def _left_table() -> tuple:
    """[4,16]: a @ table = L(a) flattened, where L(a) b = a (x) b (Hamilton product, wxyz)."""
    # L(a)[i][j] = sign * a[k], written as (k, sign) per entry.
    L = (((0, 1), (1, -1), (2, -1), (3, -1)),
         ((1, 1), (0, 1), (3, -1), (2, 1)),
         ((2, 1), (3, 1), (0, 1), (1, -1)),
         ((3, 1), (2, -1), (1, 1), (0, 1)))
    table = [[0.0] * 16 for _ in range(4)]
    for i, row in enumerate(L):
        for j, (k, sign) in enumerate(row):
            table[k][4 * i + j] = float(sign)
    return tuple(map(tuple, table))


def _shepperd_table() -> tuple:
    """[10,16]: [1, R flattened] @ table = the symmetric matrix K whose row k is 4 q_k q (R = R(q)).

    Diagonal: 1 +- m00 +- m11 +- m22 (4 w^2, 4 x^2, 4 y^2, 4 z^2); off the diagonal the sums and
    differences of R's symmetric entries (4 w x = m21 - m12, 4 x y = m10 + m01, ...)."""
    m = {(r, c): 1 + 3 * r + c for r in range(3) for c in range(3)}  # column of m_rc ([0] is the 1)
    diag = ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))
    off = {(0, 1): ((2, 1, 1), (1, 2, -1)), (0, 2): ((0, 2, 1), (2, 0, -1)), (0, 3): ((1, 0, 1), (0, 1, -1)),
           (1, 2): ((1, 0, 1), (0, 1, 1)), (1, 3): ((0, 2, 1), (2, 0, 1)), (2, 3): ((2, 1, 1), (1, 2, 1))}
    table = [[0.0] * 16 for _ in range(10)]
    for k, signs in enumerate(diag):
        table[0][5 * k] = 1.0
        for d, sign in enumerate(signs):
            table[m[d, d]][5 * k] = float(sign)
    for (i, j), terms in off.items():
        for r, c, sign in terms:
            table[m[r, c]][4 * i + j] = table[m[r, c]][4 * j + i] = float(sign)
    return tuple(map(tuple, table))


def _right_table() -> tuple:
    """[4,16]: b @ table = R(b) flattened, where R(b) a = a (x) b (Hamilton product, wxyz).

    From _left_table's entries: (a (x) b)_i = sum_j sign_ij a[k_ij] b[j], so R(b)[i][k_ij] = sign_ij b[j]."""
    left = _left_table()
    table = [[0.0] * 16 for _ in range(4)]
    for k in range(4):
        for ij, sign in enumerate(left[k]):
            if sign:
                i, j = divmod(ij, 4)
                table[j][4 * i + k] = sign
    return tuple(map(tuple, table))


_LEFT = _left_table()
_RIGHT = _right_table()
_SHEPPERD = _shepperd_table()


def quat_identity(dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """The identity quaternion (1, 0, 0, 0) [4]; one cached tensor per dtype and device (read-only)."""
    return constant((1.0, 0.0, 0.0, 0.0), dtype, device or "cpu")


def quat_left_matrix(a: torch.Tensor) -> torch.Tensor:
    """L(a) [...,4,4] with L(a) b = a (x) b for quaternions a [...,4] (wxyz): one matrix product."""
    return (a @ constant(_LEFT, a.dtype, a.device)).unflatten(-1, (4, 4))


def quat_right_matrix(b: torch.Tensor) -> torch.Tensor:
    """R(b) [...,4,4] with R(b) a = a (x) b for quaternions b [...,4] (wxyz): one matrix product."""
    return (b @ constant(_RIGHT, b.dtype, b.device)).unflatten(-1, (4, 4))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a (x) b of quaternions [...,4] (wxyz); rotation of a after b."""
    return (quat_left_matrix(a) @ b.unsqueeze(-1)).squeeze(-1)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [...,4] (wxyz, w >= 0 where possible) of rotation matrices [...,3,3].

    Shepperd's method: row k of K (see _shepperd_table) is 4 q_k q, so each element uses the row
    with the largest diagonal entry (the largest |q_k|, at least 1/2), normalised: the result stays
    accurate (and gradients finite) for every rotation.
    """
    table = constant(_SHEPPERD, R.dtype, R.device)
    K = torch.addmm(table[0], R.reshape(-1, 9), table[1:]).reshape(R.shape[:-2] + (4, 4))
    # argmax over the strided diagonal view is ten times slower on the CPU than over a contiguous copy
    best = K.diagonal(dim1=-2, dim2=-1).contiguous().argmax(-1, keepdim=True)
    row = torch.gather(K, -2, best.unsqueeze(-1).expand(best.shape + (4,))).squeeze(-2)
    norm = torch.linalg.vector_norm(row, dim=-1, keepdim=True).clamp_min(_EPS)
    return row / torch.where(row[..., :1] < 0, -norm, norm)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v [...,3] by quaternions q [...,4] (wxyz; normalised here)."""
    return (quat_to_rotmat(q) @ v.unsqueeze(-1)).squeeze(-1)


class FaceTable:
    """The columns of a posed mesh's face table (``Avatar.face_table``: one row per binding face, built by
    :meth:`rows`), as slices; every reader of the table indexes it with these.

    R: the frame R [3,3] row-major; wR: w R [3,3] row-major; M: the centroid [3]; w: the scale [1];
    L: L(quat(R)) [4,4] row-major, the matrix of r -> quat(R) (x) r. With them mu* = w R mu + M and
    r* = quat(R) (x) r are one batched matrix product each."""

    R = slice(0, 9)
    wR = slice(9, 18)
    M = slice(18, 21)
    w = slice(21, 22)
    L = slice(22, 38)
    WIDTH = 38  # the columns in all, in the order above

    @staticmethod
    def rows(R: torch.Tensor, w: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
        """The table [..., WIDTH] of frames R [...,3,3], scales w [...] and centroids M [...,3] (as from
        :func:`triangle_frames`)."""
        R9 = R.flatten(-2)
        return torch.cat((R9, w.unsqueeze(-1) * R9, M, w.unsqueeze(-1),
                          quat_left_matrix(rotmat_to_quat(R)).flatten(-2)), dim=-1)


class _FaceTableCPU(torch.autograd.Function):
    """The face table of one mesh on the CPU by the numba kernels of :mod:`rmavatar.avatar.face_kernels`
    (the same formulas as ``FaceTable.rows(*triangle_frames(...))``, to rounding)."""

    @staticmethod
    def forward(ctx, vertices, faces):
        from rmavatar.avatar.face_kernels import face_table_forward

        v, f = _cpu_arrays(vertices, faces)
        out = np.empty((f.shape[0], FaceTable.WIDTH), v.dtype)
        face_table_forward(v, f, _TABLES["shepperd"], _TABLES["left"], _EPS, out, np.empty((f.shape[0], 13)))
        ctx.save_for_backward(vertices, faces)
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        from rmavatar.avatar.face_kernels import face_table_backward

        vertices, faces = ctx.saved_tensors
        v, f = _cpu_arrays(vertices, faces)
        corners = np.empty((f.shape[0], 3, 3), v.dtype)
        face_table_backward(v, f, _TABLES["shepperd"], _TABLES["left"], _EPS,
                            g.detach().to(vertices.dtype).contiguous().numpy(), corners, np.empty((f.shape[0], 26)))
        g_vertices = torch.zeros_like(vertices)
        return g_vertices.index_add_(0, faces.reshape(-1), torch.from_numpy(corners).reshape(-1, 3)), None


_TABLES = {"shepperd": np.asarray(_SHEPPERD, dtype=np.float64), "left": np.asarray(_LEFT, dtype=np.float64)}


def _cpu_arrays(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    return vertices.detach().contiguous().numpy(), faces.to(torch.int64).contiguous().numpy()


def face_table(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The face table [...,F,FaceTable.WIDTH] of faces [F,3] of meshes vertices [V,3] or [B,V,3]:
    ``FaceTable.rows(*triangle_frames(vertices, faces))``. One mesh on the CPU whose gradient is wanted
    (pose fits: ``Avatar.face_table(..., kernels=True)``) goes through numba kernels, about twice as fast
    forward and backward there (docs/model.md, "Measured choices"); every other case through those torch
    formulas."""
    if (vertices.dim() == 2 and vertices.device.type == "cpu" and vertices.requires_grad and torch.is_grad_enabled()
            and vertices.dtype in (torch.float32, torch.float64)):
        return _FaceTableCPU.apply(vertices, faces)
    return FaceTable.rows(*triangle_frames(vertices, faces))


def same_quads(a, b) -> bool:
    """Whether ``a`` and ``b`` [F,3] triangulate one mesh alike but for the diagonal that splits some of
    its quads: every row where they differ is one of the two consecutive rows of a quad (the order in
    which the body models split their quads), and both split the same quad, the same way round (its
    four boundary edges in the same directions, so its normals agree).

    Why: Anny splits each quad along its shorter diagonal, measured in floating point, and on its eyes'
    regular grid the two diagonals are equal but for the last bit, so machines whose arithmetic rounds
    differently split a few quads the other way (6 of 13,710 between two machines here): the same body,
    one checkpoint, two triangulations. An avatar keeps the triangulation it was trained on."""
    a, b = (np.asarray(torch.as_tensor(t).cpu(), dtype=np.int64) for t in (a, b))
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        return False
    rows = np.nonzero((a != b).any(1))[0]
    first, second = rows[0::2], rows[1::2]
    if len(first) != len(second) or not np.array_equal(second, first + 1):
        return False
    return all(_quad_boundary(a[i], a[i + 1]) == _quad_boundary(b[i], b[i + 1]) is not None for i in first)


def _quad_boundary(t1, t2) -> frozenset | None:
    """The directed boundary edges of the quad that triangles ``t1``, ``t2`` split (the diagonal, the
    one edge the two share, run opposite ways); None if they do not split a quad so."""
    edges = [(int(t[k]), int(t[(k + 1) % 3])) for t in (t1, t2) for k in range(3)]
    inner = [e for e in edges if (e[1], e[0]) in edges]
    if len(inner) != 2 or len(set(edges)) != 6:
        return None
    return frozenset(e for e in edges if e not in inner)
