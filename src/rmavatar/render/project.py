"""EWA projection of 3D Gaussians and spherical-harmonics colours, in plain differentiable PyTorch.

The SH colours here are what the CPU backend uses. ``project_gaussians`` is the readable statement of
the projection rules: the CPU backend runs the fused Numba version (``kernels_project``), which the
tests check against this one.

Follows gsplat 1.5's pinhole "classic" rules so the CPU and CUDA backends draw the same picture:
OpenCV camera (x right, y down, z forward), world-to-camera ``viewmat``, wxyz quaternions normalised
here, 0.3 px^2 low-pass dilation of the 2D covariance, near plane 0.01, and an opacity-aware
3-sigma box (extent ``min(3.33, sqrt(2 ln(255 opacity)))`` standard deviations per axis).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rmavatar.utils.device import constant

EPS2D = 0.3  # low-pass dilation added to the 2D covariance diagonal (pixels^2)
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities. Rows with ``visible`` False hold harmless finite values.

    means2d [N,2] pixels, conics [N,3] (a, b, c of the inverse 2D covariance [[a,b],[b,c]]),
    depths [N] camera z, radii_xy [N,2] int32 half extents of the pixel box (0 when culled),
    visible [N] bool.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii_xy: Tensor
    visible: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [...,3,3] from wxyz quaternions [...,4] (normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def project_gaussians(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
    viewmat: Tensor, K: Tensor, width: int, height: int,
) -> Projection:
    """Project Gaussians (means [N,3], quats [N,4], scales [N,3], opacities [N]) to the image.

    ``viewmat`` [4,4] world->camera, ``K`` [3,3]. Differentiable w.r.t. the Gaussian inputs.
    """
    rot_view = viewmat[:3, :3]
    mean_c = means @ rot_view.T + viewmat[:3, 3]
    x, y, z = mean_c.unbind(-1)
    in_depth = (z >= NEAR_PLANE) & (z <= FAR_PLANE)
    # Culled rows still flow through the maths; a safe depth keeps their (unused) gradients finite.
    zs = torch.where(in_depth, z, torch.ones_like(z))

    R = quat_to_rotmat(quats)
    M = R * scales[:, None, :]
    covar = M @ M.transpose(-1, -2)
    covar_c = rot_view @ covar @ rot_view.T

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    # The Jacobian is evaluated at the point clamped to a guard band around the frustum, and the clamp
    # is differentiated as gsplat 1.5.3 does (its persp_proj_vjp and its torch _persp_proj): inside the
    # band (bounds included) J depends on x, y, z as written; outside, tx = z * lim, so the clamped
    # component only moves J through z.
    tx = zs * torch.clamp(x / zs, min=-lim_x_neg, max=lim_x_pos)
    ty = zs * torch.clamp(y / zs, min=-lim_y_neg, max=lim_y_pos)
    rz = 1.0 / zs
    zero = torch.zeros_like(rz)
    J = torch.stack(
        [fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], dim=-1
    ).reshape(-1, 2, 3)
    cov2d = J @ covar_c @ J.transpose(-1, -2)
    a = cov2d[:, 0, 0] + EPS2D
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + EPS2D
    det = a * c - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)

    with torch.no_grad():
        op = opacities.detach()
        ok_op = op >= ALPHA_MIN
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_MIN) / ALPHA_MIN)).clamp_max(3.33)
        rx = torch.ceil(extend * a.detach().clamp_min(0).sqrt())
        ry = torch.ceil(extend * c.detach().clamp_min(0).sqrt())
        mx, my = means2d.detach().unbind(-1)
        on_screen = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        visible = in_depth & ok_det & ok_op & ((rx > 0) | (ry > 0)) & on_screen
        # Clamped only for storage: a box wider than 2^30 px covers the image either way.
        radii_xy = torch.stack([rx, ry], dim=-1).clamp_max(2.0**30).to(torch.int32) * visible[:, None]
    return Projection(means2d, conics, z, radii_xy, visible)


# Real spherical-harmonics constants in the 3DGS/gsplat sign convention (Condon-Shortley phase kept).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """SH basis values [N,(degree+1)^2] for directions [N,3] (normalised here), degree 0..3."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {degree}")
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            _C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy),
            _C2[3] * x * z, _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


# The basis functions of bands 1..3 as polynomials in the unit direction (x, y, z): per basis index,
# (coefficient, monomial) terms, as in sh_basis.
_SH_POLYNOMIALS = {
    1: [(-_C1, "y")], 2: [(_C1, "z")], 3: [(-_C1, "x")],
    4: [(_C2[0], "xy")], 5: [(_C2[1], "yz")], 6: [(2 * _C2[2], "zz"), (-_C2[2], "xx"), (-_C2[2], "yy")],
    7: [(_C2[3], "xz")], 8: [(_C2[4], "xx"), (-_C2[4], "yy")],
    9: [(3 * _C3[0], "xxy"), (-_C3[0], "yyy")], 10: [(_C3[1], "xyz")],
    11: [(4 * _C3[2], "yzz"), (-_C3[2], "xxy"), (-_C3[2], "yyy")],
    12: [(2 * _C3[3], "zzz"), (-3 * _C3[3], "xxz"), (-3 * _C3[3], "yyz")],
    13: [(4 * _C3[4], "xzz"), (-_C3[4], "xxx"), (-_C3[4], "xyy")],
    14: [(_C3[5], "xxz"), (-_C3[5], "yyz")], 15: [(_C3[6], "xxx"), (-3 * _C3[6], "xyy")],
}


@functools.lru_cache(maxsize=None)
def _sh_table(degree: int) -> tuple:
    """[4^degree, (degree+1)^2]: the products of ``degree`` factors of (1, x, y, z) (flattened, first
    factor slowest) times this table are the SH basis values; each monomial is read from one product."""
    k = (degree + 1) ** 2
    table = [[0.0] * k for _ in range(4**degree)]
    table[0][0] = _C0  # 1 * 1 * ... * 1
    for j in range(1, k):
        for coef, mono in _SH_POLYNOMIALS[j]:
            factors = [0] * (degree - len(mono)) + ["_xyz".index(v) for v in mono]
            table[sum(f * 4 ** (degree - 1 - i) for i, f in enumerate(factors))][j] += coef
    return tuple(map(tuple, table))


@functools.lru_cache(maxsize=None)
def _sh_derivative_table(degree: int) -> tuple:
    """[(degree+1)^2, 3 * 4^(degree-1)]: the derivatives of the basis functions w.r.t. x, y, z, which are
    polynomials of degree - 1. Column a * 4^(degree-1) + i holds the coefficient of the derivative along
    axis a (x, y, z) on product i of ``degree - 1`` factors of (1, x, y, z), as in _sh_table."""
    k, size = (degree + 1) ** 2, 4 ** (degree - 1)
    table = [[0.0] * (3 * size) for _ in range(k)]
    for j in range(1, k):
        for coef, mono in _SH_POLYNOMIALS[j]:
            for axis, var in enumerate("xyz"):
                count = mono.count(var)
                if count:
                    rest = mono.replace(var, "", 1)  # d(var^count * rest) = count * var^(count-1) * rest
                    factors = [0] * (degree - 1 - len(rest)) + ["_xyz".index(v) for v in rest]
                    i = sum(f * 4 ** (degree - 2 - n) for n, f in enumerate(factors))
                    table[j][axis * size + i] += coef * count
    return tuple(map(tuple, table))


_threshold_backward = torch.ops.aten.threshold_backward  # grad where x > threshold, else 0: one operation
UNIT_EPS = 1e-12  # unit(v) = v / max(|v|, eps): below this length a row is divided by eps, not by itself


def unit_forward(v: Tensor, eps: float = UNIT_EPS) -> tuple[Tensor, Tensor, Tensor]:
    """unit(v) = v / max(|v|, eps) along the last dimension, for autograd Functions that write their
    backward out: returns (u, |v|, max(|v|, eps)), the last two [...,1], which :func:`unit_backward` needs."""
    norm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    clamped = norm.clamp_min(eps)
    return v / clamped, norm, clamped


def unit_backward(grad: Tensor, u: Tensor, norm: Tensor, clamped: Tensor, eps: float = UNIT_EPS) -> Tensor:
    """The gradient through :func:`unit_forward`: (g - u (u . g) [|v| > eps]) / max(|v|, eps) (below eps
    the divisor is a constant, so only the first term)."""
    radial = _threshold_backward(torch.linalg.vecdot(u, grad).unsqueeze(-1), norm, eps)
    return torch.addcmul(grad, u, radial, value=-1.0) / clamped


class _ViewColors(torch.autograd.Function):
    """``max(SH(d) . sh + 0.5, 0)`` [N,3] along d = unit(R^T (means + alpha * offset)) (R: frames [N,3,3],
    or the identity for None) with the backward written out: the basis derivative is a product of the
    degree-1 monomials (kept from the forward) with a constant table, and the normalisation's and the
    frames' gradients are a few batched products, about 22 operations forward and backward where
    autograd records about 40. The clamp passes the gradient where the value is > 0 (autograd's clamp_min
    also at exactly 0)."""

    @staticmethod
    def forward(ctx, sh, means, offset, frames, alpha, degree):
        dtype, device = means.dtype, means.device
        diff = torch.add(means, offset, alpha=alpha)  # the camera -> Gaussian direction, world axes
        d = diff if frames is None else torch.bmm(diff.unsqueeze(-2), frames).squeeze(-2)  # R^T diff
        u, norm, clamped = unit_forward(d)
        m = torch.nn.functional.pad(u, (1, 0), value=1.0)  # [N,4]: 1, x, y, z
        prev, mono = None, m
        for _ in range(degree - 1):
            prev, mono = mono, (mono.unsqueeze(-1) * m.unsqueeze(-2)).flatten(-2)  # [N, 4^degree]
        basis = mono @ constant(_sh_table(degree), dtype, device)  # [N,K]
        half = constant(0.5, dtype, device).expand(means.shape[0], 1, 3)
        out = torch.baddbmm(half, basis.unsqueeze(-2), sh).squeeze(-2).clamp_min(0.0)
        ctx.degree, ctx.alpha = degree, alpha
        ctx.save_for_backward(sh, frames, diff, norm, clamped, u, prev, basis, out)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        sh, frames, diff, norm, clamped, u, prev, basis, out = ctx.saved_tensors
        need_sh, need_means, need_offset, need_frames = ctx.needs_input_grad[:4]
        g_sh = g_means = g_offset = g_frames = None
        grad = _threshold_backward(grad, out, 0.0)
        if need_sh:
            g_sh = torch.bmm(basis.unsqueeze(-1), grad.unsqueeze(-2))  # [N,K,3]
        if need_means or need_offset or need_frames:
            degree, n = ctx.degree, u.shape[0]
            g_basis = torch.bmm(sh, grad.unsqueeze(-1)).squeeze(-1)  # [N,K]
            g_u = g_basis @ constant(_sh_derivative_table(degree), u.dtype, u.device)  # [N, 3 * 4^(degree-1)]
            if degree > 1:
                g_u = torch.bmm(g_u.view(n, 3, -1), prev.unsqueeze(-1)).squeeze(-1)  # [N,3]
            g_d = unit_backward(g_u, u, norm, clamped)
            if frames is None:
                g_diff = g_d
            else:
                g_diff = torch.bmm(frames, g_d.unsqueeze(-1)).squeeze(-1)
                if need_frames:
                    g_frames = torch.bmm(diff.unsqueeze(-1), g_d.unsqueeze(-2))  # d (R^T diff)_j / d R_ij
            g_means = g_diff
            if need_offset:
                g_offset = g_diff.sum(0) * ctx.alpha
        return g_sh, g_means, g_offset, g_frames, None, None


def _constant_colors(sh: Tensor) -> Tensor:
    """Degree 0: ``max(C0 sh_0 + 0.5, 0)`` [N,3], the same from every direction."""
    return torch.clamp_min(sh[:, 0] * _C0 + 0.5, 0.0)


def sh_to_rgb(sh: Tensor, degree: int, means: Tensor, campos: Tensor) -> Tensor:
    """RGB [N,3] seen from ``campos`` [3]: SH coefficients sh [N,K,3] (K >= (degree+1)^2) evaluated
    along the camera->Gaussian direction, then ``max(value + 0.5, 0)`` as gsplat does."""
    if degree == 0:
        return _constant_colors(sh)
    return _ViewColors.apply(sh[:, : (degree + 1) ** 2], means, campos.to(means), None, -1.0, degree)


def view_colors(sh: Tensor, degree: int, means: Tensor, viewmat: Tensor, frames: Tensor | None = None) -> Tensor:
    """RGB [N,3] of SH coefficients sh [N,K,3] seen by the camera ``viewmat`` [4,4] (world -> camera).

    ``frames`` [N,3,3] (local -> world rotations) says the coefficients are expressed in per-Gaussian
    local axes: the view direction is turned into them first. None: world axes, as in a 3DGS file.
    """
    if degree == 0:
        return _constant_colors(sh)
    viewmat = viewmat.to(means)
    # means - campos = means + R^T t (campos = -R^T t): one product, no negation
    shift = viewmat[:3, :3].T @ viewmat[:3, 3]
    k = (degree + 1) ** 2
    return _ViewColors.apply(sh[:, :k], means, shift, frames, 1.0, degree)


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
