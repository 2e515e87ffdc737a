"""The viser viewer of a small trained run: served on a free localhost port, opened in a real headless
Chromium, screenshotted while the camera presets and the timeline are used.

Needs a chromium binary (``scripts/install-browser.sh``); without one the browser test is skipped.
Set RMAVATAR_VIEWER_SHOTS=DIR to keep the screenshots for looking at.
"""

import os
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from headless import find_browser, screenshot
from helpers import dance

from rmavatar.avatar import load_trained
from rmavatar.body import Motion, PoseSequence, motion_to_sequence
from rmavatar.body.hands import hand_axes, hand_pose_from_angles
from rmavatar.viewer.app import SH_C0, avatar_viewer, splat_arrays

W, H = 800, 600


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def middle_mask(img: np.ndarray) -> np.ndarray:
    """Pixels of the middle of the page (away from viser's control panel, right) differing from white."""
    mid = img[H // 4: 3 * H // 4, W // 2 - 150: W // 2 + 100].astype(int)
    return np.abs(mid - 255).max(-1) > 40


def test_splat_arrays_match_3dgs_definitions():
    g = torch.Generator().manual_seed(1)
    q = torch.randn(5, 4, generator=g)
    s = torch.rand(5, 3, generator=g) + 0.1
    sh = torch.randn(5, 4, 3, generator=g)
    out = splat_arrays(torch.zeros(5, 3), q, s, torch.rand(5, generator=g), sh)
    from scipy.spatial.transform import Rotation

    qn = (q / q.norm(dim=1, keepdim=True)).double().numpy()
    R = Rotation.from_quat(qn[:, [1, 2, 3, 0]]).as_matrix()  # scipy is xyzw
    cov = R @ (np.eye(3)[None] * (s.double().numpy() ** 2)[:, None, :]) @ R.transpose(0, 2, 1)
    np.testing.assert_allclose(out["covariances"], cov, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out["rgbs"], np.clip(SH_C0 * sh[:, 0].numpy() + 0.5, 0, 1), atol=1e-6)
    assert out["opacities"].shape == (5, 1)


@pytest.fixture
def viewer(trained_run):  # the small trained run: a session fixture in conftest.py

    poses, trans = dance(n=6, drift=3.0)
    seq = motion_to_sequence(Motion(poses[:, :3], poses[:, 3:], trans, fps=30.0))
    v = avatar_viewer(load_trained(trained_run), seq, fps=30.0, port=free_port())
    yield v
    v.close()


def test_viewer_timeline_and_play(viewer):
    before = viewer.splats.buffer.copy()
    viewer.frame_slider.value = 2  # (frame 3 repeats frame 0's pose: the dance is periodic)
    assert viewer._shown == 2 and not np.array_equal(before, viewer.splats.buffer)
    at2 = viewer.splats.buffer.copy()
    viewer.frame_slider.value = 0
    viewer.frame_slider.value = 2  # from the cache: the same splats
    np.testing.assert_array_equal(viewer.splats.buffer, at2)
    viewer.speed.value = 60.0
    viewer.play.value = True
    # Poll rather than sleep a fixed time: the timeline loops every 6 frames, so a fixed sleep can land
    # back on frame 2, and a busy machine delays the player thread.
    deadline = time.monotonic() + 10.0
    moved = False
    while not moved and time.monotonic() < deadline:
        moved = int(viewer.frame_slider.value) != 2
        time.sleep(0.005)
    viewer.play.value = False
    assert moved  # playing advanced the timeline


def test_viewer_plays_the_finger_poses(trained_run):
    trained = load_trained(trained_run)
    bend = torch.linspace(0.0, 1.2, 3)[:, None, None, None].expand(3, 2, 5, 3)
    hands = hand_pose_from_angles(bend, torch.zeros(3, 2, 5), hand_axes(trained.body))
    zero = torch.zeros(3, 3)
    v = avatar_viewer(trained, PoseSequence(zero, torch.zeros(3, 69), zero, hands), port=free_port())
    try:  # a T-pose closing its hands: the Gaussians the page gets for the first and last frame
        flat, fists = (v.state.frame_fn(i)[0] for i in (0, 2))
    finally:
        v.close()
    moved = (fists - flat).norm(dim=-1)
    torso = flat[:, 0].abs() < 0.3  # the hands are far out on the sides
    assert float(moved.max()) > 0.03 and int(torso.sum()) > 1000 and float(moved[torso].max()) < 1e-6


def test_viewer_in_headless_chromium(viewer):
    browser = find_browser()
    if browser is None:
        pytest.skip("no chromium binary found: run scripts/install-browser.sh (or set RMAVATAR_CHROMIUM)")
    shots = screenshot(
        f"http://127.0.0.1:{viewer.port}/", W, H, timeout=90, browser=browser,
        ready=lambda img: middle_mask(img).mean() > 0.02, settle=1.0,
        steps=[lambda: viewer.set_camera("side"), lambda: viewer.set_camera("back"),
               lambda: setattr(viewer.frame_slider, "value", 4)],
    )
    keep = os.environ.get("RMAVATAR_VIEWER_SHOTS")
    if keep:
        from PIL import Image

        Path(keep).mkdir(parents=True, exist_ok=True)
        for name, img in zip(("front", "side", "back", "back_frame4"), shots):
            Image.fromarray(img).save(Path(keep) / f"viewer_{name}.png")
    front, side, back, back4 = (middle_mask(s) for s in shots)
    assert front.mean() > 0.02, "the avatar is not visible in the browser"
    assert np.abs(shots[0][H // 4:, : W // 4].astype(int) - 255).max(-1).mean() < 20  # white page elsewhere
    # the presets move the browser's camera: spread arms seen from the side are hidden
    assert side.sum() < 0.75 * front.sum()
    assert back.mean() > 0.02 and np.abs(shots[0].astype(int) - shots[2]).mean() > 1.0
    # the timeline moves the avatar in the browser
    assert (back ^ back4).mean() > 0.005
