"""A shortened end-to-end demo: every step runs and the outputs are real files with sane contents."""

import json

import imageio.v3 as iio

from rmavatar.demo import DemoConfig, run_demo
from rmavatar.export.ply import read_ply


def test_demo_end_to_end_smoke(tmp_path):
    out = tmp_path / "demo"
    cfg = DemoConfig(out=out, size=48, iters=40, video_size=64, animation_frames=8, turntable_frames=6,
                     synth={"train": 12, "test": 4, "novel_pose": 4, "ss": 1})
    m = run_demo(cfg, progress=False)
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["test"]["psnr"] == m["test"]["psnr"]
    for split in ("test", "novel_pose"):
        s = saved[split]
        # 40 iterations cannot make a good avatar, but it must beat a blank white image by a margin.
        assert 12.0 < s["psnr"] < 60.0 and 0.0 < s["ssim"] <= 1.0 and 0.0 <= s["lpips"] < 1.0
        assert len(list((out / f"eval_{split}").glob("*.png"))) == s["frames"] == 4
    assert saved["iterations"] == 40 and saved["train_seconds"] > 0
    video = iio.imread(out / "animation.mp4")
    assert video.shape[0] == 8 and video.shape[1:3] == (64, 64)
    assert video.std() > 1.0  # not a blank clip
    turn = iio.imread(out / "turntable.mp4")
    assert turn.shape[0] == 6
    ply = read_ply(out / "avatar.ply")
    assert ply.means.shape[0] == saved["gaussians"] > 1000
    assert bool(ply.means.isfinite().all())
