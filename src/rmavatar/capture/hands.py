"""Fingers for ``rmavatar capture``: MediaPipe's hand landmarks in each frame, fitted as hand poses.

Detection (:class:`HandDetector`): MediaPipe 0.10.21's hand solution (its palm detector and the full
hand landmark model, both inside the wheel) runs on a square crop around each hand, placed by the pose
landmarks capture already has (the knuckles of MediaPipe's pose), about a third of the person's height
across, on the frame written (not MediaPipe's working size), so that the hand fills the model's input
however small the person is in the frame. One tracker
per side in video mode: once a hand is found the palm detector no longer runs for it. A hand belongs to
the side whose pose wrist is nearest its own wrist (MediaPipe's handedness label assumes a mirrored
selfie and is not used); a hand whose wrist is far from the pose wrist, whose pose wrist MediaPipe
marks as hidden, or that is too small to read (MIN_HAND_PIXELS), is not found.

Fit (:func:`fit_hands`): the body's pose from the body fit stays; per frame the hand poses [90] (and a
small turn of each wrist) are fitted, all frames in one batch, so that the body's hand points
(:class:`HandChain`) match the landmarks: the directions of the hand's 20 bones against those of
MediaPipe's hand world landmarks (metric, relative: they say which way a finger points in depth), the
2D landmarks relative to the wrist (so an error of the body's wrist position does not bend the fingers),
a weak pull towards the body's relaxed hand, and anatomical limits (fingers bend towards the palm, hardly
sideways past their first joint; the thumb is freer). Then a low-pass over time on the frames that saw
the hand, and frames without it: the last (and next) good pose held for a moment, easing to the relaxed
hand when the hand stays lost (:func:`fill_missing`).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from rmavatar.body.base import FINGERS, HAND_JOINT_NAMES, HAND_POINT_NAMES, HAND_POSE_DIM, SMPL_PARENTS
from rmavatar.body.lbs import axis_angle_to_matrix, lbs, matrix_to_axis_angle

# MediaPipe pose landmarks of each hand (left = the person's left): wrist, pinky and index knuckles
POSE_HAND = ((15, 17, 19), (16, 18, 20))
HAND_CROP = 0.35  # side of the square crop around a hand, fraction of the person's height
CROP_PIXELS = 256  # the crop as MediaPipe sees it (its palm detector takes 192, its landmark model 224)
# A detected hand's wrist must lie this close to its side's pose wrist (fraction of the person's height;
# a hand is about 0.11 of it): MediaPipe's pose and hand wrists agree within a few hundredths.
WRIST_MATCH = 0.05
MIN_VISIBILITY = 0.5  # a pose wrist MediaPipe marks as this hidden or more: no hand looked for
# A hand whose landmarks span less than this (the diagonal of their box, pixels of the frame) is too
# small to read its fingers: not found. On real footage at 288x512 (hands of 14-28 pixels) the fit could
# not follow the landmarks (its 2D term 2-4 times the synthetic 1080-pixel clip's, whose hands span 80-90).
MIN_HAND_PIXELS = 32.0
# Parent of each of MediaPipe's 21 hand points (the bones of the direction term): the wrist, then per
# finger its three joints and tip, each hanging from the one before, the first from the wrist.
POINT_PARENTS = (-1,) + tuple(0 if k == 0 else 1 + 4 * f + k - 1 for f in range(5) for k in range(4))
# Joints of hand_pose's 15 (MANO order) by finger (FINGERS order) and joint 1..3: [5,3]
FINGER_JOINTS = tuple(tuple(HAND_JOINT_NAMES.index(f"{f}{k}") for k in (1, 2, 3)) for f in FINGERS)


@dataclass
class HandDetection:
    """One frame's hands, left then right: keypoints [2,21,2] pixels of the frame; world [2,21,3]
    MediaPipe's hand world landmarks (metres, relative to the hand, the crop's x right, y down, z away);
    found [2] bool. Rows of a hand not found are zeros."""

    keypoints: np.ndarray
    world: np.ndarray
    found: np.ndarray

    @classmethod
    def none(cls) -> "HandDetection":
        return cls(np.zeros((2, 21, 2), np.float32), np.zeros((2, 21, 3), np.float32), np.zeros(2, bool))


def crop_box(keypoints: np.ndarray, side: int, height: float) -> tuple[np.ndarray, float]:
    """Top-left corner (x, y) and side (pixels) of the square crop around hand ``side`` (0 left, 1
    right): centred on the pose's index and pinky knuckles (the middle of an open hand and of a fist),
    HAND_CROP of the person's ``height`` across."""
    _, pinky, index = keypoints[list(POSE_HAND[side])]
    size = HAND_CROP * height
    return (pinky + index) / 2 - size / 2, size


def match_hand(wrists: list[np.ndarray], pose_wrists: np.ndarray, side: int, height: float) -> int | None:
    """Which of the detected hands (their wrist pixels) is hand ``side``: the one nearest its pose wrist
    (pose_wrists [2,2], left then right), if within WRIST_MATCH of the height and no nearer to the other
    side's pose wrist; None if none is."""
    best, best_d = None, WRIST_MATCH * height
    for i, w in enumerate(wrists):
        own = float(np.linalg.norm(w - pose_wrists[side]))
        other = float(np.linalg.norm(w - pose_wrists[1 - side]))
        if own <= best_d and own <= other:
            best, best_d = i, own
    return best


def _hands_module():
    from rmavatar.capture.detect import protobuf_prototypes, quiet_native_stderr, require_mediapipe

    require_mediapipe()
    with quiet_native_stderr(), protobuf_prototypes():
        from mediapipe.python.solutions import hands
    return hands


class HandDetector:
    """MediaPipe's hand landmarks of the person's two hands, frame after frame (see the module
    docstring). Call it with each frame of the clip in order."""

    def __init__(self):
        hands = _hands_module()
        from rmavatar.capture.detect import quiet_native_stderr

        with quiet_native_stderr(), warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # protobuf 6 on MediaPipe's graph setup
            # a tracker per side follows one hand; when it follows the wrong one (both hands in a crop),
            # the image-mode instance looks at that crop afresh for both
            self._track = [hands.Hands(static_image_mode=False, max_num_hands=1, model_complexity=1)
                           for _ in range(2)]
            self._look = hands.Hands(static_image_mode=True, max_num_hands=2, model_complexity=1)
            blank = np.zeros((64, 64, 3), np.uint8)  # the first call starts the graphs, which log
            for graph in (*self._track, self._look):
                graph.process(blank)

    def close(self) -> None:
        for graph in (*self._track, self._look):
            graph.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __call__(self, image: np.ndarray, keypoints: np.ndarray, visibility: np.ndarray, height: float
                 ) -> HandDetection:
        """image uint8 RGB [H,W,3]; MediaPipe pose's keypoints [33,2] (pixels of ``image``) and
        visibility [33]; the person's height in pixels (sets the crops' size)."""
        out = HandDetection.none()
        pose_wrists = keypoints[[POSE_HAND[0][0], POSE_HAND[1][0]]]
        for side in (0, 1):
            if visibility[POSE_HAND[side][0]] < MIN_VISIBILITY:
                continue
            corner, size = crop_box(keypoints, side, height)
            centre = corner + size / 2
            if not (0 <= centre[0] < image.shape[1] and 0 <= centre[1] < image.shape[0]):
                continue  # the hand is out of view
            crop = _crop(image, corner, size)
            hands = self._landmarks(self._track[side], crop, corner, size)
            pick = match_hand([k[0] for k, _ in hands], pose_wrists, side, height)
            if pick is None and hands:
                hands = self._landmarks(self._look, crop, corner, size)
                pick = match_hand([k[0] for k, _ in hands], pose_wrists, side, height)
            if pick is not None and np.linalg.norm(np.ptp(hands[pick][0], axis=0)) >= MIN_HAND_PIXELS:
                out.keypoints[side], out.world[side] = hands[pick]
                out.found[side] = True
        if out.found.all() and np.linalg.norm(out.keypoints[0, 0] - out.keypoints[1, 0]) < 0.5 * WRIST_MATCH * height:
            # both sides took the same hand (MediaPipe's pose put both wrists on it): the nearer keeps it
            far = int(np.argmax(np.linalg.norm(out.keypoints[:, 0] - pose_wrists, axis=1)))
            out.keypoints[far], out.world[far], out.found[far] = 0, 0, False
        return out

    @staticmethod
    def _landmarks(graph, crop: np.ndarray, corner: np.ndarray, size: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each hand MediaPipe finds in ``crop``: (keypoints [21,2] in the frame's pixels, world [21,3])."""
        from rmavatar.capture.detect import quiet_native_stderr

        with quiet_native_stderr():
            r = graph.process(crop)
        if not r.multi_hand_landmarks:
            return []
        found = []
        for lm, world in zip(r.multi_hand_landmarks, r.multi_hand_world_landmarks):
            uv = np.array([(p.x, p.y) for p in lm.landmark], np.float32) * size + corner
            xyz = np.array([(p.x, p.y, p.z) for p in world.landmark], np.float32)
            found.append((uv.astype(np.float32), xyz))
        return found


def _crop(image: np.ndarray, corner: np.ndarray, size: float) -> np.ndarray:
    """The square of ``image`` at ``corner`` with side ``size`` pixels, as CROP_PIXELS x CROP_PIXELS (black
    outside the frame)."""
    import cv2

    s = CROP_PIXELS / size
    M = np.array([[s, 0.0, -s * corner[0]], [0.0, s, -s * corner[1]]])
    return cv2.warpAffine(np.ascontiguousarray(image), M, (CROP_PIXELS, CROP_PIXELS), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))


# --- the body's hands ------------------------------------------------------------------------------

class HandChain:
    """The body's 42 hand points (MediaPipe's order, :data:`HAND_POINT_NAMES`) for hand poses, with the
    rest of the body posed; ``error``: the largest distance (metres) from the body's own hand points on a
    few random poses (Anny: 2e-6 m).

    Each finger's first joint rides on the wrist (its metacarpal turns with the wrist), each further
    point on the joint before it; a joint's rotation composes on its parent's in the body's tree: the
    thumb's on the wrist, the other fingers' on SMPL's hand joint (22 / 23) in Anny, on the wrist in
    SMPL-H and SMPL-X (which have no such joint). The offsets between the points are the body's own at
    rest (zero pose, flat hands; shape ``betas`` [1,nb] or None)."""

    def __init__(self, body, betas: torch.Tensor | None = None):
        dev = body.v_template.device
        zero = torch.zeros(1, 3, device=dev)
        flat = torch.zeros(1, HAND_POSE_DIM, device=dev)
        with torch.no_grad():
            rest = body(betas, zero, torch.zeros(1, 69, device=dev), zero, hand_pose=flat)
            if rest.hand_points is None:
                raise ValueError(f"the body {getattr(body, 'spec', '?')} has no fingers")
            bent = torch.zeros(1, 69, device=dev)
            bent[0, 3 * 21] = 0.5  # SMPL's left hand joint (22)
            moved = body(betas, zero, bent, zero, hand_pose=flat).hand_points
        self.hand_joint = bool((moved - rest.hand_points).norm(dim=-1).max() > 1e-4)
        self.rest_joints = rest.joints  # [1,24,3]
        points = rest.hand_points[0].reshape(2, 21, 3)
        # per hand and finger: the offsets wrist -> joint 1 -> 2 -> 3 -> tip, [2,5,4,3]
        chain = points[:, 1:].reshape(2, 5, 4, 3)
        before = torch.cat([points[:, :1, None].expand(-1, 5, -1, -1), chain[:, :, :3]], 2)
        self.offsets = chain - before
        relaxed = getattr(body, "relaxed_hand_pose", None)
        self.relaxed = torch.zeros(HAND_POSE_DIM, device=dev) if relaxed is None else relaxed.detach().clone()
        self.length = float((points[:, HAND_POINT_NAMES.index("middle_tip")] - points[:, 0]).norm(dim=-1).mean())
        self.error = self._check(body, betas)

    @torch.no_grad()
    def _check(self, body, betas, count: int = 4) -> float:
        """The largest distance (metres) between these points and the body's on random poses."""
        g = torch.Generator().manual_seed(0)
        dev = self.rest_joints.device
        go, bp, tr, hp = (s * torch.randn(count, n, generator=g).to(dev)
                          for s, n in ((0.5, 3), (0.4, 69), (1.0, 3), (0.4, 90)))
        b = None if betas is None else betas.expand(count, -1)
        truth = body(b, go, bp, tr, hand_pose=hp).hand_points.reshape(count, 2, 21, 3)
        return float((self.points(hp, *self.body_frames(go, bp, tr)) - truth).norm(dim=-1).max())

    def body_frames(self, global_orient: torch.Tensor, body_pose: torch.Tensor, transl: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """From the body's pose [T,3], [T,69], [T,3]: the elbows' world rotations [T,2,3,3], the wrists'
        and hand joints' local rotations [T,2,3,3] each, and the wrists' positions [T,2,3]."""
        T = global_orient.shape[0]
        local = axis_angle_to_matrix(torch.cat([global_orient, body_pose], 1).reshape(T, 24, 3))
        _, joints, transforms = lbs(self.rest_joints[:, :1], self.rest_joints, SMPL_PARENTS, local,
                                    torch.zeros(1, 24, device=local.device))
        G = transforms[..., :3, :3]
        return G[:, 18:20], local[:, 20:22], local[:, 22:24], joints[:, 20:22] + transl[:, None]

    def points(self, hand_pose: torch.Tensor, elbow: torch.Tensor, wrist_local: torch.Tensor,
               hand_local: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
        """Hand points [T,2,21,3] for hand_pose [T,90] and the body's frames (:meth:`body_frames`; a
        wrist turn is applied to ``wrist_local`` before)."""
        T = hand_pose.shape[0]
        R = axis_angle_to_matrix(hand_pose.reshape(T, 2, 15, 3))
        R = R[:, :, torch.tensor(FINGER_JOINTS, device=R.device)]  # [T,2,5,3,3,3]
        G_wrist = elbow @ wrist_local
        G_hand = G_wrist @ hand_local if self.hand_joint else G_wrist
        parent = torch.stack([G_wrist] + [G_hand] * 4, 2)  # [T,2,5,3,3]: the thumb hangs from the wrist
        G1 = parent @ R[:, :, :, 0]
        G2 = G1 @ R[:, :, :, 1]
        G3 = G2 @ R[:, :, :, 2]
        frames = torch.stack([G_wrist[:, :, None].expand_as(G1), G1, G2, G3], 3)  # [T,2,5,4,3,3]
        steps = (frames @ self.offsets[..., None])[..., 0]  # [T,2,5,4,3]
        chain = wrist[:, :, None, None] + steps.cumsum(3)
        return torch.cat([wrist[:, :, None], chain.reshape(T, 2, 20, 3)], 2)


# --- limits ------------------------------------------------------------------------------------------

# Per finger's joints 1-3: degrees (low, high) of flexion (towards the palm), spread (in the palm's plane,
# away from the middle finger) and twist (about the bone). Generous: they forbid a finger bending
# backwards or sideways past what a hand can do; Anny's relaxed hand and a fist lie well inside.
FINGER_LIMITS = (((-25, 100), (-30, 30), (-20, 20)), ((-10, 115), (-10, 10), (-10, 10)),
                 ((-10, 95), (-10, 10), (-10, 10)))  # fmt: skip
THUMB_LIMITS = (((-40, 90), (-50, 60), (-45, 45)), ((-30, 80), (-25, 25), (-25, 25)),
                ((-20, 95), (-20, 20), (-20, 20)))  # fmt: skip


def joint_axes(body) -> torch.Tensor:
    """[2,5,3,3]: per hand and finger the unit axes of flexion, spread and twist (rows), from the body's
    flat hand (:func:`rmavatar.body.hands.hand_axes`); a hand pose's axis-angle components along them
    are what :data:`FINGER_LIMITS` bound."""
    from rmavatar.body.hands import hand_axes

    axes = hand_axes(body)
    side = torch.tensor([[1.0, 1.0, 1.0, -1.0, -1.0], [-1.0, -1.0, -1.0, 1.0, 1.0]])
    spread = side[..., None] * axes.palm[:, None]
    palm = axes.palm[:, None].expand_as(axes.flexion)
    twist = torch.nn.functional.normalize(torch.linalg.cross(palm, axes.flexion), dim=-1)
    return torch.stack([axes.flexion, spread, twist], 2).to(body.v_template.device)


def limit_bounds(device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Low and high bounds [5,3,3] (finger, joint, axis) in radians."""
    table = torch.tensor([THUMB_LIMITS] + [FINGER_LIMITS] * 4, dtype=torch.float32) * (math.pi / 180)
    return table[..., 0].to(device), table[..., 1].to(device)


def joint_components(hand_pose: torch.Tensor, axes: torch.Tensor) -> torch.Tensor:
    """hand_pose [T,90] -> [T,2,5,3,3]: per hand, finger and joint its flexion, spread and twist."""
    r = hand_pose.reshape(-1, 2, 15, 3)[:, :, torch.tensor(FINGER_JOINTS, device=hand_pose.device)]
    return torch.einsum("thfjx,hfcx->thfjc", r, axes)


# --- the fit -----------------------------------------------------------------------------------------

@dataclass
class HandFitConfig:
    """Weights and schedule of the hand fit, and how frames without a hand are filled. The measurements
    behind the defaults: docs/capture.md, "Hands"."""

    iters: int = 100  # Adam iterations (all frames at once; 80 and 300 fitted the synthetic clip alike)
    lr: float = 0.05  # Adam's learning rate (cosine decay to 5% of it)
    directions: float = 1.0  # the hand's bone directions against MediaPipe's hand world landmarks
    keypoints: float = 1.0  # the 2D landmarks relative to the wrist
    sigma: float = 0.1  # Geman-McClure scale of the 2D residuals, fraction of the hand's length
    # pull towards the body's relaxed hand (radians squared). MediaPipe's finger landmarks are noisy
    # (their bones 26 degrees off on the synthetic clip): 0.03 cut the joints' error there from 19.1
    # (0.002) to 16.7 degrees; 0.1 pulled the fingers back towards relaxed (18.1, the bones 28 against 24)
    prior: float = 0.03
    # each joint's twist about its bone (radians squared): points cannot see it (a fingertip turning
    # about its own axis moves no landmark), and finger joints are hinges
    twist: float = 1.0
    limits: float = 10.0  # squared excess past FINGER_LIMITS / THUMB_LIMITS
    # pull of the wrist's turn back to the body fit's wrist (radians squared). The body fit's wrists were
    # 30 degrees off on the synthetic clip: 0.1 let the palms bring them to 6-11, 0.5 to 13-18
    wrist: float = 0.1
    smooth: float = 0.03  # seconds: Gaussian low-pass over the frames that saw the hand (0: none)
    hold: float = 0.2  # seconds a lost hand keeps its last pose
    ease: float = 0.5  # seconds over which it then turns into the relaxed hand


@dataclass
class HandFit:
    """hand_pose [T,90] and found [T,2] (numpy), body_pose [T,69] with the wrists turned as the hands
    asked, the final loss terms, per frame and hand the mean angle (degrees) between the body's bones
    and MediaPipe's (``bone_error`` [T,2], NaN where the hand was not found), the seconds it took."""

    hand_pose: np.ndarray
    found: np.ndarray
    body_pose: np.ndarray
    losses: dict = field(default_factory=dict)
    bone_error: np.ndarray | None = None
    seconds: float = 0.0


def camera_world(world: torch.Tensor, keypoints: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """MediaPipe's hand world landmarks [...,21,3] turned into the camera's frame: they are as seen along
    the ray through the hand (the crop is a view of the hand alone), here the ray through the wrist's
    pixel keypoints [...,21,2]."""
    ray = torch.stack([(keypoints[..., 0, 0] - K[0, 2]) / K[0, 0], (keypoints[..., 0, 1] - K[1, 2]) / K[1, 1],
                       torch.ones_like(keypoints[..., 0, 0])], -1)
    ray = torch.nn.functional.normalize(ray, dim=-1)
    z = torch.zeros_like(ray)
    z[..., 2] = 1.0
    axis = torch.linalg.cross(z, ray)  # |axis| = sin of the angle off the optical axis
    angle = torch.atan2(axis.norm(dim=-1), ray[..., 2])
    rot = axis_angle_to_matrix(torch.nn.functional.normalize(axis, dim=-1) * angle[..., None])
    return world @ rot.transpose(-1, -2)


def _bones(points: torch.Tensor) -> torch.Tensor:
    """Unit directions [...,20,3] of the hand's bones (POINT_PARENTS) from points [...,21,3]."""
    parents = list(POINT_PARENTS[1:])
    return torch.nn.functional.normalize(points[..., 1:, :] - points[..., parents, :], dim=-1)


def _terms(chain: HandChain, cfg: HandFitConfig, hand_pose, turn, frames, obs, K, axes, bounds) -> dict:
    """Per frame and hand [T,2], the weighted terms (see the module docstring)."""
    from rmavatar.capture.fit import geman_mcclure, project

    elbow, wrist_local, hand_local, wrist = frames
    keypoints, world = obs
    pts = chain.points(hand_pose, elbow, wrist_local @ axis_angle_to_matrix(turn), hand_local, wrist)
    uv = project(pts, K)
    hand_px = K[0, 0] * chain.length / pts[..., 0, 2].detach().clamp_min(0.05)  # the hand's length in pixels
    rel = (uv[..., 1:, :] - uv[..., :1, :]) - (keypoints[..., 1:, :] - keypoints[..., :1, :])
    r2 = (rel / hand_px[..., None, None]).pow(2).sum(-1)
    comps = joint_components(hand_pose, axes)
    excess = torch.relu(comps - bounds[1]) + torch.relu(bounds[0] - comps)
    offset = hand_pose.reshape(-1, 2, 45) - chain.relaxed.reshape(2, 45)
    return {
        "directions": cfg.directions * (_bones(pts) - _bones(world)).pow(2).sum(-1).mean(-1),
        "keypoints": cfg.keypoints * geman_mcclure(r2, cfg.sigma).mean(-1),
        "prior": cfg.prior * offset.pow(2).sum(-1),
        "limits": cfg.limits * excess.pow(2).sum((-1, -2, -3)),
        "twist": cfg.twist * comps[..., 2].pow(2).sum((-1, -2)),
        "wrist": cfg.wrist * turn.pow(2).sum(-1),
    }


@contextlib.contextmanager
def _one_thread(device):
    """One torch thread on the CPU while the hands are fitted: their tensors hold a few thousand numbers,
    and a second thread only adds waiting (on the 2-core machine, 48 frames: 0.8 s with one thread,
    13 s with two under load)."""
    if device.type != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def fit_hands(body, global_orient, body_pose, transl, keypoints, world, found, K, times,
              cfg: HandFitConfig | None = None, betas=None) -> HandFit:
    """Fit the hand poses of T frames (arrays or tensors): the body's fitted pose ([T,3], [T,69], [T,3],
    camera frame; shape ``betas`` [nb] or None), the hand landmarks (keypoints [T,2,21,2] pixels, world
    [T,2,21,3], found [T,2]), the camera K [3,3], each frame's time in seconds [T]. Frames without a hand
    are filled (:func:`fill_missing`); see the module docstring."""
    import time

    start = time.perf_counter()
    cfg = cfg or HandFitConfig()
    dev = body.v_template.device
    t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=dev)  # noqa: E731
    with _one_thread(dev):
        chain = HandChain(body, None if betas is None else t(betas)[None])
        K = t(K)
        with torch.no_grad():
            frames = chain.body_frames(t(global_orient), t(body_pose), t(transl))
            obs = (t(keypoints), camera_world(t(world), t(keypoints), K))
        hand_pose, turn, losses, error = _optimise(chain, cfg, frames, obs, t(found), K, joint_axes(body))
        wrist_local = frames[1]
    seen = np.asarray(found, bool)
    times = np.asarray(times, np.float64)
    relaxed = chain.relaxed.cpu().numpy().reshape(2, 45)
    pose, turns = hand_pose.reshape(-1, 2, 45), turn
    for h in (0, 1):  # low-passed over the frames that saw the hand, then the others filled
        pose[:, h] = fill_missing(low_pass(pose[:, h], seen[:, h], times, cfg.smooth), seen[:, h], times,
                                  relaxed[h], cfg.hold, cfg.ease)
        turns[:, h] = fill_missing(low_pass(turns[:, h], seen[:, h], times, cfg.smooth), seen[:, h], times,
                                   np.zeros(3), cfg.hold, cfg.ease)
    out_pose = t(body_pose).cpu().numpy().copy()
    wrists = matrix_to_axis_angle(wrist_local @ axis_angle_to_matrix(torch.as_tensor(turns, device=dev)))
    out_pose[:, 3 * 19:3 * 21] = wrists.reshape(-1, 6).cpu().numpy()  # SMPL joints 20, 21
    return HandFit(pose.reshape(-1, HAND_POSE_DIM).astype(np.float32), seen.copy(), out_pose, losses,
                   np.where(seen, error, np.nan), time.perf_counter() - start)


def _optimise(chain: HandChain, cfg: HandFitConfig, frames, obs, found: torch.Tensor, K: torch.Tensor,
              axes: torch.Tensor) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """Adam on every frame's hand pose and wrist turns at once, from the relaxed hands. Returns hand
    poses [T,90], wrist turns [T,2,3] (axis-angle, applied after the body's wrists), the final terms and
    per frame and hand the mean angle between the body's bones and MediaPipe's (degrees)."""
    T = found.shape[0]
    dev = found.device
    bounds = limit_bounds(dev)
    hand_pose = chain.relaxed.expand(T, -1).clone().requires_grad_(True)
    turn = torch.zeros(T, 2, 3, device=dev, requires_grad=True)
    opt = torch.optim.Adam([hand_pose, turn], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(cfg.iters, 1), eta_min=cfg.lr * 0.05)
    weight = found / found.sum().clamp_min(1.0)  # a hand not seen has no say
    terms = {}
    for _ in range(cfg.iters):  # each frame's hands depend on their own parameters only: Adam treats them alike
        opt.zero_grad(set_to_none=True)
        terms = _terms(chain, cfg, hand_pose, turn, frames, obs, K, axes, bounds)
        sum((weight * v).sum() for v in terms.values()).backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        pts = chain.points(hand_pose, frames[0], frames[1] @ axis_angle_to_matrix(turn), frames[2], frames[3])
        cos = (_bones(pts) * _bones(obs[1])).sum(-1).clamp(-1, 1)
        error = torch.rad2deg(torch.acos(cos)).mean(-1).cpu().numpy()
    losses = {k: float((weight * v.detach()).sum()) for k, v in terms.items()}
    return hand_pose.detach().cpu().numpy(), turn.detach().cpu().numpy(), losses, error


# --- over time ---------------------------------------------------------------------------------------

def low_pass(x: np.ndarray, seen: np.ndarray, times: np.ndarray, sigma: float) -> np.ndarray:
    """x [T,D] at the frames ``seen`` [T] replaced by its Gaussian-weighted mean (``sigma`` seconds) over
    the seen frames near them (``times`` [T] seconds); the other rows unchanged."""
    out = np.array(x, copy=True)
    if sigma <= 0:
        return out
    idx = np.nonzero(seen)[0]
    t, rows = times[idx], np.asarray(x, np.float64)[idx]
    for k, i in enumerate(idx):  # the seen frames within 3 sigma of frame i
        lo, hi = np.searchsorted(t, t[k] - 3 * sigma), np.searchsorted(t, t[k] + 3 * sigma, side="right")
        w = np.exp(-0.5 * ((t[lo:hi] - t[k]) / sigma) ** 2)
        out[i] = w @ rows[lo:hi] / w.sum()
    return out


def fill_missing(x: np.ndarray, seen: np.ndarray, times: np.ndarray, relaxed: np.ndarray, hold: float,
                 ease: float) -> np.ndarray:
    """x [T,D] with the rows not ``seen`` filled: from the last seen frame, its row held for ``hold``
    seconds, then eased (smoothstep) into ``relaxed`` [D] over ``ease`` seconds; the same backwards from
    the next seen frame; between two seen frames the two cross-fade linearly in time (a short gap is
    interpolated, a long one holds, relaxes and comes back). No seen frame at all: ``relaxed``."""
    x = np.array(x, copy=True)
    idx = np.nonzero(seen)[0]
    if len(idx) == 0:
        x[:] = relaxed
        return x

    def held(row, gap):
        s = np.clip((gap - hold) / max(ease, 1e-9), 0.0, 1.0)
        s = s * s * (3 - 2 * s)
        return (1 - s) * row + s * relaxed

    for i in np.nonzero(~seen)[0]:
        k = np.searchsorted(idx, i)
        last, nxt = (idx[k - 1] if k > 0 else None), (idx[k] if k < len(idx) else None)
        if last is not None and nxt is not None:
            a, b = times[i] - times[last], times[nxt] - times[i]
            x[i] = (b * held(x[last], a) + a * held(x[nxt], b)) / max(a + b, 1e-9)
        elif last is not None:
            x[i] = held(x[last], times[i] - times[last])
        else:
            x[i] = held(x[nxt], times[nxt] - times[i])
    return x


__all__ = ["HandDetector", "HandDetection", "HandChain", "HandFitConfig", "HandFit", "fit_hands", "fill_missing",
           "low_pass", "match_hand", "crop_box"]
