"""Linear blend skinning and kinematic chains as plain functions on tensors.

Convention shared by every body: a bone's local rotation is expressed in world-aligned axes about its
head (as SMPL's), and the posed world rotation composes as ``G_c = G_parent @ L_c``.
"""

from __future__ import annotations

from typing import Sequence

import torch


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. ``rotvec [..., 3]`` axis-angle (radians) -> ``[..., 3, 3]``.

    The small-angle branch uses the Taylor series so the gradient stays finite at zero rotation.
    """
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(rotvec.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def global_rotations(local: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """Compose local rotations down a chain. ``local [B,J,3,3]`` -> world ``[B,J,3,3]``.

    ``parents[j] < j`` for every non-root joint; the root's parent is negative.
    """
    out = [local[:, 0]]
    for j in range(1, local.shape[1]):
        out.append(out[parents[j]] @ local[:, j])
    return torch.stack(out, 1)


def lbs(
    rest_vertices: torch.Tensor,
    rest_joints: torch.Tensor,
    parents: Sequence[int],
    rotations: torch.Tensor,
    weights: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose a rest mesh by linear blend skinning.

    Args:
        rest_vertices: ``[B,V,3]`` (or ``[1,V,3]``, broadcast) rest vertices, pose blend shapes already added.
        rest_joints: ``[B,J,3]`` (or ``[1,J,3]``) rest joint (bone head) positions.
        parents: ``J`` parent indices, ``parents[j] < j``, the root's negative.
        rotations: ``[B,J,3,3]`` local rotations about each joint in world-aligned axes.
        weights: ``[V,J]`` skinning weights (rows sum to 1).

    Returns:
        vertices ``[B,V,3]``, posed joints ``[B,J,3]``, and the bone transforms ``[B,J,4,4]`` that map
        rest positions to posed ones (``x' = T[:3,:3] x + T[:3,3]``).
    """
    B, J = rotations.shape[:2]
    rest_joints = rest_joints.expand(B, -1, -1)
    G = global_rotations(rotations, parents)
    # Posed joint c = posed parent + G_parent (rest offset): the chain SMPL and Anny's local-ref share.
    posed = [rest_joints[:, 0]]
    for j in range(1, J):
        p = parents[j]
        offset = rest_joints[:, j] - rest_joints[:, p]
        posed.append(posed[p] + (G[:, p] @ offset[..., None])[..., 0])
    joints = torch.stack(posed, 1)
    t = joints - (G @ rest_joints[..., None])[..., 0]
    T = torch.cat([G, t[..., None]], -1)  # [B,J,3,4]
    blended = (weights @ T.reshape(B, J, 12)).reshape(B, -1, 3, 4)  # [B,V,3,4]
    verts = rest_vertices.expand(B, -1, -1)
    vertices = (blended[..., :3] @ verts[..., None])[..., 0] + blended[..., 3]
    bottom = torch.zeros(B, J, 1, 4, dtype=T.dtype, device=T.device)
    bottom[..., 0, 3] = 1.0
    return vertices, joints, torch.cat([T, bottom], -2)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[...,3,3]`` -> axis-angle ``[...,3]`` (via quaternions, stable near pi)."""
    import roma

    return roma.rotmat_to_rotvec(R)
