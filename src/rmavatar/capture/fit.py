"""Fitting SMPL-format body parameters to MediaPipe's landmarks and masks, batched over all frames.

The camera is static and pinhole (K), at the origin looking along +z (OpenCV axes); the parameters
live in its frame. Unknowns: per frame global_orient [T,3], body_pose [T,69], transl [T,3]; one shape
for the clip (SMPL betas; Anny's shape is its preset). The objective, all residuals in units of the
person's height in the image so that weights do not depend on the resolution:

- keypoints: Geman-McClure of the 2D reprojection error of the body's landmark points
  (:mod:`rmavatar.capture.landmarks`: joints plus measured offsets) against MediaPipe's landmarks,
  weighted by :func:`visibility_weight` (landmarks MediaPipe marks as hidden count for nothing);
- directions: the body's 3D bone directions against those of MediaPipe's world landmarks (resolves
  what 2D cannot: which way a limb points in depth), weighted by the smaller weight of its two ends;
- silhouette: surface points of the body that project outside the person mask, by their squared
  distance to the mask (the body must lie inside the clothed silhouette);
- outline: the mask's outline pixels by their distance to the nearest projected surface point, robust
  (the converse of the silhouette term: a limb may not slide inside a wider mask; loose clothes and
  hair, whose outline lies far from the body, saturate the robust cost instead of inflating the body);
- limits: joint angles past anatomical limits (a box on each joint's axis-angle components);
- prior: a weak pull of body_pose towards a relaxed A-pose, and of SMPL betas towards zero;
- smooth: acceleration of the landmark points (body heights per frame^2; robust, squared with --still)
  and squared acceleration of body_pose;
- hold and up (off unless asked for, ``--still``): squared distance of each frame's body_pose, and of
  its up direction (the pelvis' y axis in the camera frame), from the clip's mean, for a person who
  holds one pose while turning on the spot.

The global rotation is optimised as a residual on its initial value (R = R0 exp(d)), so a person
seen upright (about 180 degrees from the camera's y-down axes) is no singularity.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from rmavatar.body.lbs import axis_angle_to_matrix, matrix_to_axis_angle
from rmavatar.capture.landmarks import BONES, USED, body_landmarks
from rmavatar.capture.proxy import BodyProxy

# body_pose index of SMPL joint j's three values is 3 * (j - 1).
# Anatomical limits per SMPL joint, radians, on the axis-angle components (x = the body's left, y up,
# z forward in the T-pose): generous boxes that forbid what a body cannot do (knees and elbows bending
# backwards or sideways, heads turned round) without biasing ordinary poses.
LIMITS: dict[int, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    1: ((-2.1, 0.6), (-0.8, 0.8), (-0.5, 1.2)),  # left hip: flexion is -x, abduction +z
    2: ((-2.1, 0.6), (-0.8, 0.8), (-1.2, 0.5)),  # right hip
    3: ((-0.4, 0.8), (-0.5, 0.5), (-0.4, 0.4)),  # spine1
    4: ((-0.05, 2.5), (-0.3, 0.3), (-0.15, 0.15)),  # left knee: flexion is +x only
    5: ((-0.05, 2.5), (-0.3, 0.3), (-0.15, 0.15)),  # right knee
    6: ((-0.4, 0.8), (-0.5, 0.5), (-0.4, 0.4)),  # spine2
    7: ((-0.8, 0.8), (-0.5, 0.5), (-0.5, 0.5)),  # left ankle
    8: ((-0.8, 0.8), (-0.5, 0.5), (-0.5, 0.5)),  # right ankle
    9: ((-0.4, 0.8), (-0.5, 0.5), (-0.4, 0.4)),  # spine3
    10: ((-0.6, 0.6), (-0.2, 0.2), (-0.2, 0.2)),  # left foot (toes)
    11: ((-0.6, 0.6), (-0.2, 0.2), (-0.2, 0.2)),  # right foot
    12: ((-0.6, 0.8), (-0.8, 0.8), (-0.5, 0.5)),  # neck
    13: ((-0.4, 0.4), (-0.5, 0.5), (-0.4, 0.6)),  # left collar
    14: ((-0.4, 0.4), (-0.5, 0.5), (-0.6, 0.4)),  # right collar
    15: ((-0.6, 0.8), (-0.8, 0.8), (-0.5, 0.5)),  # head
    16: ((-1.6, 1.6), (-1.7, 1.2), (-1.7, 1.7)),  # left shoulder: arm along +x
    17: ((-1.6, 1.6), (-1.2, 1.7), (-1.7, 1.7)),  # right shoulder
    18: ((-1.5, 1.5), (-2.7, 0.1), (-0.25, 0.25)),  # left elbow: flexion is -y only
    19: ((-1.5, 1.5), (-0.1, 2.7), (-0.25, 0.25)),  # right elbow: flexion is +y only
    20: ((-1.0, 1.0), (-0.8, 0.8), (-1.2, 1.2)),  # left wrist
    21: ((-1.0, 1.0), (-0.8, 0.8), (-1.2, 1.2)),  # right wrist
    22: ((-0.5, 0.5), (-0.5, 0.5), (-0.8, 0.8)),  # left hand
    23: ((-0.5, 0.5), (-0.5, 0.5), (-0.8, 0.8)),  # right hand
}

# The relaxed standing pose the prior pulls towards and the fit starts from: arms lowered 60 degrees
# from the T-pose, elbows slightly bent.
A_POSE_SHOULDER = 1.05
A_POSE_ELBOW = 0.15


# The --still settings' measurements: docs/capture.md, "Why the fit's defaults".
# hold_pose for a person who holds one pose (``rmavatar capture --still``): the recommended recording, a
# turn in a held A-pose, where MediaPipe's errors wander with the facing angle but the pose does not.
# It cuts the synthetic turn's joint-angle error (heavier holds keep the mean pose's own bias); on a
# walking clip it flattens the legs, hence not the default.
STILL_HOLD_POSE = 1.0
# hold_up for the same recording: a person turning on the spot stays upright, so the pelvis' up axis
# hardly moves in a static camera's frame, while MediaPipe's 3D landmarks tilt it in side views (depth,
# which the 2D landmarks cannot correct). 10 cuts the synthetic turn's global rotation error.
STILL_HOLD_UP = 10.0
# keypoints for the same recording. Fitted from its true pose, the synthetic turn's body settles where
# the MediaPipe landmarks pull it (their errors wander with the facing angle and do not average out;
# recalibrating their offsets on that very clip does not help), while a held pose's outline, seen from
# every side, is evidence no wrong pose fits. 0.3 (the masks' terms at 20 and 1 as before) cuts the
# turn's visible-vertex error on its training frames and test tail; on walking clips a lower weight did
# not help, hence only with --still.
STILL_KEYPOINTS = 0.3


def rest_pose(dtype=torch.float32, device=None) -> torch.Tensor:
    """The A-pose body_pose [69]."""
    p = torch.zeros(69, dtype=dtype, device=device)
    p[3 * 15 + 2], p[3 * 16 + 2] = -A_POSE_SHOULDER, A_POSE_SHOULDER  # shoulders 16, 17 about z
    p[3 * 17 + 1], p[3 * 18 + 1] = -A_POSE_ELBOW, A_POSE_ELBOW  # elbows 18, 19 about y
    return p


def limit_bounds(dtype=torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds [69] of body_pose from LIMITS."""
    lo = torch.empty(23, 3, dtype=dtype)
    hi = torch.empty(23, 3, dtype=dtype)
    for j, axes in LIMITS.items():
        for a, (low, high) in enumerate(axes):
            lo[j - 1, a], hi[j - 1, a] = low, high
    return lo.reshape(69).to(device), hi.reshape(69).to(device)


@dataclass
class BodyFitConfig:
    """Weights and schedule of the fit (see the module docstring for the terms)."""

    # The measurements behind these defaults: docs/capture.md, "Why the fit's defaults".
    iters: int = 400  # full fit (all terms), after the start below
    start_iters: int = 100  # global rotation, translation and pose from keypoints and directions only
    lr: float = 0.02  # Adam's learning rate at the start of each stage (cosine decay to 5% of it)
    sigma: float = 0.03  # Geman-McClure scale of the keypoint residuals, fraction of the person's height
    min_visibility: float = 0.5  # landmarks at or below this visibility are ignored (see visibility_weight)
    keypoints: float = 1.0  # weight of the 2D landmark term (STILL_KEYPOINTS with --still)
    directions: float = 0.05  # weight of the 3D bone directions against MediaPipe's world landmarks
    # weight of the body-inside-the-mask term. 20 (was 2, before the masks were refined): better global
    # rotation and 2D joints on the synthetic turn, walking a little better in 2D; 50 made walking worse
    silhouette: float = 20.0
    # the mask's outline pixels drawn to the body's projected surface (0: off); 1 cut the synthetic
    # turn's visible-vertex and 3D joint errors (--still) and the walking clip's 2D error
    outline: float = 1.0
    outline_sigma: float = 0.01  # its Geman-McClure scale, fraction of the person's height
    outline_every: int = 10  # iterations between searches for each outline pixel's nearest point
    limits: float = 10.0  # weight of the joint angles' excess past LIMITS
    prior: float = 0.002  # weight of body_pose's pull towards the A-pose (rest_pose)
    shape_prior: float = 0.01  # weight of SMPL betas' pull towards zero (unused for Anny)
    smooth: float = 10.0  # landmark points' acceleration (person heights per frame^2)
    # Geman-McClure scale of each landmark's acceleration (person heights per frame^2; 0: squared, as in
    # --still). Squared, a walking clip's fast swings of the legs cost so much that the fit gave up the
    # keypoints for them (the first frame's legs collapsed onto each other); robust at 0.02 the walking
    # clips of three synthetic subjects fit better in 2D and 3D; other scales gained less.
    smooth_sigma: float = 0.02
    # body_pose's acceleration (rad per frame^2). MediaPipe's evidence for the feet, hands and head is
    # weak and its errors wander with the facing angle; 5 (was 0.05) cut the fitted body's joint-angle
    # error on the synthetic turn and the walking clip; 50 smooths walking legs away.
    smooth_pose: float = 5.0
    hold_pose: float = 0.0  # body_pose's pull towards the clip's mean: 0, or STILL_HOLD_POSE (--still)
    hold_up: float = 0.0  # the pelvis' up axis' pull towards the clip's mean: 0, or STILL_HOLD_UP (--still)
    point_spacing: float = 0.04  # metres between the surface points of the silhouette term

    def still(self) -> "BodyFitConfig":
        """A copy for a person who holds one pose while turning on the spot (``--still``). Nothing of a
        held pose moves fast, so a large acceleration is MediaPipe's error, and the smoothness stays
        squared to suppress it (robust cost the synthetic turn's test frames a little, docs/capture.md);
        the keypoints weigh less against the masks (STILL_KEYPOINTS)."""
        return replace(self, hold_pose=STILL_HOLD_POSE, hold_up=STILL_HOLD_UP, smooth_sigma=0.0,
                       keypoints=STILL_KEYPOINTS)


@dataclass
class Observations:
    """What the fit sees, as tensors on one device (T frames, K = len(USED) landmarks).

    keypoints [T,K,2] pixels; visibility [T,K]; world [T,K,3] MediaPipe world landmarks (camera axes,
    metres); outside [T,h,w] distance (pixels of the full image) from each pixel to the person mask
    at a reduced resolution; K [3,3] the camera; size (width, height) of the full image;
    gaps [T-1] source-frame distance between consecutive kept frames; height_px the person's height
    in the image (pixels), the unit of every residual; outline [T,B,2] pixels on the mask's outline
    (padded) and outline_weight [T,B] (1 for a pixel, 0 for padding), or None: no outline term
    (:func:`mask_outline` makes them).
    """

    keypoints: torch.Tensor
    visibility: torch.Tensor
    world: torch.Tensor
    outside: torch.Tensor
    K: torch.Tensor
    size: tuple[int, int]
    gaps: torch.Tensor
    height_px: float
    outline: torch.Tensor | None = None
    outline_weight: torch.Tensor | None = None


@dataclass
class FitResult:
    """Fitted parameters (numpy float32, camera frame): global_orient [T,3], body_pose [T,69],
    transl [T,3], betas [10] (zeros for Anny); the final loss terms; seconds."""

    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray
    losses: dict = field(default_factory=dict)
    seconds: float = 0.0


# --- the terms (plain functions on tensors) ------------------------------------------------------

def project(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame points [...,3] -> pixels [...,2] (depth clamped to >= 1 cm)."""
    z = points[..., 2:].clamp_min(0.01)
    return points[..., :2] / z * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]


def geman_mcclure(r2: torch.Tensor, sigma: float) -> torch.Tensor:
    """rho(r) = r^2 / (r^2 + sigma^2) from squared residuals (saturates at 1 for outliers)."""
    return r2 / (r2 + sigma * sigma)


def visibility_weight(visibility: torch.Tensor, floor: float) -> torch.Tensor:
    """A landmark's weight from MediaPipe's visibility: 0 at or below ``floor`` (a guess for a hidden
    limb, often placed on the near one), rising as the square to 1 at visibility 1."""
    return ((visibility - floor) / (1.0 - floor)).clamp(0.0, 1.0).pow(2)


def keypoint_term(uv: torch.Tensor, keypoints: torch.Tensor, weights: torch.Tensor, height_px: float,
                  sigma: float) -> torch.Tensor:
    """Mean over frames of sum_k w rho(|uv - keypoint| / height) / sum_k w; uv, keypoints [T,K,2],
    weights [T,K]."""
    r2 = ((uv - keypoints) / height_px).pow(2).sum(-1)
    return ((weights * geman_mcclure(r2, sigma)).sum(1) / weights.sum(1).clamp_min(1e-6)).mean()


def direction_term(points: torch.Tensor, world: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Squared difference of the unit directions of BONES between the body's points [T,K,3] and
    MediaPipe's world landmarks [T,K,3], weighted by the smaller weight [T,K] of the two ends."""
    pos = {k: i for i, k in enumerate(USED)}
    a = torch.tensor([pos[i] for i, _ in BONES], device=points.device)
    b = torch.tensor([pos[j] for _, j in BONES], device=points.device)
    d_body = torch.nn.functional.normalize(points[:, b] - points[:, a], dim=-1)
    d_seen = torch.nn.functional.normalize(world[:, b] - world[:, a], dim=-1)
    w = torch.minimum(weights[:, a], weights[:, b])
    return ((w * (d_body - d_seen).pow(2).sum(-1)).sum(1) / w.sum(1).clamp_min(1e-6)).mean()


def sample_map(maps: torch.Tensor, uv: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear samples of per-frame maps [T,h,w] (covering the full image of ``size`` = (W,H)) at
    full-image pixel positions uv [T,P,2] (pixel centres at +0.5); outside the image: the border."""
    W, H = size
    grid = torch.stack([uv[..., 0] / W * 2 - 1, uv[..., 1] / H * 2 - 1], -1)[:, None]  # [T,1,P,2]
    out = torch.nn.functional.grid_sample(maps[:, None], grid, mode="bilinear", padding_mode="border",
                                          align_corners=False)  # fmt: skip
    return out[:, 0, 0]


def silhouette_term(uv: torch.Tensor, outside: torch.Tensor, size: tuple[int, int], height_px: float,
                    sigma: float) -> torch.Tensor:
    """Mean Geman-McClure of the distance (fraction of height) from the body's projected surface
    points uv [T,P,2] to the person mask (``outside`` distance maps [T,h,w], pixels)."""
    d = sample_map(outside, uv, size) / height_px
    return geman_mcclure(d * d, sigma).mean()


def outline_term(uv: torch.Tensor, outline: torch.Tensor, weight: torch.Tensor, nearest: torch.Tensor,
                 height_px: float, sigma: float) -> torch.Tensor:
    """Mean over frames of the weighted mean Geman-McClure of the distance (fraction of height) from
    each outline pixel outline [T,B,2] to its nearest projected surface point uv [T,P,2]; ``nearest``
    [T,B] the index of that point (:func:`nearest_points`, found now or a few iterations ago: the
    correspondences change slowly, and the search is most of the term's cost), weight [T,B]."""
    q = torch.gather(uv, 1, nearest[..., None].expand(-1, -1, 2))
    rho = geman_mcclure(((q - outline) / height_px).pow(2).sum(-1), sigma)
    return ((weight * rho).sum(1) / weight.sum(1).clamp_min(1e-6)).mean()


def nearest_points(outline: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Index [T,B] of the point of uv [T,P,2] nearest to each of outline [T,B,2]. On the CPU a k-d tree
    per frame: the dense distance matrix ([T,B,P], 61 million distances for 100 frames) took a third of
    the fit's time; on a GPU the dense search is the fast one."""
    with torch.no_grad():
        if uv.device.type != "cpu":
            return torch.cdist(outline, uv).argmin(-1)
        from scipy.spatial import cKDTree

        o, u = outline.detach().numpy(), uv.detach().numpy()
        index = np.stack([cKDTree(u[t]).query(o[t])[1] for t in range(len(o))])
        return torch.as_tensor(index, dtype=torch.long)


def mask_outline(masks: list[np.ndarray], scale: float, count: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """The outline of each boolean mask [h,w] (its pixels with a 4-neighbour outside it), at most about
    ``count`` of them evenly along the raster order, as full-image pixel centres (``scale`` full-image
    pixels per mask pixel): points [T,B,2] (x, y) padded with zeros, and weights [T,B] (0 on padding)."""
    from scipy import ndimage

    picked = []
    for m in masks:
        yx = np.argwhere(m & ~ndimage.binary_erosion(m, border_value=1))
        picked.append((yx[:: max(1, len(yx) // count)][:, ::-1] + 0.5) * scale)
    B = max(1, max(len(p) for p in picked))
    points, weights = np.zeros((len(masks), B, 2), np.float32), np.zeros((len(masks), B), np.float32)
    for i, p in enumerate(picked):
        points[i, : len(p)], weights[i, : len(p)] = p, 1.0
    return points, weights


def mask_maps(masks: list[np.ndarray], width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the mask terms compare with, from boolean masks [h,w] (reduced from ``width``-pixel-wide
    frames): ``outside`` [T,h,w] float32, each pixel's distance (full-image pixels) to the mask, and the
    outline points [T,B,2] and weights [T,B] of :func:`mask_outline`."""
    from scipy import ndimage

    px = width / masks[0].shape[1]  # full-image pixels per mask pixel
    # a mask too thin to survive the reduction leaves no foreground: every point then counts as inside
    outside = np.stack([ndimage.distance_transform_edt(~m) * px if m.any() else np.zeros(m.shape)
                        for m in masks]).astype(np.float32)  # fmt: skip
    return (outside, *mask_outline(masks, px))


def limit_term(body_pose: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Sum over joints of the squared excess past the limits, mean over frames; body_pose [T,69]."""
    excess = torch.relu(body_pose - hi) + torch.relu(lo - body_pose)
    return excess.pow(2).sum(1).mean()


def hold_term(x: torch.Tensor) -> torch.Tensor:
    """Mean over frames of the squared distance of x [T,D] (body_pose, or a unit axis: radians squared
    for small angles) from its mean over the frames."""
    return (x - x.mean(0)).pow(2).sum(1).mean()


def smooth_term(x: torch.Tensor, gaps: torch.Tensor, sigma: float = 0.0) -> torch.Tensor:
    """Mean over frames of the squared acceleration per source frame of the points x [T,...,D] (the
    change of velocity, so turning or walking at a steady speed costs nothing), summed over the points,
    with ``gaps`` [T-1] frames between rows. ``sigma`` > 0: each point's squared acceleration r^2 costs
    sigma^2 rho(r) (Geman-McClure: r^2 while small, at most sigma^2), so that a fast true motion is not
    smoothed away."""
    if x.shape[0] < 3:
        return x.new_zeros(())
    g = gaps.reshape(-1, *[1] * (x.dim() - 1))
    v = (x[1:] - x[:-1]) / g
    r2 = ((v[1:] - v[:-1]) / (0.5 * (g[1:] + g[:-1]))).pow(2).sum(-1)
    if sigma > 0:
        r2 = sigma * sigma * geman_mcclure(r2, sigma)
    return r2.reshape(r2.shape[0], -1).sum(1).mean()


# --- initialisation ------------------------------------------------------------------------------

def orientation_from_world(world: torch.Tensor) -> torch.Tensor:
    """Global rotation matrices [T,3,3] (body canonical -> camera) from MediaPipe world landmarks
    [T,33,3]: the body's left from the hip and shoulder lines, up from mid-hip to mid-shoulder."""
    hips_l, hips_r, sh_l, sh_r = world[:, 23], world[:, 24], world[:, 11], world[:, 12]
    left = torch.nn.functional.normalize((hips_l - hips_r) + (sh_l - sh_r), dim=-1)
    up = (sh_l + sh_r - hips_l - hips_r) / 2
    up = torch.nn.functional.normalize(up - (up * left).sum(-1, keepdim=True) * left, dim=-1)
    forward = torch.cross(left, up, dim=-1)
    return torch.stack([left, up, forward], -1)


def translation_from_keypoints(points: torch.Tensor, keypoints: torch.Tensor, weights: torch.Tensor,
                               K: torch.Tensor) -> torch.Tensor:
    """The translation t [T,3] that best projects body points [T,K,3] (camera frame, t = 0) onto
    keypoints [T,K,2]: linear least squares of (u - cx) (z + tz) = fx (x + tx) and the same in v,
    weighted by ``weights`` [T,K]."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    du, dv = keypoints[..., 0] - cx, keypoints[..., 1] - cy
    x, y, z = points.unbind(-1)
    zero, one = torch.zeros_like(du), torch.ones_like(du)
    # rows: fx tx - du tz = du z - fx x ;  fy ty - dv tz = dv z - fy y
    A = torch.cat([torch.stack([fx * one, zero, -du], -1), torch.stack([zero, fy * one, -dv], -1)], 1)
    b = torch.cat([du * z - fx * x, dv * z - fy * y], 1)
    w = torch.cat([weights, weights], 1).sqrt()[..., None]
    sol = torch.linalg.lstsq((A * w).double(), (b[..., None] * w).double()).solution
    return sol[..., 0].to(points.dtype)


def surface_points(body, spacing: float) -> torch.Tensor:
    """Vertex ids [P] spread evenly over the body: one per ``spacing``-metre cell of the canonical
    mesh (the vertex nearest the cell's centre), so dense parts (face, hands) do not dominate."""
    v = body.v_template.detach().cpu().double()
    cell = torch.floor(v / spacing)
    centre = (cell + 0.5) * spacing
    d = (v - centre).norm(dim=1)
    _, inverse = torch.unique(cell, dim=0, return_inverse=True)
    best = torch.full((int(inverse.max()) + 1,), float("inf"), dtype=torch.float64)
    best.scatter_reduce_(0, inverse, d, reduce="amin")
    pick = torch.nonzero(d <= best[inverse])[:, 0]
    _, first = np.unique(inverse[pick].numpy(), return_index=True)  # one per cell on ties
    return pick[torch.as_tensor(first)].sort().values


# --- the fit ---------------------------------------------------------------------------------------

class _Problem:
    """Parameters and the objective of one fit."""

    def __init__(self, proxy: BodyProxy, obs: Observations, cfg: BodyFitConfig, R0: torch.Tensor,
                 pose0: torch.Tensor, transl0: torch.Tensor):
        dev = obs.keypoints.device
        T = obs.keypoints.shape[0]
        self.obs, self.cfg = obs, cfg
        self.R0 = R0
        self.d_orient = torch.zeros(T, 3, device=dev, requires_grad=True)
        self.body_pose = pose0.clone().requires_grad_(True)
        self.transl = transl0.clone().requires_grad_(True)
        self.proxy = proxy
        nb = proxy.num_betas
        self.betas = torch.zeros(1, nb, device=dev, requires_grad=True) if nb else None
        self.lo, self.hi = limit_bounds(device=dev)
        self.weights = visibility_weight(obs.visibility, cfg.min_visibility)
        self.mean_pose = rest_pose(device=dev)
        self.nearest = None  # the outline term's correspondences, searched every cfg.outline_every steps

    def global_orient(self) -> torch.Tensor:
        return matrix_to_axis_angle(self.rotation())

    def rotation(self) -> torch.Tensor:
        return self.R0 @ axis_angle_to_matrix(self.d_orient)

    def losses(self, full: bool, step: int) -> dict[str, torch.Tensor]:
        """The weighted terms (``full``: all of them, else keypoints, directions, limits, prior) at
        iteration ``step`` of a run."""
        cfg, obs = self.cfg, self.obs
        R = self.rotation()
        go = matrix_to_axis_angle(R)
        joints, rotations, surface = self.proxy(self.betas, go, self.body_pose, self.transl)
        points = body_landmarks(joints, rotations)
        uv = project(points, obs.K)
        terms = {
            "keypoints": cfg.keypoints * keypoint_term(uv, obs.keypoints, self.weights, obs.height_px, cfg.sigma),
            "directions": cfg.directions * direction_term(points, obs.world, self.weights),
            "limits": cfg.limits * limit_term(self.body_pose, self.lo, self.hi),
            "prior": cfg.prior * (self.body_pose - self.mean_pose).pow(2).sum(1).mean(),
        }
        if full:
            scale = obs.height_px / float(obs.K[1, 1])  # metres per (height fraction) at 1 m depth
            surf = project(surface, obs.K)
            terms["silhouette"] = cfg.silhouette * silhouette_term(surf, obs.outside, obs.size, obs.height_px,
                                                                   cfg.sigma)
            if cfg.outline and obs.outline is not None:
                if self.nearest is None or step % max(cfg.outline_every, 1) == 0:
                    self.nearest = nearest_points(obs.outline, surf)
                terms["outline"] = cfg.outline * outline_term(surf, obs.outline, obs.outline_weight, self.nearest,
                                                              obs.height_px, cfg.outline_sigma)
            depth = points[..., 2:].detach().mean()
            terms["smooth"] = cfg.smooth * smooth_term(points / (scale * depth), obs.gaps, cfg.smooth_sigma) \
                + cfg.smooth_pose * smooth_term(self.body_pose, obs.gaps)
            if cfg.hold_pose:
                terms["hold"] = cfg.hold_pose * hold_term(self.body_pose)
            if cfg.hold_up:
                terms["up"] = cfg.hold_up * hold_term(R[:, :, 1])
            if self.betas is not None:
                terms["shape"] = cfg.shape_prior * self.betas.pow(2).sum()
        return terms

    def run(self, iters: int, full: bool, params: list[torch.Tensor], bar=None) -> dict[str, float]:
        opt = torch.optim.Adam(params, lr=self.cfg.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(iters, 1), eta_min=self.cfg.lr * 0.05)
        terms = {}
        for step in range(iters):
            opt.zero_grad(set_to_none=True)
            terms = self.losses(full, step)
            total = sum(terms.values())
            total.backward()
            opt.step()
            sched.step()
            if bar is not None:
                bar.update(1)
        return {k: float(v.detach()) for k, v in terms.items()}


def fit_body(body, obs: Observations, cfg: BodyFitConfig | None = None, progress: bool = True) -> FitResult:
    """Fit ``body`` (a BodyModel on the observations' device) to the observations; see the module
    docstring. Returns the parameters in the camera frame."""
    import time

    from tqdm import tqdm

    cfg = cfg or BodyFitConfig()
    start = time.perf_counter()
    dev = obs.keypoints.device
    T = obs.keypoints.shape[0]
    pos = {k: i for i, k in enumerate(USED)}
    world33 = torch.zeros(T, 33, 3, device=dev)
    world33[:, list(USED)] = obs.world
    R0 = orientation_from_world(world33)
    pose0 = rest_pose(device=dev).expand(T, -1).clone()
    proxy = BodyProxy(body, surface_points(body, cfg.point_spacing).to(dev))
    with torch.no_grad():
        go0 = matrix_to_axis_angle(R0)
        joints, rotations, _ = proxy(None, go0, pose0, torch.zeros(T, 3, device=dev))
        pts = body_landmarks(joints, rotations)
        torso = [pos[k] for k in (11, 12, 23, 24)]
        transl0 = translation_from_keypoints(pts[:, torso], obs.keypoints[:, torso],
                                             obs.visibility[:, torso].pow(2) + 1e-3, obs.K)
    problem = _Problem(proxy, obs, cfg, R0, pose0, transl0)
    bar = tqdm(total=cfg.start_iters + cfg.iters, desc="capture: fitting the body", unit="it",
               disable=not progress)
    problem.run(cfg.start_iters, False, [problem.d_orient, problem.transl, problem.body_pose], bar)
    params = [problem.d_orient, problem.transl, problem.body_pose]
    if problem.betas is not None:
        params.append(problem.betas)
    losses = problem.run(cfg.iters, True, params, bar)
    bar.close()
    with torch.no_grad():
        go = problem.global_orient()
    betas = np.zeros(10, np.float32)
    if problem.betas is not None:
        betas[: problem.betas.shape[1]] = problem.betas.detach().cpu().numpy()[0]
    return FitResult(
        global_orient=go.detach().cpu().numpy().astype(np.float32),
        body_pose=problem.body_pose.detach().cpu().numpy().astype(np.float32),
        transl=problem.transl.detach().cpu().numpy().astype(np.float32),
        betas=betas, losses=losses, seconds=time.perf_counter() - start,
    )


__all__ = ["BodyFitConfig", "Observations", "FitResult", "fit_body"]
