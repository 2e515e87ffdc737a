"""The world-space Gaussians from their faces' frames and the rectifier's offsets, as one autograd
Function with the backward written out (docs/model.md has the formulas).

Per Gaussian, from its face's row g of the posed mesh's table (columns named by
:class:`~rmavatar.avatar.geometry.FaceTable`: R, w R, M, w, L(quat(R)); see ``Avatar._posed``) and its
local parameters (means, quats, log_scales):

- no rectifier:   mu* = w R mu + M,  r* = quat(R) (x) unit(r),  s* = w exp(log_s)
- offsets in the triangle's frame (the local design): mu' = w R (mu + d_mu) + M,
  s' = max(w (exp(log_s) + d_s), min_scale), with the world offsets w R d_mu and w d_s returned too (the
  offset regulariser reads them);
- offsets in world units (the paper's design): mu' = w R mu + M + d_mu,  s' = max(w exp(log_s) + d_s, min_scale);
- both designs:   r' = quat(R) (x) unit(r) (x) unit(1 + d_r).

Autograd over the plain formulas records about 44 operations forward and backward for the local design
(each normalisation and quaternion product several); this takes 32: the two normalisations run as one
on a stacked [2,N,4], and the face rows' gradient (one [N,FaceTable.WIDTH] tensor) is made only when the
vertices need it (pose fitting), not in training. :func:`compose_reference` is those plain formulas,
which the tests compare this with.
"""

from __future__ import annotations

import torch

from rmavatar.avatar.geometry import FaceTable, quat_left_matrix, quat_right_matrix
from rmavatar.render.project import unit_backward, unit_forward
from rmavatar.utils.device import constant

_threshold_backward = torch.ops.aten.threshold_backward  # grad where x > threshold, else 0: one operation


class _Compose(torch.autograd.Function):
    """(g [N,FaceTable.WIDTH], means [N,3], quats [N,4], log_scales [N,3], d_mu, d_s, d_r, face_frame, min_scale) ->
    (mu, r, s, frames [N,3,3] (a view of g), d_mu_world, d_s_world). Without offsets (d_mu, d_s, d_r
    None) the last two outputs are None; ``face_frame``: the offsets are in the triangle's frame (the
    last two are then their world values), else in world units (the last two are None)."""

    @staticmethod
    def forward(ctx, g, means, quats, log_scales, d_mu, d_s, d_r, face_frame, min_scale):
        ctx.set_materialize_grads(False)
        rectified = d_r is not None
        face_frame = rectified and face_frame
        ctx.rectified, ctx.face_frame = rectified, face_frame
        n = g.shape[0]
        wR, M, w = g[:, FaceTable.wR].unflatten(-1, (3, 3)), g[:, FaceTable.M], g[:, FaceTable.w]
        L = g[:, FaceTable.L].unflatten(-1, (4, 4))
        e = torch.exp(log_scales)
        d_mu_w = d_s_w = None
        if face_frame:
            a = means + d_mu
            mu = torch.baddbmm(M.unsqueeze(-1), wR, a.unsqueeze(-1)).squeeze(-1)
            d_mu_w = torch.bmm(wR, d_mu.unsqueeze(-1)).squeeze(-1)
            s = ((e + d_s) * w).clamp_min(min_scale)
            d_s_w = d_s * w
        elif rectified:
            a = means
            mu = torch.baddbmm((M + d_mu).unsqueeze(-1), wR, means.unsqueeze(-1)).squeeze(-1)
            s = torch.addcmul(d_s, e, w).clamp_min(min_scale)
        else:
            a = means
            mu = torch.baddbmm(M.unsqueeze(-1), wR, means.unsqueeze(-1)).squeeze(-1)
            s = e * w
        if not rectified:
            v = quats.unsqueeze(0)  # [1,N,4]
        else:
            # both normalisations at once: [2,N,4] = (quats, 1 + d_r)
            identity = constant(((0.0,) * 4, (1.0, 0.0, 0.0, 0.0)), quats.dtype, quats.device).unsqueeze(1)
            v = torch.stack((quats, d_r)) + identity
        u, norm, clamped = unit_forward(v)
        r_star = torch.bmm(L, u[0].unsqueeze(-1)).squeeze(-1)
        if not rectified:
            r, right = r_star, None
        else:
            right = quat_right_matrix(u[1])  # r' = r* (x) unit(1 + d_r) = R(unit(1 + d_r)) r*
            r = torch.bmm(right, r_star.unsqueeze(-1)).squeeze(-1)
        ctx.min_scale = min_scale
        ctx.save_for_backward(wR, L, w, e, a, d_mu, d_s, s, u, norm, clamped, r_star, right)
        ctx.n = n
        return mu, r, s, g[:, FaceTable.R].unflatten(-1, (3, 3)), d_mu_w, d_s_w

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_mu, g_r, g_s, g_frames, g_dmu_w, g_ds_w):
        wR, L, w, e, a, d_mu, d_s, s, u, norm, clamped, r_star, right = ctx.saved_tensors
        rectified, face_frame, n = ctx.rectified, ctx.face_frame, ctx.n
        need_g, need_means, need_quats, need_scales, need_dmu, need_ds, need_dr = ctx.needs_input_grad[:7]
        zero = constant(0.0, wR.dtype, wR.device)
        g_means = g_quats = g_log_scales = g_dmu = g_ds = g_dr = None
        # the face rows (g) need gradients only where the vertices do (pose fitting), not in training

        # positions: mu = w R a + M (+ d_mu); face frame: d_mu_w = w R d_mu
        if g_mu is None:
            g_mu = zero.expand(n, 3)
        if need_means:
            g_means = torch.bmm(g_mu.unsqueeze(-2), wR).squeeze(-2)  # (w R)^T g
        if need_dmu:
            if not face_frame:
                g_dmu = g_mu
            elif g_dmu_w is None:
                g_dmu = g_means if need_means else torch.bmm(g_mu.unsqueeze(-2), wR).squeeze(-2)
            else:
                g_dmu = torch.bmm((g_mu + g_dmu_w).unsqueeze(-2), wR).squeeze(-2)

        # scales: s = max(w t (face frame) or w e + d_s (world), min_scale), or w e; face frame: d_s_w = w d_s
        if g_s is None:
            g_s = zero.expand(n, 3)
        if rectified:
            g_s = _threshold_backward(g_s, s, ctx.min_scale)  # the clamp lets it through above min_scale
        g_sw = g_s * w  # face frame: d s / d t = w, t = exp(log_s) + d_s
        if need_ds:
            if not face_frame:
                g_ds = g_s
            else:
                g_ds = g_sw if g_ds_w is None else torch.addcmul(g_sw, g_ds_w, w)
        if need_scales:
            g_log_scales = g_sw * e

        # rotations: r* = L unit(r), r' = r* (x) unit(1 + d_r) = R(unit(1 + d_r)) r* = L(r*) unit(1 + d_r)
        if g_r is None:
            g_r = zero.expand(n, 4)
        g_rs = g_r if not rectified else torch.bmm(g_r.unsqueeze(-2), right).squeeze(-2)  # R^T g
        if need_quats or need_dr:
            g_u0 = torch.bmm(g_rs.unsqueeze(-2), L).squeeze(-2)  # L^T g*
            if not rectified:
                g_u = g_u0.unsqueeze(0)
            else:
                g_u1 = torch.bmm(g_r.unsqueeze(-2), quat_left_matrix(r_star)).squeeze(-2)
                g_u = torch.stack((g_u0, g_u1))
            g_v = unit_backward(g_u, u, norm, clamped)
            g_quats = g_v[0]
            g_dr = g_v[1] if rectified else None

        g_g = None
        if need_g:
            g_wR = torch.bmm(g_mu.unsqueeze(-1), a.unsqueeze(-2))
            if face_frame and g_dmu_w is not None:
                g_wR = torch.baddbmm(g_wR, g_dmu_w.unsqueeze(-1), d_mu.unsqueeze(-2))
            g_e = g_s * e
            if face_frame:  # d s / d w = t = e + d_s; d d_s_w / d w = d_s
                g_e = torch.addcmul(g_e, g_s if g_ds_w is None else g_s + g_ds_w, d_s)
            g_w = g_e.sum(-1, keepdim=True)
            g_L = torch.bmm(g_rs.unsqueeze(-1), u[0].unsqueeze(-2))
            g_frames = zero.expand(n, 9) if g_frames is None else g_frames.reshape(n, 9)
            # the columns in FaceTable's order: R, w R, M, w, L
            g_g = torch.cat((g_frames, g_wR.reshape(n, 9), g_mu, g_w, g_L.reshape(n, 16)), dim=-1)
        return g_g, g_means, g_quats, g_log_scales, g_dmu, g_ds, g_dr, None, None


def _design_frame(design, offsets) -> bool:
    """Whether ``design`` gives its offsets in the triangle's frame (False without offsets)."""
    if offsets is None:
        return False
    face_frame = getattr(design, "offsets_in_face_frame", None)
    if face_frame is None:
        raise ValueError(f"offsets need the rectifier design that made them (a RectifierDesign), not {design!r}")
    return face_frame


def compose_gaussians(g: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                      offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                      design=None, min_scale: float = 1e-6):
    """World means [N,3], quats [N,4], scales [N,3] and frames R [N,3,3] of the Gaussians, and the
    offsets in world units (d_mu, d_s, d_r) (None without ``offsets``).

    g [N,FaceTable.WIDTH]: each Gaussian's row of the posed mesh's face table; offsets: the rectifier's raw outputs;
    design: the rectifier design that made them (a :class:`~rmavatar.avatar.rectifier.RectifierDesign`:
    its ``offsets_in_face_frame`` says whether they are in the triangle's frame or in world units)."""
    face_frame = _design_frame(design, offsets)
    if offsets is None:
        mu, r, s, frames, _, _ = _Compose.apply(g, means, quats, log_scales, None, None, None, False, min_scale)
        return mu, r, s, frames, None
    d_mu, d_s, d_r = offsets
    mu, r, s, frames, d_mu_w, d_s_w = _Compose.apply(g, means, quats, log_scales, d_mu, d_s, d_r, face_frame,
                                                     min_scale)
    return mu, r, s, frames, ((d_mu_w, d_s_w, d_r) if face_frame else (d_mu, d_s, d_r))


# ----------------------------------------------------------------------------------------------- reference
def _hamilton(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a (x) b of quaternions [...,4] (wxyz), component by component."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw), dim=-1)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)


def compose_reference(g: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                      offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                      design=None, min_scale: float = 1e-6):
    """:func:`compose_gaussians` under plain autograd, one operation at a time (for tests): the formulas
    of the module docstring, the columns of g read as independent inputs, the offsets brought to world
    units by the design's own :meth:`~rmavatar.avatar.rectifier.RectifierDesign.world_offsets`."""
    frames, wR = g[:, FaceTable.R].reshape(-1, 3, 3), g[:, FaceTable.wR].reshape(-1, 3, 3)
    M, w, L = g[:, FaceTable.M], g[:, FaceTable.w], g[:, FaceTable.L].reshape(-1, 4, 4)
    mu = (wR @ means.unsqueeze(-1)).squeeze(-1) + M
    r = (L @ _unit(quats).unsqueeze(-1)).squeeze(-1)
    s = w * torch.exp(log_scales)
    if offsets is None:
        return mu, r, s, frames, None
    _design_frame(design, offsets)
    d_mu, d_s, d_r = design.world_offsets(offsets, wR, w)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=d_r.dtype, device=d_r.device)
    return (mu + d_mu, _hamilton(r, _unit(d_r + identity)), (s + d_s).clamp_min(min_scale), frames,
            (d_mu, d_s, d_r))
