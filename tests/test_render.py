"""The CPU rasterizer against the dense float64 reference, edge cases and input checks."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from rmavatar.render import RasterInputError, rasterize
from rmavatar.render.project import sh_basis
from rmavatar.render.reference import reference_project, reference_rasterize

from devices import DEVICES

F64 = torch.float64
TOL = 1e-5
GRAD_ARGS = ("means", "quats", "scales", "opacities", "colors", "background")


def _camera(width, height, angle=0.3):
    c, s = math.cos(angle), math.sin(angle)
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=F64)
    viewmat[:3, 3] = torch.tensor([0.1, -0.05, 3.0], dtype=F64)
    K = torch.tensor([[0.9 * width, 0, width / 2 - 0.3], [0, 0.95 * width, height / 2 + 0.7], [0, 0, 1]], dtype=F64)
    return viewmat, K


def _scene(n, seed, sh_degree=None, width=40, height=32, opaque=False):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * 0.5
    quats = torch.randn(n, 4, generator=g, dtype=F64) * 2  # deliberately not normalised
    # Anisotropic: one axis up to 30x thinner than another.
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.25 + 0.008
    opacities = torch.rand(n, generator=g, dtype=F64)
    if opaque:  # push many to the 0.999 clamp so the transmittance stop is reached
        opacities = torch.where(opacities > 0.4, torch.ones_like(opacities), opacities * 0.5 + 0.5)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=F64)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=F64) * 0.4
    viewmat, K = _camera(width, height)
    background = torch.rand(3, generator=g, dtype=F64)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                background=background), viewmat, K, width, height


def _run(fn, params, viewmat, K, width, height, sh_degree, weights, **kw):
    p = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = fn(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], viewmat, K, width, height,
             background=p["background"], sh_degree=sh_degree, **kw)
    image, alpha, extra = out
    means2d = extra["means2d"] if isinstance(extra, dict) else extra
    if fn is reference_rasterize:
        means2d.retain_grad()
    ((image * weights[0]).sum() + (alpha * weights[1]).sum()).backward()
    grads = {k: p[k].grad for k in GRAD_ARGS}
    grads["means2d"] = means2d.grad
    return image.detach(), alpha.detach(), grads


def _compare(params, viewmat, K, width, height, sh_degree=None):
    g = torch.Generator().manual_seed(123)
    weights = (torch.randn(height, width, 3, generator=g, dtype=F64), torch.randn(height, width, 1, generator=g, dtype=F64))
    img, alpha, grads = _run(rasterize, params, viewmat, K, width, height, sh_degree, weights, backend="cpu")
    img_r, alpha_r, grads_r = _run(reference_rasterize, params, viewmat, K, width, height, sh_degree, weights)
    assert img.shape == (height, width, 3) and alpha.shape == (height, width, 1)
    torch.testing.assert_close(img, img_r, atol=TOL, rtol=0)
    torch.testing.assert_close(alpha, alpha_r, atol=TOL, rtol=0)
    for k in grads_r:
        assert torch.isfinite(grads[k]).all(), k
        torch.testing.assert_close(grads[k], grads_r[k], atol=TOL, rtol=0, msg=lambda m: f"d/d{k}: {m}")
    return img, alpha, grads


@pytest.mark.parametrize(
    "n,seed,sh_degree,size,opaque",
    [
        (1, 0, None, (40, 32), False),
        (25, 1, None, (40, 32), False),
        (120, 2, None, (37, 23), True),
        (80, 3, 0, (40, 32), False),
        (150, 4, 3, (40, 32), True),
        (60, 5, 1, (33, 41), False),
        (90, 6, 2, (40, 32), True),
    ],
)
def test_matches_dense_reference(n, seed, sh_degree, size, opaque):
    params, viewmat, K, w, h = _scene(n, seed, sh_degree, *size, opaque=opaque)
    img, alpha, grads = _compare(params, viewmat, K, w, h, sh_degree)
    assert alpha.max() > 0.1  # the scene is actually on screen
    assert grads["means"].abs().max() > 1e-3
    if opaque:
        # The 0.999 clamp and the transmittance stop are exercised: many layers, yet T stays > 1e-4.
        assert alpha.max() > 0.999 and alpha.max() < 1 - 1e-4


def test_overlapping_equal_depths_keep_index_order():
    params, viewmat, K, w, h = _scene(12, 7)
    params["means"][:, 2] = 0.2  # identical depths: ties resolved by index in both implementations
    _compare(params, viewmat, K, w, h)


def test_zero_gaussians():
    params, viewmat, K, w, h = _scene(0, 0)
    image, alpha, info = rasterize(params["means"], params["quats"], params["scales"], params["opacities"],
                                   params["colors"], viewmat, K, w, h, background=params["background"])
    assert torch.equal(image, params["background"].expand(h, w, 3))
    assert torch.equal(alpha, torch.zeros(h, w, 1, dtype=F64))
    assert info["means2d"].shape == (0, 2) and info["radii"].shape == (0,) and info["visible"].shape == (0,)


@pytest.mark.parametrize("where", ["behind", "offscreen"])
def test_invisible_gaussians_give_background_and_zero_grads(where):
    params, viewmat, K, w, h = _scene(20, 8)
    if where == "behind":
        params["means"][:, 2] = -3.5 - params["means"][:, 2].abs()  # camera z = world z + 3 < 0
    else:
        params["means"][:, 0] += 40.0  # far to the side, in front of the camera
        params["scales"] = params["scales"] * 0.1
    p = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    image, alpha, info = rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                   viewmat, K, w, h, background=p["background"])
    assert not info["visible"].any() and (info["radii"] == 0).all()
    torch.testing.assert_close(image.detach(), params["background"].expand(h, w, 3), atol=0, rtol=0)
    assert (alpha == 0).all()
    image.sum().backward()
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(p[k].grad, torch.zeros_like(p[k])), k
    torch.testing.assert_close(p["background"].grad, torch.full((3,), float(w * h), dtype=F64))


def test_zero_scales_render_as_dilated_dots():
    params, viewmat, K, w, h = _scene(15, 9)
    params["scales"] = torch.zeros_like(params["scales"])
    img, alpha, grads = _compare(params, viewmat, K, w, h)
    assert alpha.max() > 0.01  # the 0.3 px^2 low-pass keeps degenerate Gaussians visible


def test_one_gaussian_covers_the_image():
    params, viewmat, K, w, h = _scene(1, 10)
    params["means"] = torch.tensor([[0.0, 0.0, 0.5]], dtype=F64)
    params["scales"] = torch.tensor([[20.0, 15.0, 10.0]], dtype=F64)
    params["opacities"] = torch.tensor([0.7], dtype=F64)
    img, alpha, grads = _compare(params, viewmat, K, w, h)
    assert alpha.min() > 0.6 and alpha.max() <= 0.7 + 1e-12  # every pixel covered, nearly flat


def test_means2d_grad_and_info():
    params, viewmat, K, w, h = _scene(30, 11)
    p = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    image, alpha, info = rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                   viewmat, K, w, h)
    assert set(info) >= {"means2d", "radii", "visible", "depths"}
    assert info["radii"].dtype == torch.int32 and info["radii"].shape == (30,)
    assert torch.equal(info["visible"], info["radii"] > 0)
    depth_expected = (p["means"] @ viewmat[:3, :3].T + viewmat[:3, 3])[:, 2]
    torch.testing.assert_close(info["depths"].detach(), depth_expected.detach())
    image.sum().backward()
    g = info["means2d"].grad
    assert g is not None and g.shape == (30, 2) and g[info["visible"]].abs().sum() > 0


def test_float32_inputs():
    params, viewmat, K, w, h = _scene(40, 12)
    p32 = {k: v.float() for k, v in params.items()}
    img, alpha, _ = rasterize(p32["means"], p32["quats"], p32["scales"], p32["opacities"], p32["colors"],
                              viewmat.float(), K.float(), w, h, background=p32["background"])
    ref, ref_a, _ = reference_rasterize(*(params[k] for k in ("means", "quats", "scales", "opacities", "colors")),
                                        viewmat, K, w, h, background=params["background"])
    assert img.dtype == torch.float32
    torch.testing.assert_close(img.double(), ref, atol=1e-4, rtol=0)


@pytest.mark.parametrize("arg", ["means", "quats", "scales", "opacities", "colors", "background"])
def test_nan_input_is_a_clear_error(arg):
    params, viewmat, K, w, h = _scene(5, 13)
    params[arg] = params[arg].clone()
    params[arg].view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=arg):
        rasterize(params["means"], params["quats"], params["scales"], params["opacities"], params["colors"],
                  viewmat, K, w, h, background=params["background"])


def test_bad_inputs_are_clear_errors():
    params, viewmat, K, w, h = _scene(5, 14)
    args = [params[k] for k in ("means", "quats", "scales", "opacities", "colors")]
    with pytest.raises(RasterInputError, match="viewmat"):
        rasterize(*args, viewmat.clone().fill_(float("inf")), K, w, h)
    with pytest.raises(RasterInputError, match=r"quats must have shape \[5,4\]"):
        rasterize(args[0], args[1][:, :3], *args[2:], viewmat, K, w, h)
    with pytest.raises(RasterInputError, match="width"):
        rasterize(*args, viewmat, K, 0, h)
    with pytest.raises(RasterInputError, match="zero-length"):
        rasterize(args[0], torch.zeros(5, 4, dtype=F64), *args[2:], viewmat, K, w, h)
    with pytest.raises(RasterInputError, match="sh_degree"):
        rasterize(*args[:4], torch.zeros(5, 4, 3, dtype=F64), viewmat, K, w, h, sh_degree=2)
    with pytest.raises(RasterInputError, match="backend"):
        rasterize(*args, viewmat, K, w, h, backend="opengl")


def test_sh_basis_matches_scipy_real_harmonics():
    """gsplat's basis: real SH with the Condon-Shortley phase, m = -l..l (sin terms first)."""
    scipy_special = pytest.importorskip("scipy.special")
    g = torch.Generator().manual_seed(0)
    d = torch.randn(50, 3, generator=g, dtype=F64)
    d = d / d.norm(dim=-1, keepdim=True)
    ours = sh_basis(3, d).numpy()
    theta = np.arccos(d[:, 2].numpy())  # polar
    phi = np.arctan2(d[:, 1].numpy(), d[:, 0].numpy())
    col = 0
    for l in range(4):
        for m in range(-l, l + 1):
            y = scipy_special.sph_harm_y(l, abs(m), theta, phi)
            want = y.real if m == 0 else math.sqrt(2) * (y.imag if m < 0 else y.real)
            np.testing.assert_allclose(ours[:, col], want, atol=1e-12, err_msg=f"l={l} m={m}")
            col += 1


def test_sh_colors_match_the_basis_formula():
    """The colours from the monomial table (and their gradients w.r.t. the coefficients and the
    positions) equal the per-term basis of sh_basis, float64, for every degree; view_colors too."""
    from rmavatar.render.project import sh_to_rgb, view_colors

    g = torch.Generator().manual_seed(1)
    means = torch.randn(40, 3, generator=g, dtype=F64, requires_grad=True)
    sh = torch.randn(40, 16, 3, generator=g, dtype=F64, requires_grad=True)
    campos = torch.tensor([0.3, -0.2, 2.5], dtype=F64)
    frames = torch.linalg.qr(torch.randn(40, 3, 3, generator=g, dtype=F64)).Q
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, 3] = torch.tensor([0.1, 0.2, 3.0], dtype=F64)
    cam = -viewmat[:3, 3]
    grad = torch.randn(40, 3, generator=g, dtype=F64)
    for degree in range(4):
        k = (degree + 1) ** 2
        for ours, dirs in ((sh_to_rgb(sh, degree, means, campos), means - campos),
                           (view_colors(sh, degree, means, viewmat, frames),
                            torch.einsum("nji,nj->ni", frames, means - cam))):
            plain = torch.clamp_min((sh_basis(degree, dirs)[:, :, None] * sh[:, :k]).sum(1) + 0.5, 0.0)
            torch.testing.assert_close(ours, plain, rtol=0, atol=1e-13)
            for a, b in zip(torch.autograd.grad(ours, (means, sh), grad, allow_unused=True),
                            torch.autograd.grad(plain, (means, sh), grad, allow_unused=True)):
                if b is None or a is None:  # degree 0: no dependence on the position
                    assert degree == 0 and (a is None or not a.any()) and (b is None or not b.any())
                else:
                    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def _view_colors_plain(sh, degree, means, viewmat, frames):
    """The colours from sh_basis (one autograd operation per basis term), the view direction turned into
    the frames' axes: the reference for view_colors' written-out backward."""
    campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
    dirs = torch.einsum("nji,nj->ni", frames, means - campos)
    k = (degree + 1) ** 2
    return torch.clamp_min((sh_basis(degree, dirs)[:, :, None] * sh[:, :k]).sum(1) + 0.5, 0.0)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_view_colors_gradients_match_the_plain_formula(device, degree):
    """Values and gradients w.r.t. the coefficients, the positions, the frames and the camera, float64,
    with a Gaussian at the camera centre (direction shorter than eps) and clamped (negative) colours."""
    from rmavatar.render.project import view_colors

    g = torch.Generator().manual_seed(2)
    n = 50
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64)).Q
    viewmat[:3, 3] = torch.tensor([0.1, 0.2, 3.0], dtype=F64)
    means = torch.randn(n, 3, generator=g, dtype=F64)
    means[0] = -viewmat[:3, :3].T @ viewmat[:3, 3]  # at the camera: no direction
    frames = torch.randn(n, 3, 3, generator=g, dtype=F64)  # any matrices: the formula does not need rotations
    sh = torch.randn(n, 16, 3, generator=g, dtype=F64) * 0.5
    inputs = [t.to(device).requires_grad_(True) for t in (sh, means, viewmat, frames)]
    ours = view_colors(inputs[0], degree, inputs[1], inputs[2], inputs[3])
    plain = _view_colors_plain(inputs[0], degree, inputs[1], inputs[2], inputs[3])
    assert (plain == 0).any() and (plain > 0).any()  # both sides of the clamp
    torch.testing.assert_close(ours, plain, rtol=0, atol=1e-13)
    grad = torch.randn(n, 3, generator=g, dtype=F64).to(device)
    for a, b in zip(torch.autograd.grad(ours, inputs, grad), torch.autograd.grad(plain, inputs, grad)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_view_colors_pass_gradcheck(degree):
    from rmavatar.render.project import sh_to_rgb, view_colors

    g = torch.Generator().manual_seed(3)
    n = 5
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, 3] = torch.tensor([0.1, 0.2, 3.0], dtype=F64)
    inputs = [torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=F64) * 0.1]  # colours stay above 0
    inputs += [torch.randn(n, 3, generator=g, dtype=F64), viewmat, torch.randn(n, 3, 3, generator=g, dtype=F64)]
    inputs = [t.requires_grad_(True) for t in inputs]
    assert torch.autograd.gradcheck(lambda sh, m, v, f: view_colors(sh, degree, m, v, f), inputs)
    campos = torch.tensor([0.3, -0.2, 2.5], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda sh, m, c: sh_to_rgb(sh, degree, m, c), (inputs[0], inputs[1], campos))


def test_gsplat_backend_without_gsplat_is_a_clear_error():
    pytest.importorskip("torch")
    try:
        import gsplat  # noqa: F401
        pytest.skip("gsplat is installed")
    except ImportError:
        pass
    from rmavatar.utils import UserError

    params, viewmat, K, w, h = _scene(3, 15)
    args = [params[k] for k in ("means", "quats", "scales", "opacities", "colors")]
    with pytest.raises(UserError, match="gsplat|CUDA"):
        rasterize(*args, viewmat, K, w, h, backend="gsplat")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device and gsplat")
def test_gsplat_matches_cpu():
    pytest.importorskip("gsplat")
    params, viewmat, K, w, h = _scene(150, 16, sh_degree=3, width=64, height=48)
    g = torch.Generator().manual_seed(1)
    weights = (torch.randn(h, w, 3, generator=g, dtype=F64), torch.randn(h, w, 1, generator=g, dtype=F64))
    cpu = _run(rasterize, {k: v.float() for k, v in params.items()}, viewmat.float(), K.float(), w, h, 3,
               tuple(x.float() for x in weights), backend="cpu")
    cuda = _run(rasterize, {k: v.float().cuda() for k, v in params.items()}, viewmat.float().cuda(),
                K.float().cuda(), w, h, 3, tuple(x.float().cuda() for x in weights), backend="gsplat")
    torch.testing.assert_close(cuda[0].cpu(), cpu[0], atol=1e-4, rtol=0)
    torch.testing.assert_close(cuda[1].cpu(), cpu[1], atol=1e-4, rtol=0)
    for k in cpu[2]:
        torch.testing.assert_close(cuda[2][k].cpu(), cpu[2][k], atol=2e-3, rtol=1e-3, msg=lambda m: f"d/d{k}: {m}")


def test_numba_cache_goes_to_rmavatar_cache(tmp_path, monkeypatch):
    env = dict(os.environ, RMAVATAR_CACHE=str(tmp_path))
    env.pop("NUMBA_CACHE_DIR", None)
    code = "import rmavatar.render.kernels, os; print(os.environ['NUMBA_CACHE_DIR'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(tmp_path / "numba")
    # A user's own setting is left alone.
    from rmavatar.render import _numba

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    _numba._configure_cache()
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")


def test_needles_and_giants():
    """Extremely thin and very large Gaussians: exact in float64, finite in float32."""
    params, viewmat, K, w, h = _scene(6, 17)
    params["scales"] = torch.tensor(
        [[3.0, 1e-6, 1e-6], [1e-6, 2.0, 1e-6], [1e-7, 1e-7, 5.0], [5e9, 4e9, 1e-3], [1e-3, 1e-3, 1e-3], [0.3, 1e-5, 0.2]],
        dtype=F64)
    params["means"][:, 2] = torch.linspace(-1, 1, 6, dtype=F64)
    _compare(params, viewmat, K, w, h)
    p32 = {k: v.float() for k, v in params.items()}
    img, alpha, _ = rasterize(p32["means"], p32["quats"], p32["scales"], p32["opacities"], p32["colors"],
                              viewmat.float(), K.float(), w, h, background=p32["background"])
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()


def test_projection_and_sh_match_gsplat_torch_reference():
    """Where gsplat is installed (any machine), its pure-torch reference agrees with our projection/SH."""
    pytest.importorskip("gsplat")
    ti = pytest.importorskip("gsplat.cuda._torch_impl")
    from rmavatar.render.project import project_gaussians, sh_to_rgb

    params, viewmat, K, w, h = _scene(300, 18, sh_degree=3, width=64, height=48)
    m, q, s, o = (params[k] for k in ("means", "quats", "scales", "opacities"))
    covars, _ = ti._quat_scale_to_covar_preci(q, s, compute_covar=True, compute_preci=False, triu=False)
    radii, means2d, depths, conics, _ = ti._fully_fused_projection(
        m, covars, viewmat[None], K[None], w, h, eps2d=0.3, near_plane=0.01, far_plane=1e10)
    ours = project_gaussians(m, q, s, o, viewmat, K, w, h)
    both = ours.visible & (radii[0] > 0).all(-1)
    assert both.sum() > 100 and not (ours.visible & ~(radii[0] > 0).all(-1)).any()
    torch.testing.assert_close(ours.means2d[both], means2d[0][both])
    torch.testing.assert_close(ours.conics[both], conics[0][both])
    torch.testing.assert_close(ours.depths[both], depths[0][both])
    campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
    theirs = torch.clamp_min(ti._spherical_harmonics(3, m - campos, params["colors"]) + 0.5, 0.0)
    torch.testing.assert_close(sh_to_rgb(params["colors"], 3, m, campos), theirs)


def test_gsplat_backend_plumbing_with_a_stand_in(monkeypatch):
    """The gsplat wrapper's reshaping and means2d gradient, with gsplat 1.5.3's call signature and
    output layout imitated on the CPU (the real library needs CUDA)."""
    import types

    from rmavatar.render import gsplat_backend
    from rmavatar.render.cpu import composite, project
    from rmavatar.render.project import sh_to_rgb

    def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
                           near_plane, eps2d, sh_degree, packed, tile_size, backgrounds, render_mode,
                           rasterize_mode):
        assert (near_plane, eps2d, packed, tile_size, render_mode, rasterize_mode) == (
            0.01, 0.3, False, 16, "RGB", "classic")
        assert means.dtype == torch.float32 and viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3)
        proj = project(means, quats, scales, opacities, viewmats[0], Ks[0], width, height)
        means2d_c = proj.means2d[None]  # gsplat composites with the batched [C,N,2] tensor
        campos = -viewmats[0, :3, :3].T @ viewmats[0, :3, 3]
        rgb = sh_to_rgb(colors, sh_degree, means, campos) if sh_degree is not None else colors
        image, alpha = composite(means2d_c[0], proj.conics, rgb, opacities, backgrounds[0],
                                 proj.radii_xy, proj.depths, proj.visible, width, height)
        meta = {"means2d": means2d_c, "radii": proj.radii_xy[None], "depths": proj.depths[None]}
        return image[None], alpha[None], meta

    monkeypatch.setattr(gsplat_backend, "_import_gsplat", lambda: types.SimpleNamespace(rasterization=fake_rasterization))
    monkeypatch.setattr(gsplat_backend, "_check_device", lambda means: None)
    params, viewmat, K, w, h = _scene(40, 19, sh_degree=2)
    p32 = {k: v.float() for k, v in params.items()}
    outs = {}
    for backend in ("cpu", "gsplat"):
        p = {k: v.clone().requires_grad_(True) for k, v in p32.items()}
        image, alpha, info = rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                       viewmat.float(), K.float(), w, h, background=p["background"],
                                       sh_degree=2, backend=backend)
        (image.sum() + 2 * alpha.sum()).backward()
        outs[backend] = (image, alpha, info, p["means"].grad)
    (i1, a1, info1, g1), (i2, a2, info2, g2) = outs["cpu"], outs["gsplat"]
    assert info2["backend"] == "gsplat" and i2.shape == (h, w, 3) and a2.shape == (h, w, 1)
    torch.testing.assert_close(i2, i1)
    torch.testing.assert_close(g2, g1)
    assert info2["radii"].shape == (40,) and info2["radii"].dtype == torch.int32
    assert torch.equal(info2["radii"], info1["radii"]) and torch.equal(info2["visible"], info1["visible"])
    assert info2["means2d"].shape == (40, 2)
    torch.testing.assert_close(info2["means2d"].grad, info1["means2d"].grad)


def test_numba_projection_matches_torch_statement():
    """The fused Numba projection (values and analytic gradients) against the readable PyTorch one."""
    from rmavatar.render.cpu import project
    from rmavatar.render.project import project_gaussians

    params, viewmat, K, w, h = _scene(200, 20, width=50, height=30)
    params["means"][:20, 2] -= 4.0  # some behind the camera
    params["means"][20:40, 0] += 6.0  # some far off to the side (frustum clamp)
    g = torch.Generator().manual_seed(3)
    wts = [torch.randn(200, k, generator=g, dtype=F64) for k in (2, 3, 1)]
    out = {}
    for name, fn in (("numba", project), ("torch", project_gaussians)):
        p = {k: params[k].clone().requires_grad_(True) for k in ("means", "quats", "scales")}
        proj = fn(p["means"], p["quats"], p["scales"], params["opacities"], viewmat, K, w, h)
        vis = proj.visible
        loss = ((proj.means2d * wts[0])[vis].sum() + (proj.conics * wts[1])[vis].sum()
                + (proj.depths * wts[2][:, 0]).sum())
        loss.backward()
        out[name] = (proj, {k: v.grad for k, v in p.items()})
    (pn, gn), (pt, gt) = out["numba"], out["torch"]
    assert torch.equal(pn.visible, pt.visible) and torch.equal(pn.radii_xy, pt.radii_xy)
    assert 50 < pn.visible.sum() < 200
    v = pn.visible
    torch.testing.assert_close(pn.means2d[v], pt.means2d[v], atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(pn.conics[v], pt.conics[v], atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(pn.depths, pt.depths, atol=1e-12, rtol=0)
    for k in gn:
        torch.testing.assert_close(gn[k], gt[k], atol=1e-9, rtol=1e-9, msg=lambda m: f"d/d{k}: {m}")


def _guard_band_scene():
    """Large Gaussians whose centres lie beyond gsplat's 1.3x-frustum guard band (in x, in y, in both,
    on both sides) but whose footprints still reach the image, plus ordinary ones inside."""
    params, viewmat, K, w, h = _scene(24, 21, width=40, height=32)
    pc = torch.tensor([
        [2.6, 0.1, 3.0], [-2.7, -0.2, 3.2], [0.2, 2.4, 2.8], [-0.1, -2.2, 3.1], [2.5, 2.3, 3.0],
        [-2.4, 2.6, 2.9], [1.9, -0.3, 2.5], [-0.3, 1.8, 2.6],
    ], dtype=F64)
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    params["means"][:8] = (pc - tv) @ Rv  # camera -> world
    params["scales"][:8] = torch.tensor([0.9, 0.7, 1.1], dtype=F64)
    params["opacities"][:8] = 0.6
    return params, viewmat, K, w, h


def _beyond_band(means, viewmat, K, w, h):
    pc = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    u, v = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out_x = (u > (w - cx) / fx + 0.15 * w / fx) | (u < -(cx / fx + 0.15 * w / fx))
    out_y = (v > (h - cy) / fy + 0.15 * h / fy) | (v < -(cy / fy + 0.15 * h / fy))
    return out_x, out_y


def test_matches_dense_reference_beyond_the_guard_band():
    """Gaussians clamped in x, in y and in both still get the reference's gradients (gsplat's rule)."""
    params, viewmat, K, w, h = _guard_band_scene()
    out_x, out_y = _beyond_band(params["means"], viewmat, K, w, h)
    assert out_x[:8].sum() >= 3 and out_y[:8].sum() >= 3 and (out_x & out_y).any()
    _, _, grads = _compare(params, viewmat, K, w, h)
    assert grads["means"][:8].abs().amax(-1).min() > 1e-4  # the clamped ones are on screen and matter


@pytest.mark.parametrize("impl", ["numba", "torch", "reference"])
def test_projection_gradients_match_finite_differences(impl):
    """d(means2d, conics, depths)/d(means, quats, scales) of each projection against central finite
    differences in float64, with centres inside and beyond the guard band (where the clamped
    component of J depends on z only: the rule gsplat 1.5.3 differentiates)."""
    from rmavatar.render.cpu import project
    from rmavatar.render.project import project_gaussians

    params, viewmat, K, w, h = _guard_band_scene()
    keep = slice(0, 12)
    base = {k: params[k][keep].clone() for k in ("means", "quats", "scales")}
    opac = params["opacities"][keep]
    out_x, out_y = _beyond_band(base["means"], viewmat, K, w, h)
    # Away from the band's bounds, so a finite-difference step never crosses them.
    assert out_x.any() and out_y.any() and (~out_x & ~out_y).any()
    g = torch.Generator().manual_seed(5)
    wts = [torch.randn(12, k, generator=g, dtype=F64) for k in (2, 3, 1)]

    def loss_of(p):
        if impl == "reference":
            means2d, inv, depths, _ = reference_project(p["means"], p["quats"], p["scales"], opac, viewmat, K, w, h)
            conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
        else:
            fn = project if impl == "numba" else project_gaussians
            proj = fn(p["means"], p["quats"], p["scales"], opac, viewmat, K, w, h)
            means2d, conics, depths = proj.means2d, proj.conics, proj.depths
        return (means2d * wts[0]).sum() + (conics * wts[1]).sum() + (depths * wts[2][:, 0]).sum()

    p = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    loss_of(p).backward()
    eps = 1e-6
    for k in base:
        num = torch.zeros_like(base[k])
        for idx in np.ndindex(*base[k].shape):
            hi = {kk: vv.clone() for kk, vv in base.items()}
            lo = {kk: vv.clone() for kk, vv in base.items()}
            hi[k][idx] += eps
            lo[k][idx] -= eps
            num[idx] = (loss_of(hi) - loss_of(lo)) / (2 * eps)
        torch.testing.assert_close(p[k].grad, num, atol=1e-6, rtol=1e-6, msg=lambda m: f"{impl} d/d{k}: {m}")


def test_projection_gradients_match_gsplat_torch_reference():
    """Where gsplat is installed (any machine: its pure-torch reference needs no CUDA), the gradients
    of our projections agree with autograd through gsplat 1.5.3's ``_fully_fused_projection``,
    including centres beyond the guard band (its clamp is differentiated)."""
    ti = pytest.importorskip("gsplat.cuda._torch_impl")
    from rmavatar.render.cpu import project
    from rmavatar.render.project import project_gaussians, quat_to_rotmat

    params, viewmat, K, w, h = _guard_band_scene()
    out_x, out_y = _beyond_band(params["means"], viewmat, K, w, h)
    assert out_x.any() and out_y.any()
    n = len(params["opacities"])
    g = torch.Generator().manual_seed(6)
    wts = [torch.randn(n, k, generator=g, dtype=F64) for k in (2, 3, 1)]
    grads = {}
    for name in ("gsplat", "numba", "torch"):
        p = {k: params[k].clone().requires_grad_(True) for k in ("means", "quats", "scales")}
        if name == "gsplat":  # its quaternion->matrix is no_grad, so the covariance is built here
            M = quat_to_rotmat(p["quats"]) * p["scales"][:, None, :]
            _, means2d, depths, conics, _ = ti._fully_fused_projection(
                p["means"], M @ M.transpose(-1, -2), viewmat[None], K[None], w, h, eps2d=0.3)
            means2d, depths, conics = means2d[0], depths[0], conics[0]
        else:
            fn = project if name == "numba" else project_gaussians
            proj = fn(p["means"], p["quats"], p["scales"], params["opacities"], viewmat, K, w, h)
            means2d, conics, depths = proj.means2d, proj.conics, proj.depths
        ((means2d * wts[0]).sum() + (conics * wts[1]).sum() + (depths * wts[2][:, 0]).sum()).backward()
        grads[name] = {k: v.grad for k, v in p.items()}
    for name in ("numba", "torch"):
        for k in grads[name]:
            torch.testing.assert_close(grads[name][k], grads["gsplat"][k], atol=1e-9, rtol=1e-9,
                                       msg=lambda m: f"{name} d/d{k}: {m}")


def test_unchecked_inputs_cull_non_finite_gaussians():
    """check=False (training: no host sync) draws non-finite Gaussians as if absent, on the CPU kernels
    and in the device-side cull used before gsplat."""
    from rmavatar.render.rasterize import _cull_non_finite

    params, viewmat, K, w, h = _scene(30, 22)
    keep = torch.ones(30, dtype=torch.bool)
    keep[[3, 7, 11, 15]] = False
    args = [params[k] for k in ("means", "quats", "scales", "opacities", "colors")]
    clean_img, clean_alpha, _ = rasterize(*[a[keep] for a in args], viewmat, K, w, h,
                                          background=params["background"])
    bad = [a.clone() for a in args]
    bad[0][3, 0] = float("nan")  # x only: a rotation with zeros could keep z finite
    bad[1][7] = 0.0
    bad[2][11, 1] = float("inf")
    bad[3][15] = float("nan")
    img, alpha, info = rasterize(*bad, viewmat, K, w, h, background=params["background"], check=False)
    torch.testing.assert_close(img, clean_img, atol=1e-12, rtol=0)
    torch.testing.assert_close(alpha, clean_alpha, atol=1e-12, rtol=0)
    assert not info["visible"][~keep].any()
    culled = _cull_non_finite(*bad)
    assert all(torch.isfinite(t).all() for t in culled)
    assert (culled[3][~keep] == 0).all() and torch.equal(culled[3][keep], bad[3][keep])
    with pytest.raises(RasterInputError, match="NaN"):
        rasterize(*bad, viewmat, K, w, h)


@pytest.mark.parametrize("device", DEVICES)
def test_rasterize_on_each_device_matches_the_reference(device):
    """float32 tensors on the device through the default backend (CPU kernels / gsplat on CUDA)
    against the dense float64 reference: image, alpha and d/dmeans; outputs stay on the device."""
    if device == "cuda":
        pytest.importorskip("gsplat")
    params, viewmat, K, w, h = _scene(60, 23, sh_degree=1, width=48, height=40)
    g = torch.Generator().manual_seed(2)
    weights = (torch.randn(h, w, 3, generator=g, dtype=F64), torch.randn(h, w, 1, generator=g, dtype=F64))
    on = _run(rasterize, {k: v.float().to(device) for k, v in params.items()}, viewmat.float().to(device),
              K.float().to(device), w, h, 1, tuple(x.float().to(device) for x in weights))
    ref = _run(reference_rasterize, params, viewmat, K, w, h, 1, weights)
    assert on[0].device.type == device and on[2]["means"].device.type == device
    torch.testing.assert_close(on[0].cpu().double(), ref[0], atol=1e-4, rtol=0)
    torch.testing.assert_close(on[1].cpu().double(), ref[1], atol=1e-4, rtol=0)
    torch.testing.assert_close(on[2]["means"].cpu().double(), ref[2]["means"], atol=2e-3, rtol=1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_the_mirrored_means2d_gradient_lets_the_step_graph_go(device):
    # gsplat's [1,N,2] means2d mirrored onto its [N,2] view (as the CUDA backend does, shown here on any
    # device): the view gets the gradient, and once the caller drops it the step's graph goes with it (a
    # hook closure holding the view kept every step's graph alive, with the gradient accumulators it
    # made on the default stream: a later CUDA graph capture then failed, docs/gpu.md).
    import gc
    import weakref

    from rmavatar.render.gsplat_backend import mirror_grad

    param = torch.randn(5, 2, device=device, requires_grad=True)

    def step():  # what the backend returns to the caller: the view, in info["means2d"]
        batched = (param * 2.0)[None]  # [1,5,2]
        view = batched[0]
        mirror_grad(batched, view)
        (batched * torch.arange(10.0, device=device).view(1, 5, 2)).sum().backward()
        return view

    view = step()
    torch.testing.assert_close(view.grad, torch.arange(10.0, device=device).view(5, 2))
    ref = weakref.ref(view)
    del view
    gc.collect()
    assert ref() is None
