"""Linear blend skinning and kinematic chains as plain functions on tensors.

Convention shared by every body: a bone's local rotation is expressed in world-aligned axes about its
head (as SMPL's), and the posed world rotation composes as ``G_c = G_parent @ L_c``.
"""

from __future__ import annotations

import functools
from typing import Sequence

import torch

from rmavatar.utils.device import constant


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


@functools.lru_cache(maxsize=16)
def _levels(parents: tuple[int, ...], device: torch.device) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor]:
    """Joints grouped by depth: per level (after the root) the joint ids and their parents' positions
    within the previous level, and the permutation from depth order back to joint order."""
    children: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents[1:], start=1):
        children[p].append(j)
    level, order = [0], [0]
    ids, parent_pos = [], []
    while True:
        nxt = [c for j in level for c in children[j]]
        if not nxt:
            break
        position = {j: k for k, j in enumerate(level)}
        ids.append(torch.tensor(nxt))
        parent_pos.append(torch.tensor([position[parents[c]] for c in nxt]))
        order += nxt
        level = nxt
    if len(order) != len(parents):
        raise ValueError("every joint must descend from joint 0")
    # made once per device: a chain posed every frame (or replayed in a CUDA graph) uploads nothing
    return ([t.to(device) for t in ids], [t.to(device) for t in parent_pos],
            torch.argsort(torch.tensor(order)).to(device))


def _chain(K: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """``X_c = X_parent @ K_c`` down the tree, one batched product per depth level. ``K [B,J,n,n]``."""
    ids, parent_pos, inverse = _levels(tuple(int(p) for p in parents), K.device)
    X = [K[:, :1]]
    for level_ids, pos in zip(ids, parent_pos):
        X.append(X[-1][:, pos] @ K[:, level_ids])
    return torch.cat(X, 1)[:, inverse]


def global_rotations(local: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """Compose local rotations down a chain. ``local [B,J,3,3]`` -> world ``[B,J,3,3]``.

    The root's parent is negative; every other joint descends from joint 0.
    """
    return _chain(local, parents)


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
        parents: ``J`` parent indices, the root's negative.
        rotations: ``[B,J,3,3]`` local rotations about each joint in world-aligned axes.
        weights: ``[V,J]`` skinning weights (rows sum to 1); dense, which beats gathering Anny's 9 bones
            per vertex on CPU.

    Returns:
        vertices ``[B,V,3]``, posed joints ``[B,J,3]``, and the bone transforms ``[B,J,4,4]`` that map
        rest positions to posed ones (``x' = T[:3,:3] x + T[:3,3]``).
    """
    B, J = rotations.shape[:2]
    rest_joints = rest_joints.expand(B, -1, -1)
    # Rigid chain W_c = W_parent [L_c | h_c - h_parent] gives W_c = [G_c | posed joint c]: the chain
    # SMPL and Anny's local-ref parameterisation share.
    parent_idx = constant((0, *(int(p) for p in parents[1:])), torch.long, rest_joints.device)
    offsets = torch.cat([rest_joints[:, :1], rest_joints[:, 1:] - rest_joints[:, parent_idx[1:]]], 1)
    bottom = torch.zeros(B, J, 1, 4, dtype=rotations.dtype, device=rotations.device)
    bottom[..., 0, 3] = 1.0
    K = torch.cat([torch.cat([rotations, offsets[..., None]], -1), bottom], -2)
    W = _chain(K, parents)
    G, joints = W[..., :3, :3], W[..., :3, 3]
    t = joints - (G @ rest_joints[..., None])[..., 0]
    T = torch.cat([G, t[..., None]], -1)  # [B,J,3,4]
    # one [V,J] @ [J,B*12] product: a broadcast batched matmul would copy the weights B times
    blended = (weights @ T.reshape(B, J, 12).permute(1, 0, 2).reshape(J, B * 12)).reshape(-1, B, 3, 4)
    blended = blended.permute(1, 0, 2, 3)  # [B,V,3,4]
    verts = rest_vertices.expand(B, -1, -1)
    vertices = (blended[..., :3] * verts[:, :, None, :]).sum(-1) + blended[..., 3]
    return vertices, joints, torch.cat([T, bottom], -2)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[...,3,3]`` -> axis-angle ``[...,3]`` (via quaternions, stable near pi)."""
    import roma

    return roma.rotmat_to_rotvec(R)
