"""End to end: a synthetic subject rendered to an MP4 -> ``rmavatar capture`` -> training on the
captured dataset. Asserts the fitted joints against the true ones and the trained avatar's PSNR on
the captured test frames (tiny sizes: about 100 s of CPU time)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from rmavatar.capture.fit import STILL_HOLD_POSE, STILL_HOLD_UP, STILL_KEYPOINTS
from rmavatar.commands import main

from helpers import tiny_train_config

SIZE = 128
TRAIN, TEST = 24, 6


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    pytest.importorskip("mediapipe")
    from rmavatar.animate.video import frame_writer
    from rmavatar.data import load_dataset
    from rmavatar.data.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("capture_e2e")
    truth = root / "truth"
    synthesize(truth, SynthConfig(size=SIZE, seed=0, train=TRAIN, test=TEST, novel_pose=0, ss=2), progress=False)
    ds = load_dataset(truth)
    video = root / "turn.mp4"
    with frame_writer(video, 7.5, SIZE, SIZE) as write:
        for split in ("train", "test"):
            for f in ds.frames(split):
                write((f.image * 255 + 0.5).astype(np.uint8))
    fx = float(ds.camera("train", 0).K[0, 0])
    fov = math.degrees(2 * math.atan(SIZE / 2 / fx))
    out = root / "captured"
    # --still: the subject turns holding its A-pose, as the recording instructions ask
    assert main(["capture", str(video), "--out", str(out), "--fov", repr(fov), "--still", "--quiet"]) == 0
    return truth, out


def fitted_vs_true(truth, out):
    """Mean 2D joint error (% of the body's height in the image) and root-aligned 3D joint error (mm)
    of the 24 joints over all frames."""
    from rmavatar.body import load_body_model

    true = np.load(truth / "smpl_true.npz")
    cams = np.load(truth / "cameras.npz")
    fit = np.load(out / "smpl.npz")
    K = np.load(out / "cameras.npz")["K"]
    src = np.load(out / "capture.npz")["source_index"]
    body = load_body_model(yaml.safe_load((out / "meta.yaml").read_text())["body"])
    with torch.no_grad():
        t = body(None, *(torch.tensor(true[k][src]) for k in ("global_orient", "body_pose", "transl")))
        f = body(None, *(torch.tensor(fit[k]) for k in ("global_orient", "body_pose", "transl")))
    V = cams["viewmat"][src]
    cam = lambda x: np.einsum("nij,nkj->nki", V[:, :3, :3], x.numpy()) + V[:, None, :3, 3]  # noqa: E731
    jt, vt, jf = cam(t.joints), cam(t.vertices), f.joints.numpy()
    proj = lambda x, k: x[..., :2] / x[..., 2:] * k[..., None, [0, 1], [0, 1]] + k[..., None, :2, 2]  # noqa: E731
    ys = proj(vt, cams["K"][src])[..., 1]
    height = ys.max(1) - ys.min(1)
    e2 = np.linalg.norm(proj(jt, cams["K"][src]) - proj(jf, K), axis=-1) / height[:, None] * 100
    e3 = np.linalg.norm((jt - jt[:, :1]) - (jf - jf[:, :1]), axis=-1) * 1000
    return float(e2.mean()), float(e3.mean())


@pytest.mark.slow
def test_capture_then_train(captured, tmp_path):
    from rmavatar.data import load_dataset
    from rmavatar.evaluate import evaluate_run
    from rmavatar.train import train

    truth, out = captured
    ds = load_dataset(out)
    assert ds.poses_estimated and ds.body == "anny:neutral"
    fit = yaml.safe_load((out / "meta.yaml").read_text())["extra"]["fit"]
    assert (fit["hold_pose"], fit["hold_up"], fit["keypoints"]) == (STILL_HOLD_POSE, STILL_HOLD_UP, STILL_KEYPOINTS)
    assert {s: len(v) for s, v in ds.splits.items()} == {"train": TRAIN, "test": TEST}
    assert (out / "contact_sheet.png").is_file()
    assert main(["inspect", str(out)]) == 0
    e2, e3 = fitted_vs_true(truth, out)
    # measured: 0.59 % and 20 mm (0.62 % and 21 mm before --still weighed the keypoints 0.3; 0.72 % and
    # 24 mm before the outline term; 1.02 % and 33 mm before --still held the up axis and the silhouette
    # weighed 20; 1.03 % and 35 mm without --still; MediaPipe's own landmarks are 1.1 % off at the median)
    assert e2 < 1.6 and e3 < 75, (e2, e3)

    cfg = tiny_train_config(out, 200)  # no densification, on the CPU
    # Two passes with refinement and pose fits, as `rmavatar train` runs on captured data, but fits of 10
    # steps (the default 30 made them most of this test's time: 226 s in CI, then 100 s)
    cfg.poses.fit_steps = cfg.poses.held_fit_steps = 10
    train(cfg, tmp_path / "run", progress=False)
    res = evaluate_run(tmp_path / "run", split="test", progress=False)
    # measured: 21.37 dB on the captured test tail (200 iterations at 128 px, two passes, 10-step sweeps
    # and refits, fitting without the mask term; 21.43 before --still weighed the keypoints 0.3, 21.55
    # before refits and poses.fit_mask 0; 21.29 before the capture's outline term, 20.44 before
    # --still held the up axis and the silhouette weighed 20, 20.57 without --still, 21.0 before pose
    # refinement existed; the default 30-step sweeps were not measured here)
    assert res["mean"]["psnr"] > 20.0, res["mean"]
