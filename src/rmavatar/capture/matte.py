"""The person mask sharpened along the frame's own colour edges: the guided filter (He, Sun and Tang,
"Guided Image Filtering", ECCV 2010; TPAMI 2013), with the frame as a colour guide, and, for a static
camera, the compositing equation against a clean background plate.

Why: MediaPipe's segmentation is a probability computed at a reduced resolution and upsampled. Its soft
band is wider than the person's antialiased edge, and training composites each target as
``image * mask + background * (1 - mask)``, so the band lightens the body's rim in every target (and
leaves a rim of the real background around it). The guided filter fits the mask, window by window, as
a linear function of the frame's colour (q = a . I + b), which snaps the band to the colour edge.

On a cluttered background the guided filter also snaps to the background's own edges (a treadmill's
stripes, a window frame) up to two window radii from the person, which then show in every target as
pale streaks. A static camera sees the background behind the person in other frames: the plate
(:func:`background_plate`, the per-pixel median of the frames in which the person is not near) gives
each edge pixel its background colour B, and the person's colour F is that of the confident interior
nearby, so the compositing equation I = a F + (1 - a) B gives the edge's alpha directly,
a = (I - B).(F - B) / |F - B|^2, wherever F and B differ; where they do not (dark shorts on a dark
floor) the guided filter's value stays. The result differs from MediaPipe's hard decision only within
BAND of its edge, so nothing far from the person leaks in.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

# Window radius as a fraction of the frame's longer side (4 px at 256) and the regulariser on a window's
# colour variance (colours in 0..1): on the synthetic turn at 256 px these took the training targets
# composited with MediaPipe's masks from 37.2 to 39.6 dB of those composited with the true masks
# (white background; black: 29.2 -> 32.2); radius 1-8 px and eps 1e-4..1e-2 were tried (docs/capture.md).
RADIUS_FRACTION = 1 / 64
EPS = 1e-3
# The coefficients' grid step is the radius over this (the fast guided filter, exact below a radius of
# 16 px, frames up to about 1,000 px): at 1920 px the exact filter was most of a capture's time; what
# the step changes in the masks, and what it saves: docs/capture.md, "Speed".
STEP_DIVISOR = 8
# MediaPipe's mask values below this count as 0 (a quarter of an 8-bit step: invisible in the masks written)
FLOOR = 1 / 1024
# The plate: the median, per pixel, over at most PLATE_FRAMES frames spread over the clip, of those in which
# no mask value >= PLATE_FLOOR lies within PLATE_CLEAR of the longer side (the person's shadow and
# MediaPipe's soft margin stay out).
PLATE_FRAMES = 40
PLATE_CLEAR = 1 / 96
PLATE_FLOOR = 0.05
# With a plate, the mask departs from MediaPipe's 0/1 only within BAND of the longer side of its 0.5
# contour; F is the mean colour of the interior (farther than BAND inside) within FG_RADIUS; the plate's
# alpha is trusted by |F - B|^2 / (|F - B|^2 + SEPARATION^2), the guided filter's by the rest. On the
# synthetic turn composited over a lab's plate (scripts/measure_masks.py, docs/real.md) these gave the
# smallest edge error against the true masks of the bands 1/256-1/64 and separations 0.05-0.2 tried.
BAND = 1 / 256
FG_RADIUS = 1 / 64
SEPARATION = 0.1


def box_mean(x: np.ndarray, radius: int) -> np.ndarray:
    """Mean of x [H,W] or [H,W,C] over (2 radius + 1)^2 windows, the frame mirrored at its borders
    (``abc|cba``). OpenCV's box filter where it is installed (the capture extra brings it; about ten
    times faster than SciPy's on up to four channels), else SciPy's."""
    try:
        import cv2
    except ImportError:
        cv2 = None
    if cv2 is None or x.dtype not in (np.float32, np.float64) or min(x.shape[:2]) < 2 * radius + 1:
        size = (2 * radius + 1, 2 * radius + 1) + (1,) * (x.ndim - 2)
        return ndimage.uniform_filter(x, size=size, mode="reflect")
    k = (2 * radius + 1, 2 * radius + 1)
    if x.ndim == 2 or x.shape[2] <= 4:
        out = cv2.blur(np.ascontiguousarray(x), k, borderType=cv2.BORDER_REFLECT)
        return out.reshape(x.shape)
    return np.concatenate([box_mean(x[..., c:c + 4], radius) for c in range(0, x.shape[2], 4)], -1)


def guided_filter(guide: np.ndarray, p: np.ndarray, radius: int, eps: float, step: int = 1) -> np.ndarray:
    """The guided filter of p [H,W] by a colour guide [H,W,3] (float, 0..1): per window k,
    a_k = (Sigma_k + eps 1)^-1 cov_k(I, p), b_k = mean_k(p) - a_k . mean_k(I), and
    q = mean(a) . I + mean(b), each mean over the windows covering the pixel. Returns q [H,W], in
    float64, or float32 when both inputs are (colours in 0..1 leave float32 seven digits for the
    window's variances, against eps 1e-3).
    Sigma_k is symmetric: its six distinct entries are averaged and the 3x3 systems solved by their
    adjugate (a general batched solve of every window cost several times the filtering).
    ``step`` > 1: the fast guided filter (He and Sun 2015): mean(a) and mean(b) on a grid ``step``
    times coarser (guide and p area-averaged, the radius divided by ``step``), brought back bilinearly;
    q is then formed with the full-resolution guide. mean(a) and mean(b) vary over a window's width, so
    a step of a quarter radius loses little, and the cost falls by about step^2."""
    dtype = np.float32 if guide.dtype == np.float32 and p.dtype == np.float32 else np.float64
    full = guide.astype(dtype, copy=False)
    if step > 1:
        import cv2

        h, w = p.shape
        coarse = (max(1, round(w / step)), max(1, round(h / step)))
        I = cv2.resize(full, coarse, interpolation=cv2.INTER_AREA)
        p = cv2.resize(p.astype(dtype, copy=False), coarse, interpolation=cv2.INTER_AREA)
        radius = max(1, round(radius / step))
    else:
        I = full
        p = p.astype(dtype, copy=False)
    means = box_mean(np.concatenate([I, p[..., None]], -1), radius)
    mean_I, mean_p = means[..., :3], means[..., 3]
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    products = np.stack([I[..., 0] * p, I[..., 1] * p, I[..., 2] * p] + [I[..., i] * I[..., j] for i, j in pairs], -1)
    moments = box_mean(products, radius)
    cov_Ip = moments[..., :3] - mean_I * mean_p[..., None]
    s00, s01, s02, s11, s12, s22 = (moments[..., 3 + n] - mean_I[..., i] * mean_I[..., j] + (eps if i == j else 0.0)
                                    for n, (i, j) in enumerate(pairs))
    c00, c01, c02 = s11 * s22 - s12 * s12, s02 * s12 - s01 * s22, s01 * s12 - s02 * s11
    c11, c12, c22 = s00 * s22 - s02 * s02, s01 * s02 - s00 * s12, s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    v0, v1, v2 = cov_Ip[..., 0], cov_Ip[..., 1], cov_Ip[..., 2]
    ab = np.empty(p.shape + (4,), dtype)
    ab[..., 0] = (c00 * v0 + c01 * v1 + c02 * v2) / det
    ab[..., 1] = (c01 * v0 + c11 * v1 + c12 * v2) / det
    ab[..., 2] = (c02 * v0 + c12 * v1 + c22 * v2) / det
    ab[..., 3] = mean_p - (ab[..., :3] * mean_I).sum(-1)
    mean_ab = box_mean(ab, radius)
    if step > 1:
        mean_ab = cv2.resize(mean_ab, (w, h), interpolation=cv2.INTER_LINEAR)
    return (mean_ab[..., :3] * full).sum(-1) + mean_ab[..., 3]


def refine_mask(image: np.ndarray, mask: np.ndarray, plate: np.ndarray | None = None,
                seen: np.ndarray | None = None) -> np.ndarray:
    """MediaPipe's mask [H,W] (0..1) of the frame image [H,W,3] (uint8) snapped to the frame's colour
    edges, float32 0..1; with the background ``plate`` [H,W,3] (uint8) and where it was ``seen`` [H,W]
    (:func:`background_plate`), the edge's alpha from the compositing equation within BAND of MediaPipe's
    edge, and MediaPipe's 0/1 beyond it (module docstring).

    Only the person's box is filtered: a window that holds no mask gets a = 0 and b = 0 whatever its
    colours, so a pixel farther than two window radii from the mask stays 0, and the box (the mask's
    extent, values under FLOOR set to 0, grown by 2 radius + 1) gives the same result as the whole frame."""
    h, w = mask.shape
    radius = max(1, round(max(h, w) * RADIUS_FRACTION))
    out = np.zeros((h, w), np.float32)
    support = mask >= FLOOR
    rows, cols = np.nonzero(support.any(1))[0], np.nonzero(support.any(0))[0]
    if len(rows) == 0:
        return out
    grow = 2 * radius + 1
    r0, r1 = max(int(rows[0]) - grow, 0), min(int(rows[-1]) + grow + 1, h)
    c0, c1 = max(int(cols[0]) - grow, 0), min(int(cols[-1]) + grow + 1, w)
    box = (slice(r0, r1), slice(c0, c1))
    p = np.where(support[box], mask[box], 0.0).astype(np.float32)
    colour = image[box].astype(np.float32) / np.float32(255.0)
    q = np.clip(guided_filter(colour, p, radius, EPS, step=max(1, radius // STEP_DIVISOR)), 0.0, 1.0)
    if plate is not None:
        q = _against_plate(colour, p, q, plate[box].astype(np.float32) / np.float32(255.0),
                           np.ones(p.shape, bool) if seen is None else seen[box], max(h, w))
    out[box] = q
    return out


def _against_plate(colour: np.ndarray, mask: np.ndarray, guided: np.ndarray, plate: np.ndarray, seen: np.ndarray,
                   side: int) -> np.ndarray:
    """The mask of a frame's box from its colours [h,w,3], MediaPipe's mask [h,w], the guided filter's
    result, the plate [h,w,3] (0..1) and where it was seen [h,w]: module docstring."""
    band = max(1.0, side * BAND)
    person = mask > 0.5
    outside = _distance(~person)  # distance to the person, for pixels outside it
    interior = _distance(person) > band  # farther than the band from the background
    weight = box_mean(interior.astype(np.float32), max(1, round(side * FG_RADIUS)))
    person_colour = box_mean(colour * interior[..., None], max(1, round(side * FG_RADIUS))) / np.maximum(
        weight, 1e-6)[..., None]
    apart = person_colour - plate
    spread = np.einsum("ijk,ijk->ij", apart, apart)
    alpha = np.clip(np.einsum("ijk,ijk->ij", colour - plate, apart) / np.maximum(spread, 1e-6), 0.0, 1.0)
    trust = spread / (spread + SEPARATION ** 2) * (weight > 1e-3) * seen
    edge = trust * alpha + (1.0 - trust) * guided
    return np.where(interior, 1.0, np.where(outside <= band, edge, 0.0)).astype(np.float32)


def _distance(region: np.ndarray) -> np.ndarray:
    """Euclidean distance [h,w] float32 of each pixel of ``region`` (bool) to the nearest pixel outside it
    (0 outside): OpenCV's exact transform where it is installed (the capture extra brings it), else SciPy's."""
    try:
        import cv2
    except ImportError:
        return ndimage.distance_transform_edt(region).astype(np.float32)
    return cv2.distanceTransform(region.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def background_plate(frames: np.ndarray, masks: np.ndarray, rows: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """A static camera's view without the person: frames [T,H,W,3] uint8 and their person masks [T,H,W]
    (0..1) -> (plate [H,W,3] uint8, seen [H,W] bool). Per pixel, the median (the lower middle value) over
    the frames in which no mask value >= PLATE_FLOOR lies within PLATE_CLEAR of the longer side; where
    every frame has the person near, the median over all frames and ``seen`` False. Computed ``rows`` image
    rows at a time (memory)."""
    t, h, w, _ = frames.shape
    clear = max(1, round(max(h, w) * PLATE_CLEAR))
    away = np.stack([box_mean((m >= PLATE_FLOOR).astype(np.float32), clear) <= 0 for m in masks])  # [T,H,W]
    plate = np.empty((h, w, 3), np.uint8)
    for r in range(0, h, rows):
        part = slice(r, min(r + rows, h))
        values = np.where(away[:, part, :, None], frames[:, part].astype(np.int16), np.int16(1 << 14))
        values.sort(axis=0)  # the frames without the person first, in order of value
        count = away[:, part].sum(0)
        middle = (np.maximum(count, 1) - 1) // 2
        picked = np.take_along_axis(values, np.broadcast_to(middle[None, ..., None], (1, *middle.shape, 3)), 0)[0]
        fallback = np.median(frames[:, part], axis=0)
        plate[part] = np.where(count[..., None] > 0, picked, fallback).astype(np.uint8)
    return plate, away.any(0)


__all__ = ["background_plate", "guided_filter", "refine_mask"]
