"""``rmavatar render`` and ``rmavatar bench raster`` end to end, on tiny inputs."""

import json

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from rmavatar.commands import main
from rmavatar.export.ply import read_ply
from rmavatar.render.scenes import figure_scene


def _write_ply(path, scene, sh_degree):
    n = len(scene["means"])
    k = (sh_degree + 1) ** 2
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.zeros(n, dtype=[(nm, "<f4") for nm in names])
    for i, a in enumerate("xyz"):
        data[a] = scene["means"][:, i]
    sh = scene["colors"]
    for c in range(3):
        data[f"f_dc_{c}"] = sh[:, 0, c]
        for j in range(k - 1):
            data[f"f_rest_{c * (k - 1) + j}"] = sh[:, 1 + j, c]
    data["opacity"] = torch.logit(scene["opacities"])
    for i in range(3):
        data[f"scale_{i}"] = torch.log(scene["scales"][:, i])
    for i in range(4):
        data[f"rot_{i}"] = scene["quats"][:, i]
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
    header += "".join(f"property float {nm}\n" for nm in names) + "end_header\n"
    path.write_bytes(header.encode() + data.tobytes())


def test_ply_roundtrip(tmp_path):
    """A 3DGS file written by someone else (no rmavatar header comment): read as stored with up=None;
    by default it is taken to be y down, as 3DGS files are, and turned into rmavatar's y-up world."""
    scene = figure_scene(50, seed=1, sh_degree=2)
    _write_ply(tmp_path / "s.ply", scene, 2)
    back = read_ply(tmp_path / "s.ply", up=None)
    assert back.sh_degree == 2
    for k, name in (("means", "means"), ("quats", "quats"), ("scales", "scales"), ("opacities", "opacities"),
                    ("colors", "sh")):
        torch.testing.assert_close(getattr(back, name), scene[k], atol=1e-5, rtol=1e-5)
    up = read_ply(tmp_path / "s.ply")
    torch.testing.assert_close(up.means, scene["means"] * torch.tensor([1.0, -1.0, -1.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(up.scales, scene["scales"], atol=1e-5, rtol=1e-5)


def test_render_random_and_ply(tmp_path):
    out = tmp_path / "fig.png"
    assert main(["render", "--random", "3000", "--size", "96", "--out", str(out)]) == 0
    img = iio.imread(out)
    assert img.shape == (96, 96, 3)
    assert (img < 200).any(axis=-1).mean() > 0.05 and (img == 255).all(axis=-1).mean() > 0.3  # figure on white
    _write_ply(tmp_path / "s.ply", figure_scene(2000, seed=2, sh_degree=1), 1)
    out2 = tmp_path / "ply.png"
    assert main(["render", "--ply", str(tmp_path / "s.ply"), "--size", "64", "--out", str(out2)]) == 0
    img = iio.imread(out2)
    assert (img < 200).any(axis=-1).mean() > 0.05
    # the figure's file is y down (its head at -y), as 3DGS scenes are: render --ply shows it upright, the
    # one narrow head at the top, the two shins (further apart than the head is wide) at the bottom
    fig = (img < 200).any(axis=-1)
    filled = np.flatnonzero(fig.any(1))
    top, bottom = filled.min(), filled.max()
    tenth = max(2, (bottom - top) // 10)

    def extent(r):  # from the leftmost to the rightmost figure pixel of row r
        cols = np.flatnonzero(fig[r])
        return cols.max() - cols.min() + 1

    head = np.mean([extent(r) for r in range(top, top + tenth)])
    feet = np.mean([extent(r) for r in range(bottom - tenth + 1, bottom + 1)])
    assert head < 0.8 * feet, (head, feet)


def test_render_errors(tmp_path, capsys):
    assert main(["render", "--ply", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "x.png")]) == 2
    assert "missing.ply" in capsys.readouterr().err
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    assert main(["render", "--ply", str(tmp_path / "bad.ply"), "--out", str(tmp_path / "x.png")]) == 2
    assert not (tmp_path / "x.png").exists()


def test_bench_raster_json(tmp_path):
    out = tmp_path / "b.json"
    assert main(["bench", "raster", "--configs", "300x48", "--repeats", "1", "--warmup", "0",
                 "--no-reference", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    (row,) = rep["results"]
    assert row["n"] == 300 and row["size"] == 48
    assert 0 < row["forward_s"] and 0 < row["forward_backward_s"]
    assert row["gaussians_per_s_forward_backward"] == pytest.approx(300 / row["forward_backward_s"])
    assert row["visible"] > 0 and "peak_rss_growth_mb" in row


def test_render_argument_errors(tmp_path, capsys):
    """Options that do not fit the source are refused by name, before anything is read or written."""
    ply = tmp_path / "s.ply"
    _write_ply(ply, figure_scene(20, seed=3, sh_degree=0), 0)
    run = tmp_path / "no_run"  # never reached: the arguments are checked first
    png = str(tmp_path / "x.png")
    cases = [
        (["render", "--ply", str(ply), "--out", png, "--pose", "apose"], "--pose applies to a trained RUN"),
        (["render", "--ply", str(ply), "--out", png, "--turntable"], "--turntable applies to a trained RUN"),
        (["render", "--random", "10", "--out", png, "--elevation", "10"], "--elevation applies to a trained RUN"),
        (["render", str(run), "--out", png, "--frames", "3"], "--frames is for --turntable"),
        (["render", str(run), "--turntable", "--out", str(tmp_path / "t.mp4"), "--azimuth", "10"], "--azimuth"),
        (["render", "--ply", str(ply), "--out", png, "--elevation", "90"], "--elevation must be between"),
        (["render", "--ply", str(ply), "--out", png, "--fov", "0"], "--fov must be between"),
        (["render", "--ply", str(ply), "--out", str(tmp_path / "x.jpg")], "must end in .png"),
        (["render", str(run), "--out", str(tmp_path / "still.mp4")], "must end in .png"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        assert message in capsys.readouterr().err, argv
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]


def test_export_up_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["export", str(tmp_path), "--ply", str(tmp_path / "a.ply"), "--up", "z"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--up" in err and "'z'" in err and "-y" in err
