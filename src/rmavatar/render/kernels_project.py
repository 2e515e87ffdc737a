"""Numba EWA projection for the CPU backend, forward and analytic backward.

Same maths as ``project.project_gaussians`` (the readable PyTorch statement of the rules), fused per
Gaussian so a projection costs two parallel loops instead of a hundred small tensor ops.
Forward, per Gaussian: p = R_v m + t; Sigma = R S S R^T (R from the normalised quaternion);
Sigma_c = R_v Sigma R_v^T; J at the frustum-clamped point; cov = J Sigma_c J^T + 0.3 I;
conic = cov^-1; mean2d = (fx x / z + cx, fy y / z + cy).
Backward: the chain rule through each step, the clamp included (as gsplat 1.5.3's persp_proj_vjp):
a component clamped to the guard band moves J only through z.
"""

from __future__ import annotations

import math

import numpy as np

from rmavatar.render._numba import numba

EPS2D = 0.3
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
ALPHA_MIN = 1.0 / 255.0


@numba.njit(cache=True, inline="always")
def _rotmat(w, x, y, z, R):
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@numba.njit(cache=True, inline="always")
def _camera_covariance(quat, scale, Rv, R, M, Sc):
    """Sc = Rv (R S)(R S)^T Rv^T; fills R (rotation) and M = R S. Returns |q|."""
    qn = math.sqrt(quat[0] ** 2 + quat[1] ** 2 + quat[2] ** 2 + quat[3] ** 2)
    _rotmat(quat[0] / qn, quat[1] / qn, quat[2] / qn, quat[3] / qn, R)
    for i in range(3):
        for j in range(3):
            M[i, j] = R[i, j] * scale[j]
    # W = Rv M, Sc = W W^T
    W = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            W[i, j] = Rv[i, 0] * M[0, j] + Rv[i, 1] * M[1, j] + Rv[i, 2] * M[2, j]
    for i in range(3):
        for j in range(3):
            Sc[i, j] = W[i, 0] * W[j, 0] + W[i, 1] * W[j, 1] + W[i, 2] * W[j, 2]
    return qn


@numba.njit(parallel=True, cache=True, nogil=True)
def project_forward(means, quats, scales, opacities, viewmat, K, width, height):
    """means [N,3], quats [N,4], scales [N,3], opacities [N] (float64) -> means2d [N,2],
    conics [N,3], depths [N], radii_xy [N,2] int32 (0 where culled), visible [N] bool, and
    has_2d [N] bool (in depth range with a positive 2D determinant: means2d/conics computed)."""
    n = means.shape[0]
    means2d = np.zeros((n, 2))
    conics = np.zeros((n, 3))
    depths = np.empty(n)
    radii = np.zeros((n, 2), np.int32)
    visible = np.zeros(n, np.bool_)
    has_2d = np.zeros(n, np.bool_)
    Rv = viewmat[:3, :3].copy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x_pos = (width - cx) / fx + 0.15 * width / fx
    lim_x_neg = cx / fx + 0.15 * width / fx
    lim_y_pos = (height - cy) / fy + 0.15 * height / fy
    lim_y_neg = cy / fy + 0.15 * height / fy
    for g in numba.prange(n):
        m = means[g]
        x = Rv[0, 0] * m[0] + Rv[0, 1] * m[1] + Rv[0, 2] * m[2] + viewmat[0, 3]
        y = Rv[1, 0] * m[0] + Rv[1, 1] * m[1] + Rv[1, 2] * m[2] + viewmat[1, 3]
        z = Rv[2, 0] * m[0] + Rv[2, 1] * m[1] + Rv[2, 2] * m[2] + viewmat[2, 3]
        depths[g] = z
        # NaN fails every comparison: such rows are culled here or by the determinant test below.
        if not (z >= NEAR_PLANE and z <= FAR_PLANE and math.isfinite(x) and math.isfinite(y)):
            continue
        R = np.empty((3, 3))
        M = np.empty((3, 3))
        Sc = np.empty((3, 3))
        _camera_covariance(quats[g], scales[g], Rv, R, M, Sc)
        rz = 1.0 / z
        tx = z * min(lim_x_pos, max(-lim_x_neg, x * rz))
        ty = z * min(lim_y_pos, max(-lim_y_neg, y * rz))
        j00 = fx * rz
        j02 = -fx * tx * rz * rz
        j11 = fy * rz
        j12 = -fy * ty * rz * rz
        # cov = J Sc J^T with J = [[j00, 0, j02], [0, j11, j12]]
        a = j00 * (j00 * Sc[0, 0] + j02 * Sc[0, 2]) + j02 * (j00 * Sc[2, 0] + j02 * Sc[2, 2]) + EPS2D
        b = j00 * (j11 * Sc[0, 1] + j12 * Sc[0, 2]) + j02 * (j11 * Sc[2, 1] + j12 * Sc[2, 2])
        c = j11 * (j11 * Sc[1, 1] + j12 * Sc[1, 2]) + j12 * (j11 * Sc[2, 1] + j12 * Sc[2, 2]) + EPS2D
        det = a * c - b * b
        u = fx * x * rz + cx
        v = fy * y * rz + cy
        means2d[g, 0] = u
        means2d[g, 1] = v
        if not det > 0.0:
            continue
        has_2d[g] = True
        conics[g, 0] = c / det
        conics[g, 1] = -b / det
        conics[g, 2] = a / det
        op = opacities[g]
        if not op >= ALPHA_MIN:
            continue
        extend = min(3.33, math.sqrt(2.0 * math.log(op / ALPHA_MIN)))
        rx = math.ceil(extend * math.sqrt(a))
        ry = math.ceil(extend * math.sqrt(c))
        if rx <= 0.0 and ry <= 0.0:
            continue
        if u + rx <= 0.0 or u - rx >= width or v + ry <= 0.0 or v - ry >= height:
            continue
        visible[g] = True
        radii[g, 0] = np.int32(min(rx, 2.0**30))
        radii[g, 1] = np.int32(min(ry, 2.0**30))
    return means2d, conics, depths, radii, visible, has_2d


@numba.njit(cache=True, nogil=True, inline="always")
def _cov2d_grad_from_conic(conics, v_conics, g, V):
    """conic = cov^-1: fills V [2,2] with v_cov = -conic G conic, G the symmetric gradient w.r.t. the
    inverse (from row ``g`` of ``conics`` and ``v_conics``). Returns nothing."""
    ia, ib, ic = conics[g, 0], conics[g, 1], conics[g, 2]
    g00 = v_conics[g, 0]
    g01 = 0.5 * v_conics[g, 1]
    g11 = v_conics[g, 2]
    # (inv G) then (inv G inv), inv = [[ia, ib], [ib, ic]]
    t00 = ia * g00 + ib * g01
    t01 = ia * g01 + ib * g11
    t10 = ib * g00 + ic * g01
    t11 = ib * g01 + ic * g11
    vc00 = -(t00 * ia + t01 * ib)
    vc01 = -(t00 * ib + t01 * ic)
    vc11 = -(t10 * ib + t11 * ic)
    V[0, 0] = vc00
    V[0, 1] = vc01
    V[1, 0] = vc01
    V[1, 1] = vc11


@numba.njit(cache=True, nogil=True, inline="always")
def _cov2d_backward(V, J, Sc, vSc, vJ):
    """cov = J Sc J^T: fills vSc [3,3] = J^T V J and vJ [2,3] = 2 V J Sc from V = v_cov. Returns nothing."""
    VJ = np.empty((2, 3))
    for i in range(2):
        for k in range(3):
            VJ[i, k] = V[i, 0] * J[0, k] + V[i, 1] * J[1, k]
    for i in range(3):
        for k in range(3):
            vSc[i, k] = J[0, i] * VJ[0, k] + J[1, i] * VJ[1, k]
    for i in range(2):
        for k in range(3):
            vJ[i, k] = 2.0 * (VJ[i, 0] * Sc[0, k] + VJ[i, 1] * Sc[1, k] + VJ[i, 2] * Sc[2, k])


@numba.njit(cache=True, nogil=True, inline="always")
def _camera_point_grad(x, y, tx, ty, rz, rz2, fx, fy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg, vu, vv, vd, vJ):
    """Returns (vx, vy, vz), the gradient w.r.t. the camera-space point (x, y, z = 1 / rz) from those
    w.r.t. mean2d (vu, vv), depth (vd) and the Jacobian (vJ [2,3]); tx, ty are the clamped x, y.

    J02 = -fx tx / z^2 with tx = x inside the band (bounds included, as gsplat): dJ02/dx = -fx / z^2,
    dJ02/dz = 2 fx tx / z^3; outside, tx = z lim: dJ02/dx = 0, dJ02/dz = fx tx / z^3. Likewise J12 with y.
    """
    rz3 = rz2 * rz
    vx = fx * rz * vu
    vy = fy * rz * vv
    vz = (
        -fx * x * rz2 * vu - fy * y * rz2 * vv
        - fx * rz2 * vJ[0, 0] - fy * rz2 * vJ[1, 1]
        + vd
    )
    if x * rz <= lim_x_pos and x * rz >= -lim_x_neg:
        vx -= fx * rz2 * vJ[0, 2]
        vz += 2.0 * fx * tx * rz3 * vJ[0, 2]
    else:
        vz += fx * tx * rz3 * vJ[0, 2]
    if y * rz <= lim_y_pos and y * rz >= -lim_y_neg:
        vy -= fy * rz2 * vJ[1, 2]
        vz += 2.0 * fy * ty * rz3 * vJ[1, 2]
    else:
        vz += fy * ty * rz3 * vJ[1, 2]
    return vx, vy, vz


@numba.njit(cache=True, nogil=True, inline="always")
def _covariance_backward(vSc, Rv, R, M, s, vR, v_scales, g):
    """Sc = Rv Sigma Rv^T, Sigma = M M^T, M = R S: from vSc = dL/dSc fills vR [3,3] = dL/dR and writes
    v_scales[g] = dL/ds. Returns nothing."""
    # v_Sigma = Rv^T vSc Rv; v_M = 2 v_Sigma M (v_Sigma symmetrised).
    T = np.empty((3, 3))
    for i in range(3):
        for k in range(3):
            T[i, k] = vSc[i, 0] * Rv[0, k] + vSc[i, 1] * Rv[1, k] + vSc[i, 2] * Rv[2, k]
    vS = np.empty((3, 3))
    for i in range(3):
        for k in range(3):
            vS[i, k] = Rv[0, i] * T[0, k] + Rv[1, i] * T[1, k] + Rv[2, i] * T[2, k]
    for j in range(3):
        acc = 0.0
        for i in range(3):
            vm_ij = (vS[i, 0] + vS[0, i]) * M[0, j] + (vS[i, 1] + vS[1, i]) * M[1, j] + (vS[i, 2] + vS[2, i]) * M[2, j]
            vR[i, j] = vm_ij * s[j]
            acc += vm_ij * R[i, j]
        v_scales[g, j] = acc


@numba.njit(cache=True, nogil=True, inline="always")
def _quat_backward(quats, qn, vR, v_quats, g):
    """R = rotation of q / |q| (q = quats[g], |q| = qn): from vR = dL/dR writes v_quats[g] = dL/dq.
    Returns nothing."""
    w = quats[g, 0] / qn
    qx = quats[g, 1] / qn
    qy = quats[g, 2] / qn
    qz = quats[g, 3] / qn
    gw = 2.0 * (-qz * vR[0, 1] + qy * vR[0, 2] + qz * vR[1, 0] - qx * vR[1, 2] - qy * vR[2, 0] + qx * vR[2, 1])
    gx = 2.0 * (qy * vR[0, 1] + qz * vR[0, 2] + qy * vR[1, 0] - 2.0 * qx * vR[1, 1] - w * vR[1, 2]
                + qz * vR[2, 0] + w * vR[2, 1] - 2.0 * qx * vR[2, 2])
    gy = 2.0 * (-2.0 * qy * vR[0, 0] + qx * vR[0, 1] + w * vR[0, 2] + qx * vR[1, 0] + qz * vR[1, 2]
                - w * vR[2, 0] + qz * vR[2, 1] - 2.0 * qy * vR[2, 2])
    gz = 2.0 * (-2.0 * qz * vR[0, 0] - w * vR[0, 1] + qx * vR[0, 2] + w * vR[1, 0] - 2.0 * qz * vR[1, 1]
                + qy * vR[1, 2] + qx * vR[2, 0] + qy * vR[2, 1])
    # Through the normalisation q / |q|.
    dot = w * gw + qx * gx + qy * gy + qz * gz
    v_quats[g, 0] = (gw - w * dot) / qn
    v_quats[g, 1] = (gx - qx * dot) / qn
    v_quats[g, 2] = (gy - qy * dot) / qn
    v_quats[g, 3] = (gz - qz * dot) / qn


@numba.njit(parallel=True, cache=True, nogil=True)
def project_backward(means, quats, scales, viewmat, K, width, height, conics, has_2d, v_means2d, v_conics, v_depths):
    """Gradients w.r.t. means [N,3], quats [N,4], scales [N,3] from those w.r.t. means2d [N,2],
    conics [N,3] and depths [N]. ``has_2d`` [N] from the forward: other rows only pass the depth
    gradient."""
    n = means.shape[0]
    v_means = np.zeros((n, 3))
    v_quats = np.zeros((n, 4))
    v_scales = np.zeros((n, 3))
    Rv = viewmat[:3, :3].copy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x_pos = (width - cx) / fx + 0.15 * width / fx
    lim_x_neg = cx / fx + 0.15 * width / fx
    lim_y_pos = (height - cy) / fy + 0.15 * height / fy
    lim_y_neg = cy / fy + 0.15 * height / fy
    for g in numba.prange(n):
        if not has_2d[g]:
            for i in range(3):
                v_means[g, i] = Rv[2, i] * v_depths[g]
            continue
        m = means[g]
        x = Rv[0, 0] * m[0] + Rv[0, 1] * m[1] + Rv[0, 2] * m[2] + viewmat[0, 3]
        y = Rv[1, 0] * m[0] + Rv[1, 1] * m[1] + Rv[1, 2] * m[2] + viewmat[1, 3]
        z = Rv[2, 0] * m[0] + Rv[2, 1] * m[1] + Rv[2, 2] * m[2] + viewmat[2, 3]
        R = np.empty((3, 3))
        M = np.empty((3, 3))
        Sc = np.empty((3, 3))
        qn = _camera_covariance(quats[g], scales[g], Rv, R, M, Sc)
        rz = 1.0 / z
        rz2 = rz * rz
        tx = z * min(lim_x_pos, max(-lim_x_neg, x * rz))
        ty = z * min(lim_y_pos, max(-lim_y_neg, y * rz))
        J = np.zeros((2, 3))
        J[0, 0] = fx * rz
        J[0, 2] = -fx * tx * rz2
        J[1, 1] = fy * rz
        J[1, 2] = -fy * ty * rz2
        V = np.empty((2, 2))
        _cov2d_grad_from_conic(conics, v_conics, g, V)
        vSc = np.empty((3, 3))
        vJ = np.empty((2, 3))
        _cov2d_backward(V, J, Sc, vSc, vJ)
        vx, vy, vz = _camera_point_grad(
            x, y, tx, ty, rz, rz2, fx, fy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg,
            v_means2d[g, 0], v_means2d[g, 1], v_depths[g], vJ,
        )
        for i in range(3):
            v_means[g, i] = Rv[0, i] * vx + Rv[1, i] * vy + Rv[2, i] * vz
        vR = np.empty((3, 3))
        _covariance_backward(vSc, Rv, R, M, scales[g], vR, v_scales, g)
        _quat_backward(quats, qn, vR, v_quats, g)
    return v_means, v_quats, v_scales
