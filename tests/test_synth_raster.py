"""The synthetic subject's mesh rasterizer, checked against analytic geometry computed independently
(float64 numpy point-in-triangle tests, ray-plane intersections, exact areas)."""

import numpy as np
import pytest

from rmavatar.data.synth.raster import interpolate, rasterize, resolve

K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]])


def _project(V, K):
    return V[:, :2] / V[:, 2:] * np.diag(K)[:2] + K[:2, 2]


def _samples(width, height, ss):
    """Sample positions in pixel coordinates: pixel j's samples at j + (k + 0.5) / ss."""
    c = (np.arange(width * ss) + 0.5) / ss
    r = (np.arange(height * ss) + 0.5) / ss
    return np.meshgrid(c, r)


def _inside(px, py, tri):
    """Independent point-in-triangle test (float64), plus the distance to the closest edge line."""
    a, b, c = tri
    sgn = np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
    ins = np.ones(px.shape, bool)
    dist = np.full(px.shape, np.inf)
    for p, q in ((a, b), (b, c), (c, a)):
        e = ((q[0] - p[0]) * (py - p[1]) - (q[1] - p[1]) * (px - p[0])) * sgn
        ins &= e >= 0
        dist = np.minimum(dist, np.abs(e) / np.hypot(q[0] - p[0], q[1] - p[1]))
    return ins, dist


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_single_triangle_coverage_matches_geometry(seed):
    rng = np.random.default_rng(seed)
    V = np.column_stack([rng.uniform(-0.6, 0.6, (3, 2)), rng.uniform(1.5, 3.0, 3)])
    ss = 4
    fr = rasterize(V, np.array([[0, 1, 2]]), K, 64, 64, ss=ss)
    tri = _project(V, K)
    px, py = _samples(64, 64, ss)
    ins, dist = _inside(px, py, tri)
    clear = dist > 1e-6  # samples on an edge may go either way
    assert np.array_equal(fr.covered[clear], ins[clear])
    # Coverage (the soft mask) integrates to the triangle's area up to the sampling error.
    area = 0.5 * abs(np.cross(np.r_[tri[1] - tri[0], 0], np.r_[tri[2] - tri[0], 0])[2])
    perimeter = sum(np.linalg.norm(tri[i] - tri[(i + 1) % 3]) for i in range(3))
    cov = resolve(fr.covered.astype(np.float64), ss)
    assert abs(cov.sum() - area) <= 0.5 * perimeter / ss + 1.0
    assert cov.min() >= 0 and cov.max() <= 1


def test_nearer_triangle_wins_in_either_order():
    near = [[-0.5, -0.5, 2.0], [0.5, -0.5, 2.0], [0.0, 0.5, 2.0]]
    far = [[-0.5, 0.5, 3.0], [0.5, 0.5, 3.0], [0.0, -0.6, 3.0]]
    for order in (0, 1):
        V = np.array(near + far if order == 0 else far + near)
        F = np.array([[0, 1, 2], [3, 4, 5]])
        near_face = 0 if order == 0 else 1
        fr = rasterize(V, F, K, 64, 64, ss=1)
        px, py = _samples(64, 64, 1)
        in_near, d1 = _inside(px, py, _project(V[F[near_face]], K))
        in_far, d2 = _inside(px, py, _project(V[F[1 - near_face]], K))
        clear = (d1 > 1e-6) & (d2 > 1e-6)
        both = in_near & in_far & clear
        assert both.sum() > 100
        assert np.all(fr.face_id[both] == near_face)
        assert np.allclose(fr.depth[both], 2.0, atol=1e-5)
        only_far = in_far & ~in_near & clear
        assert np.all(fr.face_id[only_far] == 1 - near_face)
        assert np.allclose(fr.depth[only_far], 3.0, atol=1e-5)


def test_tilted_quad_uv_is_perspective_correct():
    # A quad receding in depth (z from 1.5 to 4): screen-linear interpolation would be far off.
    P = np.array([[-0.6, -0.5, 1.5], [0.6, -0.5, 1.5], [0.6, 0.5, 4.0], [-0.6, 0.5, 4.0]])
    UV = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    ss = 2
    fr = rasterize(P, F, K, 64, 64, ss=ss)
    uv = interpolate(fr, F, UV)
    # Analytic: intersect each sample's ray with the quad's plane, express the hit in the quad's axes.
    px, py = _samples(64, 64, ss)
    rays = np.stack([(px - K[0, 2]) / K[0, 0], (py - K[1, 2]) / K[1, 1], np.ones_like(px)], -1)
    o, eu, ev = P[0], P[1] - P[0], P[3] - P[0]
    n = np.cross(eu, ev)
    t = (o @ n) / (rays @ n)
    hit = rays * t[..., None] - o
    u = hit @ eu / (eu @ eu)
    v = hit @ ev / (ev @ ev)
    m = fr.covered
    assert m.sum() > 1000
    assert np.abs(uv[m, 0] - u[m]).max() < 1e-4
    assert np.abs(uv[m, 1] - v[m]).max() < 1e-4
    # A checkerboard looked up through the interpolated UV matches the analytic one.
    checker = lambda a, b: ((np.floor(a * 8) + np.floor(b * 8)) % 2).astype(int)  # noqa: E731
    interior = m & (u > 0.01) & (u < 0.99) & (v > 0.01) & (v < 0.99)
    agree = checker(uv[..., 0], uv[..., 1])[interior] == checker(u, v)[interior]
    assert agree.mean() > 0.995  # only samples within 1e-4 of a checker edge may differ
    # and it is really perspective: the screen-linear guess differs a lot
    assert np.abs(u[m] - 0.5).max() > 0.4


def test_shared_edge_is_watertight_and_never_doubled():
    # A square split along its diagonal, with the diagonal passing exactly through sample points.
    P = np.array([[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]])
    Kc = np.array([[80.0, 0.0, 32.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])  # corners land on x.5
    a = rasterize(P, np.array([[0, 1, 2]]), Kc, 64, 64, ss=1).covered
    b = rasterize(P, np.array([[0, 2, 3]]), Kc, 64, 64, ss=1).covered
    assert not np.any(a & b)
    both = rasterize(P, np.array([[0, 1, 2], [0, 2, 3]]), Kc, 64, 64, ss=1).covered
    assert np.array_equal(both, a | b)
    q = _project(P, Kc)  # the square spans [16, 48] in pixel coordinates
    px, py = _samples(64, 64, 1)
    strictly_inside = (px > q[:, 0].min()) & (px < q[:, 0].max()) & (py > q[:, 1].min()) & (py < q[:, 1].max())
    assert np.all(both[strictly_inside])


def test_pixel_centres_are_at_half_integers():
    # A small triangle around the image point (10.5, 20.5) covers exactly pixel column 10, row 20.
    cx, cy, z = 10.5, 20.5, 2.0
    pts = np.array([[cx - 0.3, cy - 0.3], [cx + 0.3, cy - 0.3], [cx, cy + 0.3]])
    V = np.column_stack([(pts[:, 0] - K[0, 2]) / K[0, 0] * z, (pts[:, 1] - K[1, 2]) / K[1, 1] * z, np.full(3, z)])
    fr = rasterize(V, np.array([[0, 1, 2]]), K, 64, 64, ss=1)
    assert list(zip(*np.nonzero(fr.covered))) == [(20, 10)]


def test_behind_camera_and_degenerate_triangles_are_skipped():
    V = np.array([[0, 0, -1.0], [1, 0, 2.0], [0, 1, 2.0], [0, 0, 2.0], [0.1, 0.1, 2.0], [0.2, 0.2, 2.0]])
    fr = rasterize(V, np.array([[0, 1, 2], [3, 4, 5]]), K, 32, 32, ss=2)
    assert not fr.covered.any()
