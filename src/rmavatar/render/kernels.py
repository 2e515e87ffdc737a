"""Numba kernels of the CPU backend: tile binning, front-to-back compositing and its backward.

All arithmetic is float64 so the analytic backward, which recovers each transmittance by dividing
the final one by ``1 - alpha`` back to front, stays accurate. Parallel loops run over 16x16 tiles;
each tile owns a contiguous slice of the depth-sorted intersection list, so the backward writes
per-intersection gradients without races and a serial pass sums them per Gaussian.

Compositing rules (gsplat 1.5 "classic"): pixel centres at +0.5, ``sigma = 0.5 d^T conic d``,
``alpha = min(0.999, opacity exp(-sigma))``, skip ``sigma < 0`` or ``alpha < 1/255``, and stop before
the Gaussian that would bring the transmittance to ``<= 1e-4``.
"""

from __future__ import annotations

import math

import numpy as np

from rmavatar.render._numba import numba

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4
# Cheap pre-test: sigma above ln(255 opacity) means alpha < 1/255; the margin leaves the exact
# decision to the same test the reference uses.
_SIGMA_MARGIN = 1e-9


@numba.njit(cache=True)
def bin_tiles(means2d, radii_xy, order, tiles_x, tiles_y):
    """Tile lists of Gaussians, front to back.

    means2d [N,2] float64, radii_xy [N,2] int, order [M] int64 visible Gaussian ids already sorted
    by depth. Returns offsets [T+1] int64 (tile t owns ids[offsets[t]:offsets[t+1]]) and ids [I].
    """
    m = order.shape[0]
    n_tiles = tiles_x * tiles_y
    bounds = np.empty((m, 4), np.int64)
    counts = np.zeros(n_tiles + 1, np.int64)
    for k in range(m):
        g = order[k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        rx = radii_xy[g, 0]
        ry = radii_xy[g, 1]
        x0 = min(max(0, int(math.floor((mx - rx) / TILE))), tiles_x)
        x1 = min(max(0, int(math.ceil((mx + rx) / TILE))), tiles_x)
        y0 = min(max(0, int(math.floor((my - ry) / TILE))), tiles_y)
        y1 = min(max(0, int(math.ceil((my + ry) / TILE))), tiles_y)
        bounds[k, 0] = x0
        bounds[k, 1] = x1
        bounds[k, 2] = y0
        bounds[k, 3] = y1
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    ids = np.empty(offsets[n_tiles], np.int64)
    cursor = offsets[:n_tiles].copy()
    for k in range(m):
        g = order[k]
        for ty in range(bounds[k, 2], bounds[k, 3]):
            for tx in range(bounds[k, 0], bounds[k, 1]):
                t = ty * tiles_x + tx
                ids[cursor[t]] = g
                cursor[t] += 1
    return offsets, ids


@numba.njit(cache=True, inline="always")
def _gather(ids, start, n, means2d, conics, colors, opacities):
    """Copy one tile's Gaussians into a contiguous [n,10] block: mx, my, a, b, c, opacity,
    ln(255 opacity), r, g, b."""
    blk = np.empty((n, 10))
    for j in range(n):
        g = ids[start + j]
        blk[j, 0] = means2d[g, 0]
        blk[j, 1] = means2d[g, 1]
        blk[j, 2] = conics[g, 0]
        blk[j, 3] = conics[g, 1]
        blk[j, 4] = conics[g, 2]
        op = opacities[g]
        blk[j, 5] = op
        blk[j, 6] = math.log(op / ALPHA_MIN) + _SIGMA_MARGIN if op > 0 else -1.0
        blk[j, 7] = colors[g, 0]
        blk[j, 8] = colors[g, 1]
        blk[j, 9] = colors[g, 2]
    return blk


@numba.njit(parallel=True, cache=True)
def composite_forward(means2d, conics, colors, opacities, background, offsets, ids, width, height, tiles_x):
    """Render. Returns image [H,W,3], final transmittance [H,W], and per pixel the count of tile-list
    entries up to and including its last contributor [H,W] (the backward starts there)."""
    n_tiles = offsets.shape[0] - 1
    image = np.empty((height, width, 3))
    t_final = np.empty((height, width))
    n_last = np.zeros((height, width), np.int32)
    bg0 = background[0]
    bg1 = background[1]
    bg2 = background[2]
    for t in numba.prange(n_tiles):
        start = offsets[t]
        n = offsets[t + 1] - start
        blk = _gather(ids, start, n, means2d, conics, colors, opacities)
        px0 = (t % tiles_x) * TILE
        py0 = (t // tiles_x) * TILE
        for py in range(py0, min(py0 + TILE, height)):
            fy = py + 0.5
            for px in range(px0, min(px0 + TILE, width)):
                fx = px + 0.5
                T = 1.0
                r = 0.0
                gc = 0.0
                b = 0.0
                last = 0
                for j in range(n):
                    dx = blk[j, 0] - fx
                    dy = blk[j, 1] - fy
                    sigma = 0.5 * (blk[j, 2] * dx * dx + blk[j, 4] * dy * dy) + blk[j, 3] * dx * dy
                    if sigma < 0.0 or sigma > blk[j, 6]:
                        continue
                    alpha = min(ALPHA_MAX, blk[j, 5] * math.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    next_t = T * (1.0 - alpha)
                    if next_t <= T_MIN:
                        break
                    w = alpha * T
                    r += blk[j, 7] * w
                    gc += blk[j, 8] * w
                    b += blk[j, 9] * w
                    T = next_t
                    last = j + 1
                image[py, px, 0] = r + T * bg0
                image[py, px, 1] = gc + T * bg1
                image[py, px, 2] = b + T * bg2
                t_final[py, px] = T
                n_last[py, px] = last
    return image, t_final, n_last


@numba.njit(parallel=True, cache=True)
def composite_backward(
    means2d, conics, colors, opacities, background, offsets, ids, width, height, tiles_x,
    t_final, n_last, v_image, v_alpha,
):
    """Gradients of a loss given v_image [H,W,3] = dL/dimage and v_alpha [H,W] = dL/dalpha.

    Walks each pixel's contributors back to front, recovering T_i = T_{i+1} / (1 - alpha_i) and the
    colour S_i composited behind Gaussian i (background included):
      dC/dc_i = alpha_i T_i,  dC/dalpha_i = c_i T_i - S_i / (1 - alpha_i),
      dA/dalpha_i = T_final / (1 - alpha_i),  dC/dbackground = T_final.
    Returns per-intersection gradients [I,9] (dmx, dmy, da, db, dc, dr, dg, db, dopacity) and the
    background gradient [3].
    """
    n_tiles = offsets.shape[0] - 1
    grads = np.zeros((ids.shape[0], 9))
    v_bg_tiles = np.zeros((n_tiles, 3))
    bg0 = background[0]
    bg1 = background[1]
    bg2 = background[2]
    for t in numba.prange(n_tiles):
        start = offsets[t]
        n = offsets[t + 1] - start
        blk = _gather(ids, start, n, means2d, conics, colors, opacities)
        px0 = (t % tiles_x) * TILE
        py0 = (t // tiles_x) * TILE
        vb0 = 0.0
        vb1 = 0.0
        vb2 = 0.0
        for py in range(py0, min(py0 + TILE, height)):
            fy = py + 0.5
            for px in range(px0, min(px0 + TILE, width)):
                fx = px + 0.5
                t_fin = t_final[py, px]
                vr = v_image[py, px, 0]
                vg = v_image[py, px, 1]
                vb = v_image[py, px, 2]
                va = v_alpha[py, px]
                vb0 += vr * t_fin
                vb1 += vg * t_fin
                vb2 += vb * t_fin
                T = t_fin
                s0 = t_fin * bg0
                s1 = t_fin * bg1
                s2 = t_fin * bg2
                for j in range(n_last[py, px] - 1, -1, -1):
                    dx = blk[j, 0] - fx
                    dy = blk[j, 1] - fy
                    sigma = 0.5 * (blk[j, 2] * dx * dx + blk[j, 4] * dy * dy) + blk[j, 3] * dx * dy
                    if sigma < 0.0 or sigma > blk[j, 6]:
                        continue
                    gauss = math.exp(-sigma)
                    raw = blk[j, 5] * gauss
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    one_minus = 1.0 - alpha
                    T = T / one_minus
                    w = alpha * T
                    k = start + j
                    grads[k, 5] += w * vr
                    grads[k, 6] += w * vg
                    grads[k, 7] += w * vb
                    v_a = (
                        (blk[j, 7] * T - s0 / one_minus) * vr
                        + (blk[j, 8] * T - s1 / one_minus) * vg
                        + (blk[j, 9] * T - s2 / one_minus) * vb
                        + va * t_fin / one_minus
                    )
                    s0 += blk[j, 7] * w
                    s1 += blk[j, 8] * w
                    s2 += blk[j, 9] * w
                    if raw <= ALPHA_MAX:  # the clamp has zero slope
                        grads[k, 8] += gauss * v_a
                        v_sigma = -raw * v_a
                        ga = blk[j, 2]
                        gb = blk[j, 3]
                        gcc = blk[j, 4]
                        grads[k, 0] += (ga * dx + gb * dy) * v_sigma
                        grads[k, 1] += (gb * dx + gcc * dy) * v_sigma
                        grads[k, 2] += 0.5 * dx * dx * v_sigma
                        grads[k, 3] += dx * dy * v_sigma
                        grads[k, 4] += 0.5 * dy * dy * v_sigma
        v_bg_tiles[t, 0] = vb0
        v_bg_tiles[t, 1] = vb1
        v_bg_tiles[t, 2] = vb2
    v_bg = np.zeros(3)
    for t in range(n_tiles):
        v_bg[0] += v_bg_tiles[t, 0]
        v_bg[1] += v_bg_tiles[t, 1]
        v_bg[2] += v_bg_tiles[t, 2]
    return grads, v_bg


@numba.njit(cache=True)
def sum_per_gaussian(grads, ids, n):
    """Sum per-intersection gradients [I,9] into per-Gaussian ones [n,9]."""
    out = np.zeros((n, 9))
    for k in range(ids.shape[0]):
        g = ids[k]
        for c in range(9):
            out[g, c] += grads[k, c]
    return out
