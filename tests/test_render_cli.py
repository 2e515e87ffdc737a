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
    scene = figure_scene(50, seed=1, sh_degree=2)
    _write_ply(tmp_path / "s.ply", scene, 2)
    back = read_ply(tmp_path / "s.ply")
    assert back.sh_degree == 2
    for k, name in (("means", "means"), ("quats", "quats"), ("scales", "scales"), ("opacities", "opacities"),
                    ("colors", "sh")):
        torch.testing.assert_close(getattr(back, name), scene[k], atol=1e-5, rtol=1e-5)


def test_render_random_and_ply(tmp_path):
    out = tmp_path / "fig.png"
    assert main(["render", "--random", "3000", "--size", "96", "--out", str(out)]) == 0
    img = iio.imread(out)
    assert img.shape == (96, 96, 3)
    assert (img < 200).any(axis=-1).mean() > 0.05 and (img == 255).all(axis=-1).mean() > 0.3  # figure on white
    _write_ply(tmp_path / "s.ply", figure_scene(2000, seed=2, sh_degree=1), 1)
    out2 = tmp_path / "ply.png"
    assert main(["render", "--ply", str(tmp_path / "s.ply"), "--size", "64", "--out", str(out2)]) == 0
    assert (iio.imread(out2) < 200).any(axis=-1).mean() > 0.05


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
