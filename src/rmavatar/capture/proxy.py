"""A fast stand-in for a body model while fitting: SMPL's 24-joint chain and linear blend skinning of a
few hundred surface points, with skinning weights recovered from the body itself.

Posing a full body for every frame at every iteration is what a fit would spend its time on (Anny:
104 bones and 13,718 vertices). The fit needs only the 24 joints and some surface points. For any
body driven by SMPL-format parameters, the joints follow SMPL's chain from the body's own rest (zero
pose) joints exactly (Anny by construction of its retargeting, SMPL by definition), so
:class:`BodyProxy` poses them with :func:`rmavatar.body.lbs.lbs`. The surface points are skinned to
the 24 joint transforms with weights found by non-negative least squares from the body posed at
random poses: exact for an LBS body whose bones follow the SMPL joints, and for SMPL up to its pose
blend shapes (which move the surface by millimetres to a centimetre).
"""

from __future__ import annotations

import numpy as np
import torch

from rmavatar.body.base import SMPL_PARENTS
from rmavatar.body.lbs import axis_angle_to_matrix, lbs


class BodyProxy:
    """Joints, joint rotations and surface points of ``body`` for SMPL-format parameters.

    point_ids [P]: the body's vertices to pose; num_poses random poses (seeded) recover the weights.
    ``weights`` [P,24] (rows sum to about 1); ``fit_error`` the largest distance (metres) between the
    proxy's points and the body's on other random poses.
    """

    def __init__(self, body, point_ids: torch.Tensor, num_poses: int = 48, seed: int = 0):
        from scipy.optimize import nnls

        self.body = body
        self.point_ids = point_ids
        dev = body.faces.device
        self.num_betas = min(int(getattr(body, "num_betas", 0)), 10)
        g = torch.Generator().manual_seed(seed)

        def random_pose(n):
            return (0.5 * torch.randn(n, 3, generator=g)).to(dev), (0.4 * torch.randn(n, 69, generator=g)).to(dev)

        with torch.no_grad():
            rest_joints, rest_points = self.rest(None)
            go, bp = random_pose(num_poses)
            posed = body(None, go, bp, torch.zeros(num_poses, 3, device=dev)).vertices[:, point_ids]
            transforms = self._transforms(rest_joints, go, bp)  # [N,24,3,4]
        # point i posed by pose n = sum_j w_ij (T_nj [p_i; 1]): columns T_nj [p_i; 1] per joint j
        p = torch.cat([rest_points[0], torch.ones(len(point_ids), 1, device=dev)], 1).double().cpu()
        cols = torch.einsum("njab,pb->pnaj", transforms.double().cpu(), p)  # [P,N,3,24]
        A = cols.reshape(len(point_ids), -1, 24).numpy()
        b = posed.double().cpu().permute(1, 0, 2).reshape(len(point_ids), -1).numpy()
        weights = np.zeros((len(point_ids), 24))
        ones = np.full((1, 24), 10.0)  # rows sum to 1, as a strongly weighted equation
        for i in range(len(point_ids)):
            weights[i], _ = nnls(np.vstack([A[i], ones]), np.append(b[i], 10.0))
        self.weights = torch.as_tensor(weights, dtype=torch.float32, device=dev)
        with torch.no_grad():
            go, bp = random_pose(16)
            tr = torch.zeros(16, 3, device=dev)
            _, _, points = self(None, go, bp, tr)
            truth = body(None, go, bp, tr).vertices[:, point_ids]
        self.fit_error = float((points - truth).norm(dim=-1).max())

    def rest(self, betas: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest (zero pose) joints [1,24,3] and surface points [1,P,3] for shape ``betas`` [1,nb] (or None);
        differentiable in betas."""
        if betas is None and getattr(self, "_rest", None) is not None:
            return self._rest
        dev = self.body.faces.device
        zero = torch.zeros(1, 3, device=dev)
        out = self.body(betas, zero, torch.zeros(1, 69, device=dev), zero)
        rest = out.joints, out.vertices[:, self.point_ids]
        if betas is None:
            self._rest = tuple(r.detach() for r in rest)
        return rest

    @staticmethod
    def _transforms(rest_joints: torch.Tensor, global_orient: torch.Tensor, body_pose: torch.Tensor) -> torch.Tensor:
        """SMPL chain transforms [B,24,3,4] (rest -> posed, no translation) from the rest joints."""
        B = global_orient.shape[0]
        R = axis_angle_to_matrix(torch.cat([global_orient, body_pose], 1).reshape(B, 24, 3))
        dummy = rest_joints[:, :1]
        _, _, T = lbs(dummy, rest_joints, SMPL_PARENTS, R, torch.zeros(1, 24, device=R.device))
        return T[..., :3, :]

    def __call__(self, betas, global_orient: torch.Tensor, body_pose: torch.Tensor, transl: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """joints [B,24,3], joint world rotations [B,24,3,3], surface points [B,P,3] (SMPL semantics:
        rotation about the rest pelvis, then ``transl``)."""
        B = global_orient.shape[0]
        rest_joints, rest_points = self.rest(betas)
        R = axis_angle_to_matrix(torch.cat([global_orient, body_pose], 1).reshape(B, 24, 3))
        _, joints, T = lbs(rest_joints[:, :1], rest_joints, SMPL_PARENTS, R, self.weights[:1])
        # point p = sum_j w_pj T_j [rest_p; 1] = sum_(j,c) T_j[:, c] (w_pj [rest_p; 1]_c): one product of the
        # transforms [B*3, 24*4] with a [24*4, P] table, where blending a 3x4 matrix per point and frame
        # first made [B,P,3,4] arrays (and their gradients) that were most of the fit's time
        table = self._table(betas, rest_points)
        points = (T[..., :3, :].permute(0, 2, 1, 3).reshape(B * 3, -1) @ table).reshape(B, 3, -1).transpose(1, 2)
        t = transl[:, None]
        return joints + t, T[..., :3, :3], points + t

    def _table(self, betas, rest_points: torch.Tensor) -> torch.Tensor:
        """w_pj [rest_p; 1]_c as a [24*4, P] table (cached for the rest shape, betas None)."""
        if betas is None and getattr(self, "_cached_table", None) is not None:
            return self._cached_table
        points = rest_points[0]
        homo = torch.cat([points, torch.ones_like(points[:, :1])], 1)  # [P,4]
        table = (self.weights[:, :, None] * homo[:, None, :]).reshape(len(points), -1).T.contiguous()
        if betas is None:
            self._cached_table = table.detach()
        return table
