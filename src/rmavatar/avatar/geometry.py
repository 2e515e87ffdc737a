"""Triangle frames and quaternion helpers (quaternions are w, x, y, z, Hamilton product).

All functions are batched over leading dimensions and differentiable.
"""

from __future__ import annotations

import torch

from rmavatar.render.project import quat_to_rotmat  # part of this module's API

# Below this length a vector is treated as zero: a degenerate triangle then gets a zero scale w
# (its Gaussians collapse onto its centroid) instead of NaNs.
_EPS = 1e-12


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(_EPS)


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
