"""``rmavatar bench capture``: the report of a tiny synthetic clip through the command, and its measures of
the fit against the truth (a capture of a clip whose true poses and masks are known)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rmavatar.commands import main


@pytest.fixture(scope="module")
def turn(tmp_path_factory):
    """A 128-px synthetic turn (10 frames) as an MP4, its truth dataset, and its true field of view."""
    pytest.importorskip("mediapipe")
    from rmavatar.animate.video import frame_writer
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("bench_capture")
    truth = root / "truth"
    synthesize(truth, SynthConfig(size=128, seed=0, train=8, test=2, novel_pose=0, ss=2, turns=0.4), progress=False)
    ds = load_dataset(truth)
    video = root / "turn.mp4"
    with frame_writer(video, 7.5, 128, 128) as write:
        for split in ("train", "test"):
            for f in ds.frames(split):
                write((f.image * 255 + 0.5).astype(np.uint8))
    fov = math.degrees(2 * math.atan(64 / float(ds.camera("train", 0).K[0, 0])))
    return video, truth, fov


def test_bench_capture_reports_stages_and_quality(turn, tmp_path, capsys):
    video, _, fov = turn
    out = tmp_path / "capture.json"
    assert main(["bench", "capture", str(video), "--frames", "6", "--fov", repr(fov), "--still", "--quiet",
                 "--json", str(out)]) == 0
    capsys.readouterr()
    r = json.loads(out.read_text())
    assert r["frames_decoded"] == 6 and r["frames_with_person"] == 6 and r["share_with_person"] == 1.0
    per = r["seconds_per_frame"]
    assert set(per) == {"decode", "landmarks", "masks", "fit", "shape", "views", "write", "other", "total"}
    assert all(v >= 0 for k, v in per.items() if k != "other")
    assert per["total"] == pytest.approx(sum(v for k, v in per.items() if k != "total"), abs=1e-3)
    assert set(r["cpu_seconds_per_frame"]) == {"decode", "landmarks", "masks", "fit", "shape", "views", "write"}
    assert 0.5 < r["landmarks_visible"] <= 1 and 0.5 < r["silhouette_iou"] <= 1
    assert 0.5 < r["silhouette_iou_preset"] <= 1 and r["shape"]["frames"] == 6 and r["shape"]["max_mm"] > 0
    assert r["frame_size"] == [128, 128] and r["detection_size"] == [128, 128]
    assert "load_average_before" in r["machine"]


def test_assess_against_the_truth(turn, tmp_path):
    """The captured synthetic turn against its truth: the fit's joints within a per cent or so of the
    height, the masks close to the true ones; and iou() on hand-made masks."""
    from rmavatar.bench.capture import assess, iou
    from rmavatar.capture import CaptureConfig, capture
    from rmavatar.capture.fit import BodyFitConfig

    video, truth, fov = turn
    out = tmp_path / "captured"
    fit = BodyFitConfig().still()
    fit.start_iters, fit.iters = 40, 160
    capture(video, out, CaptureConfig(fov=fov, fit=fit), progress=False)
    got = assess(out, truth)
    t = got["truth"]
    # measured: 0.67 % of the height, 21 mm, mask IoU 0.983, silhouette IoU 0.934 with the fitted shape and
    # 0.898 with the preset's (160 iterations at 128 px)
    assert t["joint_2d_percent_height"] < 1.5 and t["joint_3d_root_aligned_mm"] < 45, t
    assert t["mask_iou"] > 0.95 and got["silhouette_iou_preset"] > 0.8, got
    assert got["silhouette_iou"] > got["silhouette_iou_preset"] + 0.01, got
    a = np.zeros((2, 4, 4), bool)
    a[0, :2], a[1, :] = True, False
    b = np.zeros((2, 4, 4), bool)
    b[0, :1] = True
    np.testing.assert_allclose(iou(a, b), [0.5, 1.0])
