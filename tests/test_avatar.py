"""Geometry, mesh-embedded Gaussians and the rectifier (docs/model.md)."""

import math

import numpy as np
import pytest
import torch
import trimesh

from rmavatar.avatar import (
    GAUSSIAN_PARAMS,
    SH_C0,
    Avatar,
    AvatarConfig,
    Rectifier,
    area_counts,
    positional_encoding,
    quat_multiply,
    quat_to_rotmat,
    rotmat_to_quat,
    triangle_frames,
    window_alpha,
)
from rmavatar.avatar.geometry import same_quads
from rmavatar.body import load_body_model
from rmavatar.utils import UserError

from devices import DEVICES

# These tests check the paper's design on a bare mesh (no skinning weights); the local design, the
# default, has its own tests in test_rectifier.py.
PAPER = AvatarConfig(rectifier="paper")


def sphere():
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    v = torch.tensor(m.vertices, dtype=torch.float32)
    # Stretch it so triangles differ in size and shape.
    v = v * torch.tensor([1.0, 2.0, 0.7])
    return v, torch.tensor(m.faces, dtype=torch.long)


def random_rotation(gen, dtype=torch.float64):
    q = torch.randn(4, generator=gen, dtype=dtype)
    return quat_to_rotmat(q / q.norm())


def randomise(avatar, gen):
    """Give the local parameters non-trivial values."""
    with torch.no_grad():
        for p in (getattr(avatar, name) for name in GAUSSIAN_PARAMS):
            p.copy_(torch.randn(p.shape, generator=gen, dtype=p.dtype) * 0.5)


def frames_reference(v, f):
    """Independent float64 numpy version of the frame formulas."""
    v = np.asarray(v, np.float64)
    R, W, M = [], [], []
    for a, b, c in np.asarray(f):
        e1, e2 = v[b] - v[a], v[c] - v[a]
        a0 = e1 / np.linalg.norm(e1)
        n = np.cross(a0, e2)
        a1 = n / np.linalg.norm(n)
        a2 = np.cross(a0, a1)
        R.append(np.stack([a0, a1, a2], 1))
        W.append((np.linalg.norm(e1) + abs(a2 @ e2)) / 2)
        M.append((v[a] + v[b] + v[c]) / 3)
    return np.array(R), np.array(W), np.array(M)


# ---------------------------------------------------------------- geometry
def test_frames_orthonormal_and_match_reference():
    v, f = sphere()
    vb = torch.stack([v, v * 1.3 + 0.1])
    R, w, M = triangle_frames(vb, f)
    assert R.shape == (2, f.shape[0], 3, 3) and w.shape == (2, f.shape[0]) and M.shape == (2, f.shape[0], 3)
    eye = torch.eye(3).expand_as(R)
    assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(2, f.shape[0]), atol=1e-5)
    Rr, Wr, Mr = frames_reference(v, f)
    np.testing.assert_allclose(R[0].numpy(), Rr, atol=1e-5)
    np.testing.assert_allclose(w[0].numpy(), Wr, rtol=1e-5)
    np.testing.assert_allclose(M[0].numpy(), Mr, atol=1e-6)
    np.testing.assert_allclose(w[1].numpy(), 1.3 * Wr, rtol=1e-5)
    # a0 along the first edge, a1 the normal: both orthogonal to the in-plane edge / normal.
    e1 = v[f[:, 1]] - v[f[:, 0]]
    assert torch.allclose(R[0, :, :, 0], e1 / e1.norm(dim=-1, keepdim=True), atol=1e-6)


def test_frames_of_a_known_triangle():
    v = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0.5, 1, 0]])
    R, w, M = triangle_frames(v, torch.tensor([[0, 1, 2]]))
    # a0 = x, a1 = x cross (0.5,1,0) = +z, a2 = a0 x a1 = -y; w = (2 + |-1|)/2.
    assert torch.allclose(R[0], torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), atol=1e-6)
    assert torch.isclose(w[0], torch.tensor(1.5))
    assert torch.allclose(M[0], torch.tensor([2.5 / 3, 1 / 3, 0]))


def test_degenerate_triangles_stay_finite():
    v = torch.tensor([[0.0, 0, 0], [0, 0, 0], [1, 0, 0], [2, 0, 0]], requires_grad=True)
    f = torch.tensor([[0, 1, 2], [0, 2, 3], [1, 1, 1]])  # zero edge, collinear, a point
    R, w, M = triangle_frames(v, f)
    q = rotmat_to_quat(R)
    assert torch.isfinite(R).all() and torch.isfinite(w).all() and torch.isfinite(q).all()
    (R.sum() + w.sum() + q.sum()).backward()
    assert torch.isfinite(v.grad).all()


def test_quaternion_round_trip_and_product():
    gen = torch.Generator().manual_seed(1)
    q = torch.randn(500, 4, generator=gen, dtype=torch.float64)
    # Include near-180-degree rotations (w ~ 0), where naive formulas break.
    q[:50, 0] = 1e-9
    q = q / q.norm(dim=-1, keepdim=True)
    R = quat_to_rotmat(q)
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12)
    q2 = rotmat_to_quat(R)
    # q and -q are the same rotation.
    assert torch.allclose(torch.minimum((q2 - q).abs().amax(-1), (q2 + q).abs().amax(-1)),
                          torch.zeros(500, dtype=torch.float64), atol=1e-9)
    a, b = q[:250], q[250:]
    assert torch.allclose(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-12)


# ---------------------------------------------------------------- embedding
def test_init_values_and_centroid():
    v, f = sphere()
    av = Avatar(f, None, v, AvatarConfig(rectifier=False))
    assert av.num_gaussians == f.shape[0]
    assert torch.equal(av.face_ids, torch.arange(f.shape[0]))
    g, extras = av.forward_with_extras(v)
    assert torch.allclose(g.means, v[f].mean(1), atol=1e-6)
    assert torch.allclose(g.opacities, torch.full((f.shape[0],), 0.1))
    assert torch.allclose(0.5 + SH_C0 * g.sh[:, 0], torch.full((f.shape[0], 3), 0.5))
    assert g.sh.shape == (f.shape[0], 1, 3) and g.sh_degree == 0 and extras.offsets is None
    _, w, _ = triangle_frames(v, f)
    assert torch.allclose(g.scales, w.unsqueeze(-1).expand(-1, 3), rtol=1e-6)
    R, _, _ = triangle_frames(v, f)
    assert torch.allclose(quat_to_rotmat(g.quats), R, atol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_gaussians_move_rigidly_with_a_rigid_mesh(device):
    v, f = sphere()
    gen = torch.Generator().manual_seed(2)
    av = Avatar(f, None, v, AvatarConfig(rectifier=False)).double()
    randomise(av, gen)
    av.to(device)
    v = v.double().to(device)
    g0 = av(v)
    assert g0.means.device.type == device
    for _ in range(3):
        Q = random_rotation(gen).to(device)
        t = torch.randn(3, generator=gen, dtype=torch.float64).to(device)
        c = float(torch.rand(1, generator=gen)) * 2 + 0.2
        g1 = av(c * v @ Q.T + t)
        assert torch.allclose(g1.means, c * g0.means @ Q.T + t, atol=1e-10)
        assert torch.allclose(quat_to_rotmat(g1.quats), Q @ quat_to_rotmat(g0.quats), atol=1e-10)
        assert torch.allclose(g1.scales / g0.scales, torch.full_like(g0.scales, c), rtol=1e-10)


def test_rotated_sh_evaluates_like_local_sh_along_local_directions():
    from rmavatar.render.project import rotate_sh, sh_rotation_matrices, sh_to_rgb

    gen = torch.Generator().manual_seed(5)
    R = torch.stack([random_rotation(gen) for _ in range(6)])
    sh = torch.randn(6, 16, 3, generator=gen, dtype=torch.float64) * 0.3
    world = rotate_sh(sh, sh_rotation_matrices(R, 3))
    assert torch.equal(world[:, 0], sh[:, 0])  # band 0 does not turn
    for _ in range(5):
        d = torch.randn(6, 3, generator=gen, dtype=torch.float64)  # camera -> Gaussian, world axes
        local_d = torch.einsum("nji,nj->ni", R, d)  # R^T d
        zero = torch.zeros(3, dtype=torch.float64)
        expect = sh_to_rgb(sh, 3, local_d, zero)
        assert torch.allclose(sh_to_rgb(world, 3, d, zero), expect, atol=1e-10)
        # Without the rotation the colours differ: the test can fail.
        assert not torch.allclose(sh_to_rgb(sh, 3, d, zero), expect, atol=1e-3)


def test_view_dependent_colour_turns_with_the_body():
    """Turning the posed body and the camera together leaves every Gaussian's colour unchanged, and the
    export (world-axis SH for standard readers) gives the same colours."""
    from rmavatar.render.project import sh_to_rgb

    v, f = sphere()
    gen = torch.Generator().manual_seed(6)
    av = Avatar(f, None, v, AvatarConfig(rectifier=False, sh_degree=3)).double()
    randomise(av, gen)
    av.active_sh_degree.fill_(3)
    v = v.double()
    view = torch.eye(4, dtype=torch.float64)
    view[:3, 3] = torch.tensor([0.2, 0.1, 3.0])
    g0 = av(v)
    c0 = g0.colors(view)
    Q = torch.eye(4, dtype=torch.float64)
    Q[:3, :3] = random_rotation(gen)
    g1 = av(v @ Q[:3, :3].T)
    assert torch.allclose(g1.colors(view @ Q.T), c0, atol=1e-9)  # camera turned with the body
    assert not torch.allclose(g1.colors(view), c0, atol=1e-3)  # a different view: other colours
    ex = av.world_gaussians(v @ Q[:3, :3].T)
    campos = -(view @ Q.T)[:3, :3].T @ (view @ Q.T)[:3, 3]
    assert torch.allclose(ex.colors(view @ Q.T), c0, atol=1e-9)
    assert torch.allclose(sh_to_rgb(ex.world_sh(), 3, ex.means, campos), c0, atol=1e-9)


def test_each_gaussian_follows_its_own_triangle_under_any_deformation():
    # Disconnected triangles, each moved by its own random similarity transform (an arbitrary
    # "pose"): every Gaussian must move exactly like its parent triangle.
    gen = torch.Generator().manual_seed(3)
    nf = 40
    v = torch.randn(nf * 3, 3, generator=gen, dtype=torch.float64)
    f = torch.arange(nf * 3).reshape(nf, 3)
    av = Avatar(f, None, v, AvatarConfig(rectifier=False, placement="area", num_gaussians=100)).double()
    randomise(av, gen)
    g0 = av(v)
    Q = torch.stack([random_rotation(gen) for _ in range(nf)])
    t = torch.randn(nf, 3, generator=gen, dtype=torch.float64)
    c = torch.rand(nf, generator=gen, dtype=torch.float64) + 0.5
    v1 = (c[:, None, None] * (v.reshape(nf, 3, 3) @ Q.transpose(-1, -2)) + t[:, None]).reshape(-1, 3)
    g1 = av(v1)
    fid = av.face_ids
    expect = c[fid, None] * (Q[fid] @ g0.means.unsqueeze(-1)).squeeze(-1) + t[fid]
    assert torch.allclose(g1.means, expect, atol=1e-10)
    assert torch.allclose(quat_to_rotmat(g1.quats), Q[fid] @ quat_to_rotmat(g0.quats), atol=1e-10)
    assert torch.allclose(g1.scales, c[fid, None] * g0.scales, rtol=1e-10)


def test_area_placement():
    v, f = sphere()
    counts = area_counts(torch.tensor([1.0, 1.0, 8.0, 0.0]), 14)
    assert counts.tolist() == [2, 2, 9, 1]
    with pytest.raises(UserError):
        area_counts(torch.ones(5), 4)
    av = Avatar(f, None, v, AvatarConfig(rectifier=False, placement="area", num_gaussians=500))
    assert av.num_gaussians == 500
    per_face = torch.bincount(av.face_ids, minlength=f.shape[0])
    assert per_face.min() >= 1
    # Positions lie inside their triangles: in the plane, barycentric coordinates in [0, 1].
    g = av(v)
    tri = v[f[av.face_ids]].double()
    p = g.means.double()
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    assert ((p - tri[:, 0]) * n).sum(-1).abs().max() < 1e-5 * n.norm(dim=-1).max()
    A = torch.stack((tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], n), -1)
    bc = torch.linalg.solve(A, (p - tri[:, 0]).unsqueeze(-1)).squeeze(-1)
    assert (bc[:, :2] >= -1e-5).all() and (bc[:, :2].sum(-1) <= 1 + 1e-5).all()
    # Bigger triangles got more Gaussians.
    tri_all = v[f]
    area = 0.5 * torch.linalg.cross(tri_all[:, 1] - tri_all[:, 0], tri_all[:, 2] - tri_all[:, 0], dim=-1).norm(dim=-1)
    order = torch.argsort(area)
    assert per_face[order[-10:]].float().mean() > per_face[order[:10]].float().mean()


def test_initial_colors_and_errors():
    v, f = sphere()
    cols = torch.rand(f.shape[0], 3)
    av = Avatar(f, None, v, AvatarConfig(rectifier=False), init_colors=cols)
    assert torch.allclose(0.5 + SH_C0 * av(v).sh[:, 0], cols, atol=1e-6)
    with pytest.raises(UserError):
        Avatar(f, None, v, init_colors=torch.rand(7, 3))
    with pytest.raises(UserError):
        Avatar(f, None, v, AvatarConfig(rectifier="paper", placement="area"))
    with pytest.raises(ValueError):
        av(v[:-1])
    av2 = Avatar(f, None, v, PAPER)
    with pytest.raises(ValueError):
        av2(v, None)
    with pytest.raises(ValueError):
        av2(v, torch.zeros(72))


# ---------------------------------------------------------------- rectifier
def test_positional_encoding_values():
    x = torch.tensor([[0.3, -1.2, 2.0]], dtype=torch.float64)
    g = positional_encoding(x, 6)
    assert g.shape == (1, 36)
    for k in range(6):
        for d in range(3):
            assert math.isclose(float(g[0, 3 * k + d]), math.sin(2**k * float(x[0, d])), abs_tol=1e-12)
            assert math.isclose(float(g[0, 18 + 3 * k + d]), math.cos(2**k * float(x[0, d])), abs_tol=1e-12)
    assert window_alpha(0, 10, 20, 6) == 0.0 and window_alpha(15, 10, 20, 6) == 3.0 and window_alpha(99, 10, 20, 6) == 6.0


def test_positional_encoding_gradient_matches_autograd_of_the_formula():
    # The written-out backward (and the host-made window) against autograd through sin/cos, float64, and
    # against the reference beside the fused Function.
    from rmavatar.avatar.rectifier import _Encoding, window_values

    gen = torch.Generator().manual_seed(3)
    x = torch.randn(50, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    grad = torch.randn(50, 36, generator=gen, dtype=torch.float64)
    r = Rectifier().double()
    for alpha in (6.0, 2.5, 0.0):
        window = torch.tensor(window_values(6, alpha), dtype=torch.float64)
        xb = (x.unsqueeze(-2) * (2.0 ** torch.arange(6.0, dtype=torch.float64)).unsqueeze(-1)).flatten(-2)
        wb = window.repeat_interleave(3)
        plain = torch.cat((torch.sin(xb) * wb, torch.cos(xb) * wb), -1)
        r.set_frequency_alpha(alpha)
        for ours in (positional_encoding(x, 6, window), r.encode(x)):
            torch.testing.assert_close(ours, plain, rtol=0, atol=1e-15)
            (a,), (b,) = torch.autograd.grad(ours, x, grad), torch.autograd.grad(plain, x, grad, retain_graph=True)
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
        columns = None if alpha == 6.0 else torch.cat((wb, wb))
        ref = _Encoding.reference(x, 6, columns)
        torch.testing.assert_close(ref, plain, rtol=0, atol=1e-15)
        (a,), (b,) = torch.autograd.grad(r.encode(x), x, grad), torch.autograd.grad(ref, x, grad)
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert window_values(6, 2.5) == pytest.approx([1, 1, 0.5, 0, 0, 0])
    half_open = torch.tensor(window_values(4, 2.5), dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda v: positional_encoding(v, 4, half_open), (x[:5].detach().requires_grad_(),))


def test_rectifier_shapes_and_fast_path_matches_plain_mlp():
    r = Rectifier().double()
    assert r.in_dim == 105
    widths = [(m.in_features, m.out_features) for m in (r.l1, r.l2, r.l3, r.l4, r.l5)]
    assert widths == [(105, 128), (128, 128), (164, 128), (128, 128), (128, 10)]
    assert not any(isinstance(m, torch.nn.Dropout) for m in r.modules())
    gen = torch.Generator().manual_seed(4)
    with torch.no_grad():
        r.l5.weight.normal_(0, 0.1, generator=gen)
    mu = torch.randn(300, 3, generator=gen, dtype=torch.float64)
    pose = torch.randn(69, generator=gen, dtype=torch.float64)
    for alpha in (6.0, 2.5):
        r.set_frequency_alpha(alpha)
        fast, ref = r(mu, pose), r.reference_forward(mu, pose)
        for a, b in zip(fast, ref):
            assert torch.allclose(a, b, atol=1e-12)
    assert [t.shape[-1] for t in fast] == [3, 3, 4]
    r.set_frequency_alpha(0.0)
    # A closed window removes the position: every Gaussian gets the same offsets.
    d_mu = r(mu, pose)[0]
    assert torch.allclose(d_mu, d_mu[:1].expand_as(d_mu), atol=1e-12)
    with pytest.raises(ValueError):
        r(mu, torch.zeros(72, dtype=torch.float64))


def test_fused_backward_matches_autograd_of_the_plain_mlp():
    gen = torch.Generator().manual_seed(8)
    r = Rectifier().double()
    with torch.no_grad():
        r.l5.weight.normal_(0, 0.1, generator=gen)
    r.set_frequency_alpha(4.3)
    mu = torch.randn(200, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    pose = torch.randn(69, generator=gen, dtype=torch.float64, requires_grad=True)
    wts = [torch.randn(200, k, generator=gen, dtype=torch.float64) for k in (3, 3, 4)]
    inputs = [mu, pose, *r.parameters()]
    fast = torch.autograd.grad(sum((o * w).sum() for o, w in zip(r(mu, pose), wts)), inputs)
    ref = torch.autograd.grad(sum((o * w).sum() for o, w in zip(r.reference_forward(mu, pose), wts)), inputs)
    for a, b in zip(fast, ref):
        assert torch.allclose(a, b, atol=1e-12)
    small_mu = mu[:2].detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda m, p: r(m, p), (small_mu, pose))


@pytest.mark.parametrize("grouped", [False, True])
def test_fused_mlp_matches_its_reference(grouped):
    """_FusedMLP against _FusedMLP.reference (nn.functional.linear on the concatenated inputs), float64:
    values and the gradients of every input (gamma, the pose rows, all weights and biases)."""
    from rmavatar.avatar.rectifier import _FusedMLP

    gen = torch.Generator().manual_seed(10)
    r = Rectifier().double()
    with torch.no_grad():
        r.l5.weight.normal_(0, 0.1, generator=gen)
    n, u = 120, (4 if grouped else 1)
    gamma = torch.randn(n, 36, generator=gen, dtype=torch.float64, requires_grad=True)
    pose = torch.randn(u, 69, generator=gen, dtype=torch.float64, requires_grad=True)
    group = torch.randint(0, u, (n,), generator=gen) if grouped else None
    weights = list(r._weights())
    inputs = [gamma, pose, *weights]
    fast = _FusedMLP.apply(gamma, pose, group, *weights, torch.float64)
    ref = _FusedMLP.reference(gamma, pose, group, *weights)
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    upstream = torch.randn(n, 10, generator=gen, dtype=torch.float64)
    for a, b in zip(torch.autograd.grad(fast, inputs, upstream), torch.autograd.grad(ref, inputs, upstream)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_auto_precision_is_bfloat16_where_the_cpu_multiplies_it_and_float32_elsewhere():
    from rmavatar.avatar.rectifier import cpu_multiplies_bf16

    gen = torch.Generator().manual_seed(8)
    mu, pose = torch.randn(300, 3, generator=gen), torch.randn(69, generator=gen) * 0.3
    nets = {p: Rectifier(precision=p) for p in ("auto", "float32", "bfloat16")}
    for net in nets.values():
        net.load_state_dict(nets["float32"].state_dict())
        with torch.no_grad():
            net.l5.weight.copy_(torch.linspace(-0.05, 0.05, net.l5.weight.numel()).view_as(net.l5.weight))
    auto = nets["auto"]
    chosen = "bfloat16" if cpu_multiplies_bf16() else "float32"
    assert auto.compute_dtype(mu) == getattr(torch, chosen) and auto.compute_dtype(mu.double()) == torch.float64
    assert nets["float32"].compute_dtype(mu) == torch.float32 and nets["bfloat16"].compute_dtype(mu) == torch.bfloat16
    got, want = torch.cat(auto(mu, pose), -1), torch.cat(nets[chosen](mu, pose), -1)
    assert got.dtype == torch.float32 and torch.equal(got, want)
    assert AvatarConfig().rectifier_precision == "auto"
    with pytest.raises(UserError, match="rectifier_precision"):
        AvatarConfig(rectifier_precision="float16")


def test_bfloat16_rectifier_is_close_to_float32():
    gen = torch.Generator().manual_seed(9)
    r32 = Rectifier()
    with torch.no_grad():
        r32.l5.weight.normal_(0, 0.05, generator=gen)
    r16 = Rectifier(precision="bfloat16")
    r16.load_state_dict(r32.state_dict())
    mu = torch.randn(2000, 3, generator=gen) * 0.5
    pose = torch.randn(69, generator=gen) * 0.3
    a, b = torch.cat(r32(mu, pose), -1), torch.cat(r16(mu, pose), -1)
    assert b.dtype == torch.float32
    assert (a - b).abs().max() < 0.03 * a.abs().max()
    ga = torch.autograd.grad(a.square().sum(), list(r32.parameters()))
    gb = torch.autograd.grad(b.square().sum(), list(r16.parameters()))
    for x, y in zip(ga, gb):
        assert y.dtype == torch.float32
        assert torch.linalg.vector_norm(x - y) < 0.05 * torch.linalg.vector_norm(x)
    with pytest.raises(ValueError):
        Rectifier(precision="float16")


def test_rectifier_starts_as_identity_and_is_deterministic():
    v, f = sphere()
    gen = torch.Generator().manual_seed(5)
    torch.manual_seed(0)
    av = Avatar(f, None, v, PAPER)
    randomise(av, gen)
    pose = torch.randn(69, generator=gen) * 0.5
    g, extras = av.forward_with_extras(v, pose)
    mu, r, s = av.posed(v)
    assert torch.allclose(g.means, mu, atol=1e-3 * 0.3)
    assert torch.allclose(g.scales, s.clamp_min(1e-6), atol=1e-3 * 0.3)
    assert torch.allclose(quat_to_rotmat(g.quats), quat_to_rotmat(r), atol=1e-3)
    assert all(o.abs().max() < 1e-3 for o in extras.offsets)
    av.eval()
    with torch.no_grad():
        a, b = av(v, pose), av(v, pose)
    assert torch.equal(a.means, b.means) and torch.equal(a.quats, b.quats) and torch.equal(a.scales, b.scales)
    w = av.world_gaussians(v, pose)
    assert torch.equal(w.means, a.means) and not w.means.requires_grad
    assert w.sh.shape == (f.shape[0], 16, 3) and w.sh_degree == 3


def test_rectified_attributes_follow_the_paper():
    v, f = sphere()
    gen = torch.Generator().manual_seed(6)
    av = Avatar(f, None, v, PAPER).double()
    randomise(av, gen)
    with torch.no_grad():
        av.rectifier.l5.weight.normal_(0, 0.05, generator=gen)
        av.rectifier.l5.bias.normal_(0, 0.05, generator=gen)
    v = v.double()
    pose = torch.randn(69, generator=gen, dtype=torch.float64)
    g = av(v, pose)
    mu, r, s = av.posed(v)
    d_mu, d_s, d_r = av.rectifier.reference_forward(mu, pose)
    assert torch.allclose(g.means, mu + d_mu, atol=1e-12)
    assert torch.allclose(g.scales, (s + d_s).clamp_min(1e-6), atol=1e-12)
    dq = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64) + d_r
    assert torch.allclose(quat_to_rotmat(g.quats), quat_to_rotmat(r) @ quat_to_rotmat(dq), atol=1e-12)


@pytest.mark.parametrize("device", DEVICES)
def test_gradients_reach_every_parameter(device):
    v, f = sphere()
    gen = torch.Generator().manual_seed(7)
    av = Avatar(f, None, v, PAPER)
    randomise(av, gen)
    av.to(device)
    av.active_sh_degree.fill_(3)
    g, extras = av.forward_with_extras(v.to(device), torch.randn(69, generator=gen).to(device))
    loss = (g.means.square().sum() + g.quats.sum() + g.scales.sum() + g.opacities.sum() + g.sh.square().sum())
    loss = loss + sum(o.square().sum() for o in extras.offsets)
    loss.backward()
    for name, p in av.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, name


def test_sh_degree_grows():
    v, f = sphere()
    av = Avatar(f, None, v, AvatarConfig(rectifier=False, sh_degree=2))
    assert av(v).sh.shape[1] == 1
    av.set_progress(2, 100)  # one band every sh_every_frac (2%) of the run
    assert av(v).sh.shape[1] == 4 and av(v).sh_degree == 1
    av.set_progress(100, 100)
    assert av(v).sh.shape[1] == 9 and av(v).sh_degree == 2


def test_state_dict_round_trip_with_a_different_count():
    v, f = sphere()
    a = Avatar(f, None, v, AvatarConfig(rectifier="paper", placement="area", num_gaussians=333))
    a.set_frequency_alpha(2.0)
    b = Avatar(f, None, v, PAPER)
    b.load_state_dict(a.state_dict())
    assert b.num_gaussians == 333 and float(b.rectifier.freq_alpha) == 2.0
    pose = torch.randn(69)
    assert torch.equal(a(v, pose).means, b(v, pose).means)


class _Body:
    def __init__(self, v, f):
        self.v_template, self.faces, self.binding_faces = v, f, torch.arange(f.shape[0] - 3)


def test_checkpoint_state_round_trip_and_body_check():
    v, f = sphere()
    body = _Body(v, f)
    a = AvatarConfig(rectifier="paper", placement="area", num_gaussians=200, sh_degree=2).build(body)
    assert a.num_gaussians == 200 and int(a.face_ids.max()) < f.shape[0] - 3
    a.set_progress(700, 1000)
    state = a.checkpoint_state()
    b = Avatar.from_state(body, state)
    assert b.config == a.config and b.num_gaussians == 200
    pose = torch.randn(69)
    ga, gb = a(v, pose), b(v, pose)
    assert torch.equal(ga.means, gb.means) and torch.equal(ga.sh, gb.sh)
    other = _Body(*sphere())
    other.faces = torch.flip(other.faces, dims=[1])
    with pytest.raises(UserError, match="different body mesh"):
        Avatar.from_state(other, state)
    with pytest.raises(UserError):
        Avatar.from_state(body, {"weights": 1})


def test_set_progress_schedules():
    v, f = sphere()
    a = Avatar(f, None, v, AvatarConfig(rectifier="paper", sh_degree=3, c2f_start=0.1, c2f_end=0.5))
    a.set_progress(0, 1000)
    assert int(a.active_sh_degree) == 0 and float(a.rectifier.freq_alpha) == 0.0
    a.set_progress(300, 1000)  # SH every 20 iterations; window half open
    assert int(a.active_sh_degree) == 3 and float(a.rectifier.freq_alpha) == pytest.approx(3.0)
    a.set_progress(10, 1000)
    assert int(a.active_sh_degree) == 0
    a.set_progress(1000, 1000)
    assert float(a.rectifier.freq_alpha) == 6.0
    b = Avatar(f, None, v, AvatarConfig(rectifier="paper", coarse_to_fine=False))
    b.set_progress(0, 1000)
    assert float(b.rectifier.freq_alpha) == 6.0


# ---------------------------------------------------------------- the batched forms against the plain formulas
# The library builds frames, Shepperd's quaternion and Hamilton products with few, large tensor
# operations (a training step's launch count); these are the element-by-element formulas they replace.
def _frames_plain(vertices, faces):
    v0, v1, v2 = vertices[..., faces, :].unbind(-2)
    e1, e2 = v1 - v0, v2 - v0
    unit = lambda x: x / torch.linalg.vector_norm(x, dim=-1, keepdim=True).clamp_min(1e-12)  # noqa: E731
    a0 = unit(e1)
    a1 = unit(torch.linalg.cross(a0, e2, dim=-1))
    a2 = torch.linalg.cross(a0, a1, dim=-1)
    w = 0.5 * (torch.linalg.vector_norm(e1, dim=-1) + (a2 * e2).sum(-1).abs())
    return torch.stack((a0, a1, a2), dim=-1), w, (v0 + v1 + v2) / 3.0


def _quat_multiply_plain(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw), dim=-1)


def _rotmat_to_quat_plain(R):
    m = [[R[..., i, j] for j in range(3)] for i in range(3)]
    t = torch.stack((1 + m[0][0] + m[1][1] + m[2][2], 1 + m[0][0] - m[1][1] - m[2][2],
                     1 - m[0][0] + m[1][1] - m[2][2], 1 - m[0][0] - m[1][1] + m[2][2]), dim=-1)
    a, b, c = m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]
    d, e, f = m[1][0] + m[0][1], m[0][2] + m[2][0], m[2][1] + m[1][2]
    cand = torch.stack((torch.stack((t[..., 0], a, b, c), -1), torch.stack((a, t[..., 1], d, e), -1),
                        torch.stack((b, d, t[..., 2], f), -1), torch.stack((c, e, f, t[..., 3]), -1)), dim=-2)
    cand = cand / (2.0 * t.clamp_min(1e-8).sqrt()).unsqueeze(-1)
    best = t.argmax(-1, keepdim=True)
    q = torch.gather(cand, -2, best.unsqueeze(-1).expand(best.shape + (4,))).squeeze(-2)
    q = torch.where(q[..., :1] < 0, -q, q)
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)


def _assert_same_values_and_gradients(fa, fb, inputs, gen, rtol=1e-10):
    a, b = fa(*inputs), fb(*inputs)
    a, b = (a,) if torch.is_tensor(a) else a, (b,) if torch.is_tensor(b) else b
    grads_out = [torch.randn(x.shape, generator=gen, dtype=x.dtype) for x in a]
    for x, y in zip(a, b):
        assert torch.allclose(x, y, rtol=rtol, atol=rtol * float(x.detach().abs().max()))
    ga = torch.autograd.grad(sum((x * g).sum() for x, g in zip(a, grads_out)), inputs)
    gb = torch.autograd.grad(sum((y * g).sum() for y, g in zip(b, grads_out)), inputs)
    for x, y in zip(ga, gb):
        assert torch.allclose(x, y, rtol=rtol, atol=rtol * float(x.detach().abs().max()))


def test_frames_match_the_plain_formulas():
    gen = torch.Generator().manual_seed(11)
    v, f = sphere()
    v = (v.double() + 0.01 * torch.randn(v.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    vb = torch.stack((v.detach(), 1.3 * v.detach())).requires_grad_(True)
    for x in (v, vb):
        _assert_same_values_and_gradients(lambda x: _frames_plain(x, f), lambda x: triangle_frames(x, f), (x,), gen)


def test_rotmat_to_quat_matches_the_plain_formula():
    gen = torch.Generator().manual_seed(12)
    q = torch.randn(400, 4, generator=gen, dtype=torch.float64)
    q[:40, 0] = 1e-9  # near 180 degrees: another row of K is picked
    q[40:80, 1:3] = 0.0
    R = quat_to_rotmat(q)
    # Off SO(3) too (frames of float32 meshes are rotations only to rounding), and with every row picked.
    R = torch.cat((R, R + 0.05 * torch.randn(R.shape, generator=gen, dtype=torch.float64))).requires_grad_(True)
    _assert_same_values_and_gradients(_rotmat_to_quat_plain, rotmat_to_quat, (R,), gen)
    K_best = _rotmat_to_quat_plain(R).abs().argmax(-1)
    assert set(K_best.tolist()) == {0, 1, 2, 3}


def test_quat_multiply_matches_the_hamilton_formula():
    gen = torch.Generator().manual_seed(13)
    a = torch.randn(300, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    b = torch.randn(300, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    _assert_same_values_and_gradients(_quat_multiply_plain, quat_multiply, (a, b), gen)


def test_posed_matches_the_plain_embedding():
    gen = torch.Generator().manual_seed(14)
    v, f = sphere()
    av = Avatar(f, None, v, AvatarConfig(rectifier=False, placement="area", num_gaussians=3 * f.shape[0])).double()
    randomise(av, gen)
    v = (v.double() + 0.02 * torch.randn(v.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)

    def plain(vertices, means, quats, log_scales):
        R, w, M = _frames_plain(vertices, av.faces[av.face_ids])
        mu = w.unsqueeze(-1) * (R @ means.unsqueeze(-1)).squeeze(-1) + M
        r = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True).clamp_min(1e-12)
        return mu, _quat_multiply_plain(_rotmat_to_quat_plain(R), r), w.unsqueeze(-1) * torch.exp(log_scales)

    def library(vertices, *params):  # the avatar's own parameters are the inputs
        return av.posed(vertices)

    _assert_same_values_and_gradients(plain, library, (v, av.means, av.quats, av.log_scales), gen)


def test_unit_rows_value_and_gradient_match_autograd():
    # The written-out backward of v / max(|v|, eps) against autograd (float64), with a zero row and a
    # row shorter than eps (divided by the constant eps: only the first term of the Jacobian).
    from rmavatar.avatar.geometry import unit_rows

    gen = torch.Generator().manual_seed(0)
    v = torch.randn(20, 4, generator=gen, dtype=torch.float64)
    v[0], v[1] = 0.0, 1e-13
    v.requires_grad_(True)
    w = v.detach().clone().requires_grad_(True)
    grad = torch.randn(20, 4, generator=gen, dtype=torch.float64)
    from rmavatar.avatar.geometry import _UnitRows

    ours = unit_rows(v, 1e-12)
    plain = w / torch.linalg.vector_norm(w, dim=-1, keepdim=True).clamp_min(1e-12)
    assert torch.equal(ours, plain)
    (ours * grad).sum().backward()
    (plain * grad).sum().backward()
    torch.testing.assert_close(v.grad, w.grad, rtol=1e-12, atol=1e-12)
    x = v.detach().clone().requires_grad_(True)
    ref = _UnitRows.reference(x, 1e-12)  # the reference beside the fused Function
    assert torch.equal(ref, plain)
    (ref * grad).sum().backward()
    torch.testing.assert_close(v.grad, x.grad, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(lambda x: unit_rows(x, 1e-12), (v[2:].detach().clone().requires_grad_(True),))



def test_face_table_columns_are_named_by_face_table():
    """Avatar.face_table's columns, read through FaceTable's slices, are the frames they name."""
    from rmavatar.avatar.geometry import FaceTable, quat_left_matrix
    from rmavatar.avatar.model import FACE_TABLE

    gen = torch.Generator().manual_seed(15)
    v, f = sphere()
    v = v.double() + 0.01 * torch.randn(v.shape, generator=gen, dtype=torch.float64)
    av = Avatar(f, None, v.float(), AvatarConfig(rectifier=False)).double()
    table = av.face_table(v)
    assert FACE_TABLE == FaceTable.WIDTH == table.shape[-1] == 38
    names = (FaceTable.R, FaceTable.wR, FaceTable.M, FaceTable.w, FaceTable.L)
    assert [c.start for c in names] == [0, 9, 18, 21, 22] and names[-1].stop == FaceTable.WIDTH
    assert all(a.stop == b.start for a, b in zip(names, names[1:]))  # in order, no gaps
    R, w, M = triangle_frames(v, f)
    assert torch.equal(table[:, FaceTable.R].reshape(-1, 3, 3), R)
    torch.testing.assert_close(table[:, FaceTable.wR].reshape(-1, 3, 3), w[:, None, None] * R, rtol=0, atol=0)
    assert torch.equal(table[:, FaceTable.M], M) and torch.equal(table[:, FaceTable.w], w.unsqueeze(-1))
    assert torch.equal(table[:, FaceTable.L].reshape(-1, 4, 4), quat_left_matrix(rotmat_to_quat(R)))


def test_encoding_window_is_read_from_the_alpha_buffer_on_the_device():
    # The window is computed from the freq_alpha buffer at each forward (a captured CUDA graph replays
    # it), so filling the buffer in place changes it; it equals the host formula at any alpha.
    from rmavatar.avatar.rectifier import window_values

    r = Rectifier()
    x = torch.randn(7, 3, generator=torch.Generator().manual_seed(1))
    for alpha in (0.3, 1.7, 4.99):
        r.freq_alpha.fill_(alpha)
        want = torch.tensor(window_values(6, alpha), dtype=torch.float32).repeat_interleave(3).repeat(2)
        torch.testing.assert_close(r._band_weights(x), want, rtol=0, atol=1e-6)


def _rotated_meshes(gen, dtype):
    """A jittered sphere turned by rotations that pick every row of Shepperd's K, with a degenerate
    triangle (two corners equal) and a zero-area one (three corners on a line)."""
    v, f = sphere()
    q = torch.randn(4, 4, generator=gen, dtype=torch.float64)
    q[0, 0], q[1, 1:] = 1e-9, 0.0  # near 180 degrees; the identity's direction
    meshes = []
    for R in quat_to_rotmat(q):
        x = v.double() @ R.T + 0.01 * torch.randn(v.shape, generator=gen, dtype=torch.float64)
        x[f[0, 1]] = x[f[0, 0]]
        x[f[1, 2]] = 0.5 * (x[f[1, 0]] + x[f[1, 1]])
        meshes.append(x.to(dtype))
    return meshes, f


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_cpu_face_table_kernels_match_the_torch_formulas(dtype):
    """The numba face table (one mesh on the CPU with gradients: pose fits and refining steps) against
    FaceTable.rows(*triangle_frames(...)), values and gradients."""
    from rmavatar.avatar.geometry import FaceTable, face_table

    gen = torch.Generator().manual_seed(21)
    meshes, f = _rotated_meshes(gen, dtype)
    rows = set()
    tol = 1e-11 if dtype == torch.float64 else 2e-5
    for x in meshes:
        x = x.requires_grad_(True)
        kernel = face_table(x, f)
        assert kernel.grad_fn is not None and "FaceTableCPU" in type(kernel.grad_fn).__name__
        plain = FaceTable.rows(*triangle_frames(x, f))
        # the degenerate faces' frames (those two and their neighbours across the zero edge) are
        # rounding noise: finite, and differently so in each
        tri = x.detach()[f]
        area = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1).norm(dim=-1)
        degenerate = area < 1e-6
        assert 2 <= int(degenerate.sum()) <= 4
        torch.testing.assert_close(kernel[~degenerate], plain[~degenerate], rtol=tol, atol=tol)
        g = torch.randn(plain.shape, generator=gen, dtype=dtype)
        (gk,) = torch.autograd.grad((kernel * g).sum(), x, retain_graph=True)
        assert torch.isfinite(kernel).all() and torch.isfinite(gk).all()
        g[degenerate] = 0.0
        (gk,) = torch.autograd.grad((kernel * g).sum(), x)
        (gp,) = torch.autograd.grad((plain * g).sum(), x)
        torch.testing.assert_close(gk, gp, rtol=tol, atol=tol * float(gp.abs().max()))
        with torch.no_grad():
            R = plain[:, FaceTable.R].reshape(-1, 3, 3)
            K = torch.addmm(torch.tensor(_SHEPPERD_DIAG_ONES, dtype=dtype), R.reshape(-1, 9),
                            torch.tensor(_shepperd_diag(), dtype=dtype))
            rows |= set(K.argmax(-1).tolist())
    assert rows == {0, 1, 2, 3}  # every row of K was picked somewhere
    # without gradients, batched, or on another device: the torch formulas themselves
    x = meshes[0].detach()
    assert torch.equal(face_table(x, f), FaceTable.rows(*triangle_frames(x, f)))
    batch = torch.stack((x, x)).requires_grad_(True)
    assert "FaceTableCPU" not in type(face_table(batch, f).grad_fn).__name__


_SHEPPERD_DIAG_ONES = (1.0, 1.0, 1.0, 1.0)


def _shepperd_diag():
    """[9,4]: R flattened @ this + 1 = K's diagonal (4 w^2, 4 x^2, 4 y^2, 4 z^2)."""
    signs = ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))
    table = [[0.0] * 4 for _ in range(9)]
    for k, s in enumerate(signs):
        for d in range(3):
            table[4 * d][k] = float(s[d])
    return table


class _Triangulated:
    """``body`` with another triangulation ``faces`` (what the checks and ``from_state`` read of a body)."""

    def __init__(self, body, faces):
        self.spec, self.v_template, self.binding_faces, self.offsets = body.spec, body.v_template, body.binding_faces, None
        self.faces = faces


def _resplit(faces, rows):
    """``faces`` with the quads whose first triangle is row ``rows[k]`` split along their other diagonal."""
    out = faces.clone()
    for i in rows:
        (a, b, c), (c2, d, a2) = faces[i].tolist(), faces[i + 1].tolist()
        assert (c2, a2) == (c, a), "not a quad split [a,b,c], [c,d,a]"
        out[i], out[i + 1] = torch.tensor([a, b, d]), torch.tensor([d, b, c])
    return out


def test_an_avatar_loads_on_a_body_that_splits_some_quads_the_other_way():
    """Anny splits each quad along its shorter diagonal in floating point; on its eyes' grid the two are
    equal but for the last bit, and machines that round otherwise split a few quads the other way. A run
    trained on one machine loads on another, its avatar on the triangulation it was trained on."""
    from rmavatar.avatar.run import body_signature, check_body

    body = load_body_model("anny")
    f = body.faces
    # quads split [a,b,c], [c,d,a] among the binding faces (the Gaussians sit on them)
    quads = [int(i) for i in body.binding_faces[:-1]
             if bool((f[i, [0, 2]] == f[i + 1, [2, 0]]).all()) and int(f[i, 1]) != int(f[i + 1, 1])][:40:8]
    assert len(quads) == 5
    moved = _resplit(f, quads)
    other = _Triangulated(body, moved)
    assert same_quads(f, moved) and same_quads(moved, f) and same_quads(f, f)
    flipped = moved.clone()
    flipped[quads[0] : quads[0] + 2] = flipped[quads[0] : quads[0] + 2].flip(1)  # the quad turned inside out
    assert not same_quads(f, flipped)
    torn = moved.clone()
    torn[quads[0] + 1, 1] = int(f[quads[0] + 1, 1]) + 1  # another vertex: another quad
    assert not same_quads(f, torn)
    a = AvatarConfig(rectifier="paper").build(body)
    randomise(a, torch.Generator().manual_seed(3))
    state = a.checkpoint_state()
    b = Avatar.from_state(other, state)
    assert torch.equal(b.faces, f) and torch.equal(b.rest_frames, a.rest_frames)
    pose = torch.randn(69, generator=torch.Generator().manual_seed(4)) * 0.2
    ga, gb = a(body.v_template, pose), b(body.v_template, pose)
    assert torch.equal(ga.means, gb.means) and torch.equal(ga.quats, gb.quats) and torch.equal(ga.scales, gb.scales)
    saved = body_signature(body)
    check_body(saved, other, "ckpt", faces=f)
    with pytest.raises(UserError, match="incompatible"):
        check_body(saved, other, "ckpt")  # without the avatar's triangulation: a different mesh
    with pytest.raises(UserError, match="different body mesh"):
        Avatar.from_state(_Triangulated(body, flipped), state)
