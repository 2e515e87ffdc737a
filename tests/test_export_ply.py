"""The 3DGS PLY writer/reader on plain Gaussians: file layout checked with an independent reader
(plyfile), values against the 3DGS definitions, the y-up / y-down world conventions, and render round
trips."""

import os

import numpy as np
import pytest
import torch

from rmavatar.export.ply import ply_property_names, ply_up, read_ply, write_ply
from rmavatar.render.project import quat_to_rotmat, sh_basis
from rmavatar.utils import UserError

plyfile = pytest.importorskip("plyfile")


def random_gaussians(n=200, degree=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    K = (degree + 1) ** 2
    return dict(
        means=torch.randn(n, 3, generator=g) * 0.3,
        quats=torch.randn(n, 4, generator=g) * 2.0,  # not normalised on purpose
        scales=torch.rand(n, 3, generator=g) * 0.05 + 0.005,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh=torch.randn(n, K, 3, generator=g) * 0.5,
    )


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_plyfile_reads_standard_layout(tmp_path, degree):
    gs = random_gaussians(degree=degree)
    path = write_ply(tmp_path / "a.ply", **gs, up="y")  # y up: the values are the Gaussians' own
    ply = plyfile.PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    assert "rmavatar up y" in ply.comments
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    K = (degree + 1) ** 2
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(3 * (K - 1))]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert [p.name for p in v.properties] == expected == ply_property_names(K)
    assert all(p.val_dtype in ("f4", "float32") for p in v.properties)
    assert v.count == 200

    col = lambda name: np.asarray(v[name], np.float64)  # noqa: E731
    np.testing.assert_allclose(np.stack([col("x"), col("y"), col("z")], 1), gs["means"].numpy(), atol=1e-7)
    np.testing.assert_array_equal(np.stack([col("nx"), col("ny"), col("nz")], 1), 0.0)
    # opacity is a logit: sigmoid(opacity) gives it back
    np.testing.assert_allclose(1 / (1 + np.exp(-col("opacity"))), gs["opacities"].numpy(), rtol=1e-5)
    # scales are natural logs of the world scales
    np.testing.assert_allclose(np.exp(np.stack([col(f"scale_{i}") for i in range(3)], 1)),
                               gs["scales"].numpy(), rtol=1e-5)
    # rotations are normalised wxyz
    q = np.stack([col(f"rot_{i}") for i in range(4)], 1)
    q_ref = gs["quats"].double().numpy()
    q_ref /= np.linalg.norm(q_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(q, q_ref, atol=1e-6)
    # f_dc is SH band 0; f_rest is channel-major: red's K-1 coefficients, then green's, then blue's
    sh = gs["sh"].numpy()
    np.testing.assert_allclose(np.stack([col(f"f_dc_{c}") for c in range(3)], 1), sh[:, 0], atol=1e-7)
    for c in range(3):
        for k in range(1, K):
            np.testing.assert_allclose(col(f"f_rest_{c * (K - 1) + (k - 1)}"), sh[:, k, c], atol=1e-7)


def test_read_ply_round_trip(tmp_path):
    gs = random_gaussians(degree=2, seed=3)
    back = read_ply(write_ply(tmp_path / "b.ply", **gs))
    assert back.sh_degree == 2
    q = gs["quats"] / gs["quats"].norm(dim=1, keepdim=True)
    for name, ref in (("means", gs["means"]), ("quats", q), ("scales", gs["scales"]),
                      ("opacities", gs["opacities"]), ("sh", gs["sh"])):
        torch.testing.assert_close(getattr(back, name), ref, rtol=1e-5, atol=1e-6, msg=name)


# 180 degrees about x: y up <-> y down (the 3DGS / COLMAP convention of the default file)
TURN = torch.diag(torch.tensor([1.0, -1.0, -1.0]))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_default_file_is_turned_to_y_down(tmp_path, degree):
    """The default file holds the Gaussians turned 180 degrees about x: positions, rotations and the
    view-dependent colour all turned (checked from plyfile's values, not our reader)."""
    gs = random_gaussians(n=100, degree=degree, seed=11)
    path = write_ply(tmp_path / "down.ply", **gs)
    ply = plyfile.PlyData.read(str(path))
    assert "rmavatar up -y" in ply.comments and ply_up(path) == "-y"
    v = ply["vertex"]
    col = lambda name: torch.tensor(np.asarray(v[name]), dtype=torch.float64)  # noqa: E731
    means = torch.stack([col("x"), col("y"), col("z")], 1)
    torch.testing.assert_close(means, gs["means"].double() @ TURN.double().T, atol=1e-7, rtol=0)
    rot = quat_to_rotmat(torch.stack([col(f"rot_{i}") for i in range(4)], 1))
    torch.testing.assert_close(rot, TURN.double() @ quat_to_rotmat(gs["quats"].double()), atol=1e-6, rtol=0)
    K = (degree + 1) ** 2
    sh = torch.empty(100, K, 3, dtype=torch.float64)
    sh[:, 0] = torch.stack([col(f"f_dc_{c}") for c in range(3)], 1)
    for c in range(3):
        for k in range(1, K):
            sh[:, k, c] = col(f"f_rest_{c * (K - 1) + (k - 1)}")
    # seen along the turned direction, the file's SH give the colour the original gives along d
    dirs = torch.randn(100, 3, dtype=torch.float64)
    before = torch.einsum("nk,nkc->nc", sh_basis(degree, dirs), gs["sh"].double())
    after = torch.einsum("nk,nkc->nc", sh_basis(degree, dirs @ TURN.double().T), sh)
    torch.testing.assert_close(after, before, atol=1e-6, rtol=0)
    if degree > 0:
        assert not torch.allclose(sh[:, 1:], gs["sh"][:, 1:].double(), atol=1e-3)  # they were turned


def test_y_down_file_renders_as_the_scene_seen_turned(tmp_path):
    """The y-down file as stored, seen by the camera turned with it, is the original picture."""
    from rmavatar.animate.camera import intrinsics, look_at
    from rmavatar.render import rasterize

    gs = random_gaussians(n=300, degree=3, seed=8)
    raw = read_ply(write_ply(tmp_path / "d.ply", **gs), up=None)
    view = look_at([0.4, 0.3, 2.0], [0.0, 0.0, 0.0])
    turned = view.clone()
    turned[:3, :3] = view[:3, :3] @ TURN  # world -> camera of the y-down world
    K = intrinsics(48, 40, 45.0)
    bg = torch.ones(3)
    ref, _, _ = rasterize(gs["means"], gs["quats"], gs["scales"], gs["opacities"], gs["sh"], view, K, 48, 40,
                          background=bg, sh_degree=3)
    img, _, _ = rasterize(raw.means, raw.quats, raw.scales, raw.opacities, raw.sh, turned, K, 48, 40,
                          background=bg, sh_degree=3)
    assert float((ref - 1).abs().amax()) > 0.1
    assert float((img - ref).abs().max()) < 1e-5
    # and the raw file from the unturned camera is not the same picture (the turn is really there)
    wrong, _, _ = rasterize(raw.means, raw.quats, raw.scales, raw.opacities, raw.sh, view, K, 48, 40,
                            background=bg, sh_degree=3)
    assert float((wrong - ref).abs().max()) > 0.1


def test_read_ply_conventions(tmp_path):
    """read_ply brings both conventions back to y up (or to -y, or leaves the file as stored); a 3DGS file
    without our header comment is y down."""
    gs = random_gaussians(n=50, degree=3, seed=4)
    q = gs["quats"] / gs["quats"].norm(dim=1, keepdim=True)
    down, up = write_ply(tmp_path / "down.ply", **gs), write_ply(tmp_path / "up.ply", **gs, up="y")
    assert (ply_up(down), ply_up(up)) == ("-y", "y")
    for path in (down, up):
        back = read_ply(path)
        torch.testing.assert_close(back.means, gs["means"], atol=1e-6, rtol=0)
        torch.testing.assert_close(back.quats, q, atol=1e-6, rtol=0)
        torch.testing.assert_close(back.sh, gs["sh"], atol=1e-6, rtol=0)
    # up="-y" gives the y-down Gaussians whichever way the file was written; the turn is exact
    for name in ("means", "quats", "sh"):
        stored = getattr(read_ply(down, up=None), name)
        torch.testing.assert_close(getattr(read_ply(up, up="-y"), name), stored, atol=0, rtol=0)
        torch.testing.assert_close(getattr(read_ply(down, up="-y"), name), stored, atol=0, rtol=0)
    # someone else's 3DGS file: same data, no comment -> y down
    data = plyfile.PlyData.read(str(down))["vertex"].data
    other = tmp_path / "other.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(other))
    assert ply_up(other) == "-y"
    torch.testing.assert_close(read_ply(other).means, gs["means"], atol=1e-6, rtol=0)
    torch.testing.assert_close(read_ply(other, up=None).means, read_ply(down, up=None).means, atol=0, rtol=0)


def test_bad_conventions(tmp_path):
    gs = random_gaussians(n=5)
    with pytest.raises(UserError, match="up must be -y .* or y"):
        write_ply(tmp_path / "z.ply", **gs, up="z")
    assert not (tmp_path / "z.ply").exists()
    good = write_ply(tmp_path / "g.ply", **gs)
    with pytest.raises(UserError, match="up must be"):
        read_ply(good, up="+z")
    odd = tmp_path / "odd.ply"
    odd.write_bytes(good.read_bytes().replace(b"comment rmavatar up -y\n", b"comment rmavatar up z\n", 1))
    with pytest.raises(UserError, match="unknown world convention .*'z'"):
        read_ply(odd)


def test_read_ply_written_by_plyfile_big_endian(tmp_path):
    """Our reader accepts files from another writer (plyfile), in the other byte order."""
    gs = random_gaussians(n=20, degree=1, seed=5)
    ours = plyfile.PlyData.read(str(write_ply(tmp_path / "c.ply", **gs)))
    data = ours["vertex"].data.astype(ours["vertex"].data.dtype.newbyteorder(">"))
    other = tmp_path / "big.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")], byte_order=">").write(str(other))
    back = read_ply(other)
    torch.testing.assert_close(back.means, gs["means"], atol=1e-6, rtol=0)
    torch.testing.assert_close(back.sh, gs["sh"], atol=1e-6, rtol=0)


def test_render_round_trip(tmp_path):
    """A PLY re-rendered as a plain static 3DGS scene matches the render of the original Gaussians."""
    from rmavatar.animate.camera import intrinsics, look_at
    from rmavatar.render import rasterize

    gs = random_gaussians(n=300, degree=1, seed=7)
    back = read_ply(write_ply(tmp_path / "d.ply", **gs))
    view = look_at([0.3, 0.2, 2.0], [0.0, 0.0, 0.0])
    K = intrinsics(48, 40, 45.0)
    bg = torch.ones(3)
    ref, _, _ = rasterize(gs["means"], gs["quats"], gs["scales"], gs["opacities"], gs["sh"], view, K, 48, 40,
                          background=bg, sh_degree=1)
    img, _, _ = rasterize(back.means, back.quats, back.scales, back.opacities, back.sh, view, K, 48, 40,
                          background=bg, sh_degree=back.sh_degree)
    assert float((ref - 1).abs().amax()) > 0.1  # the Gaussians are in view
    assert float((img - ref).abs().max()) < 1e-5


def test_bad_files(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "x.ply").write_bytes(b"hello")
    with pytest.raises(UserError, match="not a PLY"):
        read_ply(tmp_path / "x.ply")
    mesh = tmp_path / "mesh.ply"
    verts = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(verts, "vertex")]).write(str(mesh))
    with pytest.raises(UserError, match="not a 3D Gaussian Splatting PLY"):
        read_ply(mesh)
    good = write_ply(tmp_path / "g.ply", **random_gaussians(n=10))
    raw = good.read_bytes()
    (tmp_path / "trunc.ply").write_bytes(raw[:-7])
    with pytest.raises(UserError, match="truncated"):
        read_ply(tmp_path / "trunc.ply")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into read-only folders")
def test_unwritable_folder_nonroot(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(UserError, match="not writable"):
            write_ply(ro / "a.ply", **random_gaussians(n=5))
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o700)


def test_failed_write_leaves_nothing(tmp_path):
    gs = random_gaussians(n=5)
    gs["sh"] = gs["sh"][:, :3]  # 3 coefficients is not a full SH degree
    with pytest.raises(ValueError):
        write_ply(tmp_path / "bad.ply", **gs)
    with pytest.raises(UserError, match="does not exist"):
        write_ply(tmp_path / "no" / "such" / "a.ply", **random_gaussians(n=5))
    (tmp_path / "in_the_way.ply").mkdir()  # refused before writing: no temporary file may remain
    with pytest.raises(UserError, match="in_the_way.ply is a folder"):
        write_ply(tmp_path / "in_the_way.ply", **random_gaussians(n=5))
    assert [p.name for p in tmp_path.iterdir()] == ["in_the_way.ply"]
    assert list((tmp_path / "in_the_way.ply").iterdir()) == []


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc (a file system nobody can create files in)")
def test_unwritable_file_system():
    with pytest.raises(UserError, match="cannot write --ply /proc/rmavatar-test.ply"):
        write_ply("/proc/rmavatar-test.ply", **random_gaussians(n=5))
