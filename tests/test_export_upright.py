"""Exported avatars stand upright where people open them, and our renders agree with each other.

Stock 3DGS viewers (SuperSplat, PlayCanvas' splat-transform viewer) take a PLY to be in the COLMAP /
OpenCV convention, y down: ``rmavatar export`` must write the avatar with its head towards -y (unless
``--up y``), say so in the header, and ``render --ply`` of the file must show what ``render RUN`` shows.
Uses the session's tiny trained run (conftest.py): its Gaussians sit on the body mesh, so their layout
is the T-pose's whatever 10 iterations made of their colours.
"""

import imageio.v3 as iio
import numpy as np
import pytest

from rmavatar.commands import main

plyfile = pytest.importorskip("plyfile")

# render --ply of an exported avatar against render RUN of the same pose, as uint8 PNGs. Both rasterize
# the same Gaussians through the same camera (frame_camera depends on positions only, and the y-up ->
# y-down turn only flips signs, so positions come back bit for bit); what the file rounds is the log-scales,
# opacity logits and unit quaternions to float32 and the SH turned into world axes, ~1e-6 relative. That
# moves a pixel by well under one grey level, except where it flips a value across a rounding half-step
# (one level) or a Gaussian across one of the rasterizer's cutoffs (alpha 1/255, transmittance 1e-4, the
# 3-sigma box): a few levels at a few pixels. An upside-down, mirrored or wrongly coloured file changes most
# figure pixels by tens of levels.
MAX_LEVELS = 6  # largest difference of any channel, in uint8 levels
MAX_CHANGED = 0.01  # fraction of channel values that may differ at all


def _export(run, path, *extra):
    assert main(["export", str(run), "--ply", str(path), *extra]) == 0
    return path


def _head_up_checks(path, up):
    """In the convention ``up`` the T-pose's arms (its widest part) are at the upper end, the feet at the
    lower end, and the toes point the way the avatar faces; and the header names that convention (read
    by our reader only: stock viewers go by the geometry alone, taking it to be y down)."""
    ply = plyfile.PlyData.read(str(path))
    v = ply["vertex"]
    pos = np.stack([np.asarray(v[a], np.float64) for a in "xyz"], 1)
    up_dir = np.array([0.0, -1.0, 0.0]) if up == "-y" else np.array([0.0, 1.0, 0.0])
    front_dir = np.array([0.0, 0.0, -1.0]) if up == "-y" else np.array([0.0, 0.0, 1.0])
    height = pos @ up_dir
    lo, hi = np.quantile(height, [0.005, 0.995])
    assert hi - lo > 0.5  # a standing body, about 1.7 m tall along the up axis
    upper = height > 0.5 * (lo + hi)
    width = lambda sel: np.ptp(pos[sel, 0])  # noqa: E731  (the arms and shoulders run along x)
    # the T-pose's arms: the upper half is much wider than the legs below
    assert width(upper) > 2.0 * width(~upper), (width(upper), width(~upper))
    # the widest slice across the up axis (the arms) is in the upper quarter: the head end is up
    edges = np.linspace(lo, hi, 13)
    widths = [width((height >= a) & (height < b)) for a, b in zip(edges[:-1], edges[1:])]
    assert np.argmax(widths) >= 8, widths
    # the feet (lowest 3%) reach further forward than back from the body's middle: toes face front
    depth = pos @ front_dir - np.median(pos @ front_dir)
    feet = depth[height < np.quantile(height, 0.03)]
    assert feet.max() > -feet.min() + 0.02, (feet.max(), feet.min())
    assert f"rmavatar up {up}" in ply.comments, ply.comments


@pytest.mark.parametrize("up", ["-y", "y"])
def test_export_head_up_in_written_convention(trained_run, tmp_path, up):
    """The default export is y down (what stock 3DGS viewers expect); --up y writes SMPL's y up."""
    extra = [] if up == "-y" else ["--up", "y"]
    _head_up_checks(_export(trained_run, tmp_path / "a.ply", *extra), up)


def _figure(img):
    return np.abs(img.astype(int) - 255).max(-1) > 12  # on the white background


def test_render_ply_matches_render_run(trained_run, tmp_path):
    """``render --ply`` of an exported avatar (either convention) is ``render RUN`` of the same pose."""
    view = ["--size", "64", "--azimuth", "30", "--elevation", "10", "--backend", "cpu"]
    still = tmp_path / "run.png"
    assert main(["render", str(trained_run), "--out", str(still), *view]) == 0  # the T-pose
    ref = iio.imread(still)
    fig = _figure(ref)
    assert ref.shape == (64, 64, 3) and fig.mean() > 0.05
    rows = np.flatnonzero(fig.any(1))
    top, bottom = rows.min(), rows.max()
    assert bottom - top > 0.5 * 64  # framed: a standing figure fills much of the height
    # upright: the widest row of the figure (shoulders and arms) is in its upper half
    widths = fig.sum(1)
    assert np.argmax(widths) < 0.5 * (top + bottom), (np.argmax(widths), top, bottom)
    for up in ("-y", "y"):
        ply = _export(trained_run, tmp_path / f"a{up}.ply", f"--up={up}")
        out = tmp_path / f"ply{up}.png"
        assert main(["render", "--ply", str(ply), "--out", str(out), *view]) == 0
        diff = np.abs(iio.imread(out).astype(int) - ref.astype(int))
        assert diff.max() <= MAX_LEVELS and (diff > 0).mean() <= MAX_CHANGED, (up, diff.max(), (diff > 0).mean())


def test_render_run_still_options(trained_run, tmp_path, capsys):
    """``render RUN --out still.png`` is a still; the pose and camera options change it."""
    base = ["--size", "48", "--backend", "cpu"]
    shots = {}
    for name, extra in (("front", ["--azimuth", "0"]), ("side", ["--azimuth", "90"]),
                        ("apose", ["--azimuth", "0", "--pose", "apose"]),
                        ("up", ["--azimuth", "0", "--elevation", "30"])):
        out = tmp_path / f"{name}.png"
        assert main(["render", str(trained_run), "--out", str(out), *base, *extra]) == 0
        shots[name] = _figure(iio.imread(out))
    assert "the avatar of" in capsys.readouterr().out
    assert shots["side"].sum() < 0.7 * shots["front"].sum()  # the spread arms point at the camera
    for other in ("apose", "up"):
        assert (shots[other] != shots["front"]).mean() > 0.02
