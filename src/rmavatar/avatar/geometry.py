"""Triangle frames and quaternion helpers (quaternions are w, x, y, z, Hamilton product).

All functions are batched over leading dimensions and differentiable.
"""

from __future__ import annotations

import math

import torch

from rmavatar.render.project import quat_to_rotmat, sh_basis  # quat_to_rotmat: part of this module's API

# Below this length a vector is treated as zero: a degenerate triangle then gets a zero scale w
# (its Gaussians collapse onto its centroid) instead of NaNs.
_EPS = 1e-12


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(_EPS)


def triangle_frames(
    vertices: torch.Tensor, faces: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Local frame of every triangle of a batch of meshes (SPEC §2).

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
    tri = vertices[..., faces, :]  # [B,F,3,3]: corner, xyz
    v0, v1, v2 = tri.unbind(-2)
    e1 = v1 - v0
    e2 = v2 - v0
    a0 = _normalize(e1)
    a1 = _normalize(torch.linalg.cross(a0, e2, dim=-1))
    a2 = torch.linalg.cross(a0, a1, dim=-1)
    R = torch.stack((a0, a1, a2), dim=-1)
    w = 0.5 * (torch.linalg.vector_norm(e1, dim=-1) + (a2 * e2).sum(-1).abs())
    M = (v0 + v1 + v2) / 3.0
    return R, w, M


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a (x) b of quaternions [...,4] (wxyz); rotation of a after b."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [...,4] (wxyz, w >= 0 where possible) of rotation matrices [...,3,3].

    Shepperd's method: of the four algebraically equal formulas, each element uses the one with
    the largest denominator, so the result stays accurate (and gradients finite) for every rotation.
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    t = torch.stack(
        (
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ),
        dim=-1,
    )  # 4 w^2, 4 x^2, 4 y^2, 4 z^2
    a, b, c = m21 - m12, m02 - m20, m10 - m01
    d, e, f = m10 + m01, m02 + m20, m21 + m12
    cand = torch.stack(
        (
            torch.stack((t[..., 0], a, b, c), -1),
            torch.stack((a, t[..., 1], d, e), -1),
            torch.stack((b, d, t[..., 2], f), -1),
            torch.stack((c, e, f, t[..., 3]), -1),
        ),
        dim=-2,
    )  # [...,4 candidates,4]
    cand = cand / (2.0 * t.clamp_min(1e-8).sqrt()).unsqueeze(-1)
    best = t.argmax(-1, keepdim=True)
    q = torch.gather(cand, -2, best.unsqueeze(-1).expand(best.shape + (4,))).squeeze(-2)
    q = torch.where(q[..., :1] < 0, -q, q)
    return _normalize(q)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v [...,3] by quaternions q [...,4] (wxyz; normalised here)."""
    return (quat_to_rotmat(q) @ v.unsqueeze(-1)).squeeze(-1)


def _sample_dirs(n: int) -> torch.Tensor:
    """``n`` well-spread unit directions [n,3] (a Fibonacci sphere), float64."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = torch.sqrt(1.0 - z * z)
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), dim=-1)


def sh_rotation_matrices(R: torch.Tensor, degree: int) -> list[torch.Tensor]:
    """Per-band matrices that carry SH coefficients from a local frame to the world.

    R [F,3,3] rotates local to world. For band l the matrix M_l [F,2l+1,2l+1] satisfies
    Y_l(R^T d) = Y_l(d) M_l for every direction d (Y_l the band's basis row, gsplat's convention), so
    coefficients c_local evaluated along local directions equal c_world = M_l c_local evaluated along
    world directions. Solved exactly by least squares over fixed sample directions (bands are closed
    under rotation). Returns [M_1, ..., M_degree] (band 0 is invariant).
    """
    dirs = _sample_dirs(20)  # one set for every band: the 20x16 basis matrix has full column rank
    world = sh_basis(degree, dirs)  # [S,K]
    local_dirs = torch.einsum("fji,sj->fsi", R, dirs.to(R.dtype))  # R^T d for every face
    local = sh_basis(degree, local_dirs.reshape(-1, 3)).reshape(R.shape[0], dirs.shape[0], -1)  # [F,S,K]
    mats = []
    for band in range(1, degree + 1):
        lo, hi = band * band, (band + 1) ** 2
        pinv = torch.linalg.pinv(world[:, lo:hi]).to(R.dtype)  # [2l+1,S]
        mats.append(torch.einsum("ks,fsj->fkj", pinv, local[..., lo:hi]))
    return mats


def rotate_sh(sh: torch.Tensor, mats: list[torch.Tensor]) -> torch.Tensor:
    """SH coefficients sh [N,K,3] in local frames -> world axes, row i with the band matrices
    mats[l-1][i] of :func:`sh_rotation_matrices`. Bands beyond len(mats) are not allowed."""
    degree = math.isqrt(sh.shape[1]) - 1
    if degree > len(mats):
        raise ValueError(f"sh has degree {degree} but only {len(mats)} band matrices were given")
    out = [sh[:, :1]]
    for band in range(1, degree + 1):
        out.append(mats[band - 1] @ sh[:, band * band:(band + 1) ** 2])
    return torch.cat(out, dim=1)
