"""rmavatar capture's fingers: the body's hand points for a hand pose, the hand fit on synthetic
landmarks, frames without a hand (held, then eased to the relaxed hand), left / right assignment, and
MediaPipe's hand model on a rendered frame."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import roma
import torch
from helpers import random_smplx, save_npz

from rmavatar.body import PoseSequence, load_body_model, posed_vertices
from rmavatar.body.base import HAND_POINT_NAMES
from rmavatar.body.hands import hand_axes, hand_pose_from_angles
from rmavatar.capture import hands as H
from rmavatar.capture.fit import project
from rmavatar.data.synth.motion import HAND_SHAPES, finger_motion

K = torch.tensor([[1400.0, 0.0, 540.0], [0.0, 1400.0, 540.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def anny():
    return load_body_model("anny:neutral")


def _raised_arms(T: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A body facing the camera (camera axes: y down), forearms raised, with some random variation."""
    go = torch.tensor([[math.pi, 0.0, 0.0]]).repeat(T, 1) + 0.1 * torch.randn(T, 3, generator=g)
    bp = torch.zeros(T, 69)
    bp[:, 3 * 15 + 2], bp[:, 3 * 16 + 2] = -1.2, 1.2  # shoulders 16, 17
    bp[:, 3 * 17 + 1], bp[:, 3 * 18 + 1] = -2.0, 2.0  # elbows 18, 19
    bp += 0.15 * torch.randn(T, 69, generator=g)
    return go, bp, torch.tensor([[0.0, 0.2, 3.0]]).repeat(T, 1)


def _landmarks(anny, go, bp, tr, hand_pose, g, px: float, metres: float):
    """What MediaPipe would give for the body's own hand points: pixels [T,2,21,2] with ``px`` noise,
    world [T,2,21,3] relative to the wrist, as seen along the ray through it, with ``metres`` noise."""
    T = go.shape[0]
    with torch.no_grad():
        pts = anny(None, go, bp, tr, hand_pose=hand_pose).hand_points.reshape(T, 2, 21, 3)
    kp = project(pts, K) + px * torch.randn(T, 2, 21, 2, generator=g)
    to_camera = H.camera_world(torch.eye(3).expand(T, 2, 3, 3), kp, K)  # rows: world @ to_camera = camera
    world = (pts - pts[:, :, :1]) @ to_camera.transpose(-1, -2) + metres * torch.randn(T, 2, 21, 3, generator=g)
    return kp, world


def _angles(a, b) -> np.ndarray:
    """Geodesic angle (degrees) between matching joints of two hand poses [T,90] -> [T,30]."""
    ra = roma.rotvec_to_rotmat(torch.as_tensor(a, dtype=torch.float64).reshape(-1, 30, 3))
    rb = roma.rotvec_to_rotmat(torch.as_tensor(b, dtype=torch.float64).reshape(-1, 30, 3))
    return torch.rad2deg(roma.rotmat_to_rotvec(ra.transpose(-1, -2) @ rb).norm(dim=-1)).numpy()


def test_the_hand_chain_poses_the_bodys_hand_points(anny):
    chain = H.HandChain(anny)
    assert chain.error < 1e-5  # metres, on random body and hand poses
    assert chain.hand_joint  # Anny's four fingers turn with SMPL's hand joint
    assert 0.15 < chain.length < 0.25


def test_the_hand_chain_follows_smplh_fingers_from_the_wrist(tmp_path):
    save_npz(random_smplx("smplh", 16, seed=0), tmp_path / "smplh.npz")
    body = load_body_model(f"smpl:{tmp_path / 'smplh.npz'}")
    chain = H.HandChain(body)
    assert not chain.hand_joint  # SMPL-H has no joints 22 / 23: its fingers hang from the wrist
    g = torch.Generator().manual_seed(0)
    go, bp, tr, hp = (s * torch.randn(3, n, generator=g) for s, n in ((0.5, 3), (0.4, 69), (1.0, 3), (0.4, 90)))
    truth = body(None, go, bp, tr, hand_pose=hp).hand_points.reshape(3, 2, 21, 3)
    joints = [k for k, name in enumerate(HAND_POINT_NAMES) if not name.endswith("_tip")]
    # the joints exactly; the tips ride on the last joint, which this file's random skinning does not do
    error = (chain.points(hp, *chain.body_frames(go, bp, tr)) - truth)[:, :, joints].norm(dim=-1)
    assert float(error.max()) < 1e-5


def _scene(anny, T: int, seed: int, frames_per_shape: float):
    """T frames of the synthetic finger motion on raised arms, and their landmarks with small noise:
    (true hand poses, global_orient, body_pose, transl, 2D keypoints, world landmarks, found [T,2])."""
    g = torch.Generator().manual_seed(seed)
    truth = torch.as_tensor(finger_motion(T, hand_axes(anny), np.random.default_rng(seed),
                                          frames_per_shape=frames_per_shape))
    go, bp, tr = _raised_arms(T, g)
    kp, world = _landmarks(anny, go, bp, tr, truth, g, px=0.2, metres=0.0005)
    return truth, go, bp, tr, kp, world, np.ones((T, 2), bool)


def test_the_fit_recovers_a_known_hand_pose(anny):
    T = 8
    truth, go, bp, tr, kp, world, found = _scene(anny, T, seed=0, frames_per_shape=2.0)
    # with a weak prior the landmarks alone recover it; the default prior (for MediaPipe's noisy
    # landmarks) pulls it some way towards the relaxed hand
    times = np.arange(T) / 30.0
    fit = H.fit_hands(anny, go, bp, tr, kp, world, found, K, times, H.HandFitConfig(smooth=0.0, prior=0.002))
    error = _angles(truth, fit.hand_pose)
    relaxed = _angles(truth, anny.relaxed_hand_pose.expand(T, -1))
    assert error.mean() < 3.0, error.mean(0)
    assert relaxed.mean() > 5 * error.mean()
    assert fit.found.all() and np.nanmax(fit.bone_error) < 5.0
    default = _angles(truth, H.fit_hands(anny, go, bp, tr, kp, world, found, K, times).hand_pose)
    assert error.mean() < default.mean() < relaxed.mean() / 2
    # the wrists are the body's own here: they turn by little
    turned = torch.as_tensor(fit.body_pose - bp.numpy())[:, 57:63].reshape(T, 2, 3).norm(dim=-1)
    assert float(turned.max()) < math.radians(3)
    others = np.r_[0:57, 63:69]  # every joint but the wrists stays the body fit's
    assert np.array_equal(fit.body_pose[:, others], bp.numpy()[:, others])


def test_limits_bound_flexion_spread_and_twist(anny):
    axes = H.joint_axes(anny)
    lo, hi = H.limit_bounds()
    relaxed = H.joint_components(anny.relaxed_hand_pose[None], axes)[0]
    assert bool(((relaxed >= lo) & (relaxed <= hi)).all())  # Anny's relaxed hand is a possible hand
    back = H.joint_components(-torch.as_tensor(finger_motion(1, hand_axes(anny), np.random.default_rng(0))), axes)
    fist = torch.as_tensor(finger_motion(40, hand_axes(anny), np.random.default_rng(0), frames_per_shape=8.0))
    comps = H.joint_components(fist, axes)
    assert bool(((comps >= lo - 1e-4) & (comps <= hi + 1e-4)).all())  # the synthetic shapes lie inside
    assert float(comps[..., 0].max()) > math.radians(70)  # ... and they include a fist
    assert bool((comps[..., 2].abs() < 1e-4).all())  # bends and spreads do not twist
    assert bool(((back < lo) | (back > hi)).any())  # fingers bent backwards are not


def test_a_lost_hand_holds_its_pose_then_eases_to_relaxed():
    times = np.arange(40) / 10.0  # 10 frames per second
    seen = np.zeros(40, bool)
    seen[:5] = True
    seen[35:] = True
    x = np.zeros((40, 2))
    x[:5], x[35:] = [1.0, 2.0], [3.0, 4.0]
    relaxed = np.array([-1.0, -1.0])
    out = H.fill_missing(x, seen, times, relaxed, hold=0.2, ease=0.5)
    np.testing.assert_array_equal(out[seen], x[seen])
    np.testing.assert_allclose(out[5], [1.0, 2.0], atol=0.2)  # just lost: nearly the last pose
    assert np.allclose(out[6], out[5], atol=0.15)
    np.testing.assert_allclose(out[12:28], np.broadcast_to(relaxed, (16, 2)), atol=0.05)  # long lost: relaxed
    np.testing.assert_allclose(out[34], [3.0, 4.0], atol=0.2)  # about to come back: nearly the next pose
    assert np.all(np.diff(out[4:13, 0]) <= 1e-9)  # easing, never overshooting
    # a short gap is interpolated between its ends
    seen_short = np.ones(10, bool)
    seen_short[4:6] = False
    y = np.linspace(0, 9, 10)[:, None]
    gappy = np.where(seen_short[:, None], y, 100.0)
    short = H.fill_missing(gappy, seen_short, np.arange(10) / 30.0, np.zeros(1), 0.2, 0.5)
    np.testing.assert_allclose(short[:, 0], y[:, 0])
    # a hand never seen is relaxed throughout
    np.testing.assert_array_equal(H.fill_missing(x, np.zeros(40, bool), times, relaxed, 0.2, 0.5),
                                  np.broadcast_to(relaxed, (40, 2)))


def test_the_fit_flags_the_frames_that_saw_each_hand_and_fills_the_others(anny):
    T = 30
    truth, go, bp, tr, kp, world, found = _scene(anny, T, seed=1, frames_per_shape=30.0)
    found[3:, 1] = False  # the right hand is lost after frame 2
    kp[3:, 1], world[3:, 1] = 0.0, 0.0
    fit = H.fit_hands(anny, go, bp, tr, kp, world, found, K, np.arange(T) / 30.0, H.HandFitConfig(iters=60))
    np.testing.assert_array_equal(fit.found, found)
    right = fit.hand_pose[:, 45:]
    np.testing.assert_allclose(right[3], right[2], atol=1e-6)  # held
    np.testing.assert_allclose(right[-1], anny.relaxed_hand_pose[45:].numpy(), atol=1e-6)  # then relaxed
    assert np.isnan(fit.bone_error[3:, 1]).all() and not np.isnan(fit.bone_error[:, 0]).any()
    # the right wrist turns back to the body fit's once the hand is gone
    np.testing.assert_allclose(fit.body_pose[-1, 60:63], bp[-1, 60:63].numpy(), atol=1e-5)


def test_low_pass_smooths_the_seen_frames_only():
    times = np.arange(12) / 30.0
    seen = np.ones(12, bool)
    seen[6] = False
    x = np.zeros((12, 1))
    x[3] = 1.0  # a one-frame spike
    x[6] = 50.0  # a frame not seen: neither smoothed nor smoothing the others
    out = H.low_pass(x, seen, times, sigma=1.0 / 30)
    assert out[3, 0] < 0.5 and out[2, 0] > 0.1 and out[4, 0] > 0.1
    assert out[6, 0] == 50.0 and out[7, 0] == 0.0  # frame 7 is beyond 3 sigma of the spike
    np.testing.assert_allclose(out[seen].sum(), x[seen].sum(), atol=0.05)  # moved about, not lost
    np.testing.assert_array_equal(H.low_pass(x, seen, times, sigma=0.0), x)


def test_each_hand_goes_to_the_nearest_pose_wrist():
    wrists = np.array([[700.0, 300.0], [400.0, 300.0]])  # the person's left wrist is on the image's right
    height = 900.0
    near_left, near_right = np.array([705.0, 310.0]), np.array([395.0, 290.0])
    assert H.match_hand([near_right, near_left], wrists, 0, height) == 1
    assert H.match_hand([near_right, near_left], wrists, 1, height) == 0
    # a hand nearer the other wrist is not this side's, even within reach
    between = np.array([560.0, 300.0])
    assert H.match_hand([between], wrists, 0, height) is None
    # nor one far from either wrist
    assert H.match_hand([np.array([700.0, 500.0])], wrists, 0, height) is None
    corner, size = H.crop_box(np.tile(np.array([[700.0, 300.0]]), (33, 1)), 0, height)
    assert size == pytest.approx(H.HAND_CROP * height) and np.allclose(corner + size / 2, [700.0, 300.0])


@pytest.fixture(scope="module")
def raised_hands_frame(anny):
    """A 640x640 frame of the synthetic subject's upper body, forearms raised; the true hand points
    [2,21,2] (pixels) and the person's height in pixels."""
    from scipy.spatial.transform import Rotation

    from rmavatar.data.synth.motion import look_at
    from rmavatar.data.synth.render import render
    from rmavatar.data.synth.subject import build_subject, garment_state

    bp = np.zeros((1, 69))
    bp[0, 3 * 15 + 2], bp[0, 3 * 16 + 2] = -1.2, 1.2
    bp[0, 3 * 17 + 1], bp[0, 3 * 18 + 1] = -2.0, 2.0
    bp[0, 3 * 19], bp[0, 3 * 20] = 1.0, 1.0  # the wrists turn the palms from each other
    # the left hand spread, the right one open (the synthetic subject's shapes)
    bend = torch.stack([torch.tensor(HAND_SHAPES[k][0]) for k in ("spread", "open")])[None]
    spread = torch.stack([torch.tensor(HAND_SHAPES[k][1]) for k in ("spread", "open")])[None]
    hand_pose = hand_pose_from_angles(torch.deg2rad(bend), torch.deg2rad(spread), hand_axes(anny)).numpy()
    zero = np.zeros((1, 3))
    verts = posed_vertices(anny, PoseSequence.from_arrays(zero, bp, zero, hand_pose)).numpy()[0]
    size, f, distance = 640, 700.0, 1.4
    K_frame = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.15, 0.2])
    viewmat = look_at(target + np.array([0.0, 0.0, distance]), target)
    image, _ = render(build_subject(anny, 0), verts, Rotation.from_rotvec(zero[0]).as_matrix(), garment_state(bp[0]),
                      K_frame, viewmat, size, size, ss=2)
    with torch.no_grad():
        pts = anny(None, torch.zeros(1, 3), torch.as_tensor(bp, dtype=torch.float32), torch.zeros(1, 3),
                   hand_pose=torch.as_tensor(hand_pose)).hand_points[0].double().numpy()
    cam = pts @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * f + size / 2
    height = float(anny.v_template[:, 1].max() - anny.v_template[:, 1].min()) * f / (distance + 0.2)
    return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8), uv.reshape(2, 21, 2), height


@pytest.mark.skipif(importlib.util.find_spec("mediapipe") is None, reason="needs mediapipe (rmavatar[capture])")
def test_mediapipe_finds_both_hands_on_a_rendered_frame(raised_hands_frame):
    from rmavatar.capture.detect import Detector

    image, truth, height = raised_hands_frame
    with Detector() as detect, H.HandDetector() as find_hands:
        person = detect.look(image)
        hands = find_hands(image, person.keypoints, person.visibility, height)
    assert hands.found.all()
    hand_px = np.linalg.norm(truth.max(1) - truth.min(1), axis=-1)  # [2] the diagonal of each hand's box
    error = np.linalg.norm(hands.keypoints - truth, axis=-1)  # [2,21], each hand on its own side
    assert (np.median(error, 1) < 0.1 * hand_px).all(), (np.median(error, 1), hand_px)
    assert np.abs(hands.world).max() < 0.2 and np.abs(hands.world).max() > 0.02  # metres, about the hand
