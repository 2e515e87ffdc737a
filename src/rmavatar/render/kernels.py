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


@numba.njit(cache=True, nogil=True)
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
        # Clamp in floating point before converting, so huge boxes cannot overflow.
        x0 = int(math.floor(min(max(0.0, (mx - rx) / TILE), tiles_x)))
        x1 = int(math.ceil(min(max(0.0, (mx + rx) / TILE), tiles_x)))
        y0 = int(math.floor(min(max(0.0, (my - ry) / TILE), tiles_y)))
        y1 = int(math.ceil(min(max(0.0, (my + ry) / TILE), tiles_y)))
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
def _row_span(py0, th, my, a, b, c, smax):
    """Tile rows [y0, y1) that can hold pixels with sigma <= smax (plus one row of slack)."""
    det = a * c - b * b
    if not det > 0.0:  # rounding on an extremely thin Gaussian: scan the whole tile
        return py0, py0 + th
    ry = math.sqrt(2.0 * smax * a / det)  # y half-extent of the ellipse
    y0 = max(py0, int(math.ceil(my - ry - 0.5)) - 1) if my - ry > py0 else py0
    y1 = min(py0 + th, int(math.floor(my + ry - 0.5)) + 2) if my + ry < py0 + th else py0 + th
    return y0, y1


@numba.njit(cache=True, inline="always")
def _col_span(px0, tw, fy, mx, my, a, b, c, smax):
    """Tile columns [x0, x1) of row centre ``fy`` with sigma <= smax (plus one pixel of slack),
    from the roots of 0.5 a dx^2 + b dy dx + 0.5 c dy^2 - smax = 0 with dx = mx - x."""
    dy = my - fy
    bd = b * dy
    disc = bd * bd - a * (c * dy * dy - 2.0 * smax)
    if disc < 0.0:
        return px0, px0
    sq = math.sqrt(disc)
    lo = mx + (bd - sq) / a
    hi = mx + (bd + sq) / a
    x0 = max(px0, int(math.ceil(lo - 0.5)) - 1) if lo > px0 else px0
    x1 = min(px0 + tw, int(math.floor(hi - 0.5)) + 2) if hi < px0 + tw else px0 + tw
    return x0, x1


@numba.njit(parallel=True, cache=True, nogil=True)
def composite_forward(means2d, conics, colors, opacities, background, offsets, ids, width, height, tiles_x, tile_order):
    """Render. Returns image [H,W,3], final transmittance [H,W], and per pixel the count of tile-list
    entries up to and including its last contributor [H,W] (the backward starts there).

    ``tile_order`` [T] is the order tiles are handed to threads (see ``interleaved_tiles``).
    Gaussian-major within a tile: each Gaussian visits only the pixels of the tile inside its
    ellipse sigma <= ln(255 opacity) (row by row, from the quadratic's roots), the pixels keep their
    running transmittance, and the tile stops once every pixel has terminated.
    """
    n_tiles = offsets.shape[0] - 1
    image = np.empty((height, width, 3))
    t_final = np.empty((height, width))
    n_last = np.zeros((height, width), np.int32)
    for i in numba.prange(n_tiles):
        t = tile_order[i]
        start = offsets[t]
        n = offsets[t + 1] - start
        px0 = (t % tiles_x) * TILE
        py0 = (t // tiles_x) * TILE
        tw = min(TILE, width - px0)
        th = min(TILE, height - py0)
        trans = np.ones(TILE * TILE)
        acc = np.zeros((TILE * TILE, 3))
        last = np.zeros(TILE * TILE, np.int32)
        done = np.zeros(TILE * TILE, np.bool_)
        n_done = 0
        for j in range(n):
            if n_done == tw * th:
                break
            g = ids[start + j]
            mx = means2d[g, 0]
            my = means2d[g, 1]
            ca = conics[g, 0]
            cb = conics[g, 1]
            cc = conics[g, 2]
            op = opacities[g]
            smax = math.log(op / ALPHA_MIN) + _SIGMA_MARGIN
            y0, y1 = _row_span(py0, th, my, ca, cb, cc, smax)
            for py in range(y0, y1):
                fy = py + 0.5
                x0, x1 = _col_span(px0, tw, fy, mx, my, ca, cb, cc, smax)
                dy = my - fy
                for px in range(x0, x1):
                    k = (py - py0) * TILE + (px - px0)
                    if done[k]:
                        continue
                    dx = mx - (px + 0.5)
                    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0.0 or sigma > smax:
                        continue
                    alpha = min(ALPHA_MAX, op * math.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    T = trans[k]
                    next_t = T * (1.0 - alpha)
                    if next_t <= T_MIN:
                        done[k] = True
                        n_done += 1
                        continue
                    w = alpha * T
                    acc[k, 0] += colors[g, 0] * w
                    acc[k, 1] += colors[g, 1] * w
                    acc[k, 2] += colors[g, 2] * w
                    trans[k] = next_t
                    last[k] = j + 1
        for py in range(py0, py0 + th):
            for px in range(px0, px0 + tw):
                k = (py - py0) * TILE + (px - px0)
                T = trans[k]
                image[py, px, 0] = acc[k, 0] + T * background[0]
                image[py, px, 1] = acc[k, 1] + T * background[1]
                image[py, px, 2] = acc[k, 2] + T * background[2]
                t_final[py, px] = T
                n_last[py, px] = last[k]
    return image, t_final, n_last


@numba.njit(cache=True, nogil=True, inline="always")
def _start_tile_backward(t, px0, py0, tw, th, background, t_final, n_last, v_image, trans, behind, stop, v_bg_tiles):
    """Set up tile ``t``'s per-pixel backward state from the forward's: ``trans`` = T_final, ``behind`` =
    T_final * background (the colour composited behind the last contributor), ``stop`` = n_last, and
    add the tile's background gradient (sum of v_image * T_final) to ``v_bg_tiles[t]``.
    Returns the largest ``stop`` in the tile: the backward walks list entries [0, n_max) back to front."""
    n_max = 0
    for py in range(py0, py0 + th):
        for px in range(px0, px0 + tw):
            k = (py - py0) * TILE + (px - px0)
            T = t_final[py, px]
            trans[k] = T
            behind[k, 0] = T * background[0]
            behind[k, 1] = T * background[1]
            behind[k, 2] = T * background[2]
            stop[k] = n_last[py, px]
            n_max = max(n_max, stop[k])
            v_bg_tiles[t, 0] += v_image[py, px, 0] * T
            v_bg_tiles[t, 1] += v_image[py, px, 1] * T
            v_bg_tiles[t, 2] += v_image[py, px, 2] * T
    return n_max


@numba.njit(cache=True, nogil=True, inline="always")
def _gaussian_backward(
    g, j, row, px0, py0, tw, th, means2d, conics, colors, opacities, t_final, v_image, v_alpha,
    trans, behind, stop, grads,
):
    """Back-propagate Gaussian ``g``, entry ``j`` of its tile's list, through the tile's pixels it
    covers, updating their ``trans`` (T_j) and ``behind`` (colour composited behind it) on the way.
    Writes its summed gradients (dmx, dmy, da, db, dc, dr, dg, db, dopacity) to ``grads[row]``;
    returns nothing."""
    mx = means2d[g, 0]
    my = means2d[g, 1]
    ca = conics[g, 0]
    cb = conics[g, 1]
    cc = conics[g, 2]
    op = opacities[g]
    cr = colors[g, 0]
    cg = colors[g, 1]
    cbl = colors[g, 2]
    smax = math.log(op / ALPHA_MIN) + _SIGMA_MARGIN
    g_mx = 0.0
    g_my = 0.0
    g_a = 0.0
    g_b = 0.0
    g_c = 0.0
    g_r = 0.0
    g_g = 0.0
    g_bl = 0.0
    g_op = 0.0
    y0, y1 = _row_span(py0, th, my, ca, cb, cc, smax)
    for py in range(y0, y1):
        fy = py + 0.5
        x0, x1 = _col_span(px0, tw, fy, mx, my, ca, cb, cc, smax)
        dy = my - fy
        for px in range(x0, x1):
            k = (py - py0) * TILE + (px - px0)
            if j >= stop[k]:
                continue
            dx = mx - (px + 0.5)
            sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            if sigma < 0.0 or sigma > smax:
                continue
            gauss = math.exp(-sigma)
            raw = op * gauss
            alpha = min(ALPHA_MAX, raw)
            if alpha < ALPHA_MIN:
                continue
            inv = 1.0 / (1.0 - alpha)
            T = trans[k] * inv
            trans[k] = T
            w = alpha * T
            vr = v_image[py, px, 0]
            vg = v_image[py, px, 1]
            vb = v_image[py, px, 2]
            g_r += w * vr
            g_g += w * vg
            g_bl += w * vb
            v_a = (cr * T * vr + cg * T * vg + cbl * T * vb) - inv * (
                behind[k, 0] * vr + behind[k, 1] * vg + behind[k, 2] * vb
                - v_alpha[py, px] * t_final[py, px]
            )
            behind[k, 0] += cr * w
            behind[k, 1] += cg * w
            behind[k, 2] += cbl * w
            if raw <= ALPHA_MAX:  # the clamp has zero slope
                g_op += gauss * v_a
                v_sigma = -raw * v_a
                g_mx += (ca * dx + cb * dy) * v_sigma
                g_my += (cb * dx + cc * dy) * v_sigma
                g_a += 0.5 * dx * dx * v_sigma
                g_b += dx * dy * v_sigma
                g_c += 0.5 * dy * dy * v_sigma
    grads[row, 0] = g_mx
    grads[row, 1] = g_my
    grads[row, 2] = g_a
    grads[row, 3] = g_b
    grads[row, 4] = g_c
    grads[row, 5] = g_r
    grads[row, 6] = g_g
    grads[row, 7] = g_bl
    grads[row, 8] = g_op


@numba.njit(parallel=True, cache=True, nogil=True)
def composite_backward(
    means2d, conics, colors, opacities, background, offsets, ids, width, height, tiles_x, tile_order,
    t_final, n_last, v_image, v_alpha,
):
    """Gradients of a loss given v_image [H,W,3] = dL/dimage and v_alpha [H,W] = dL/dalpha.

    Walks each pixel's contributors back to front, recovering T_i = T_{i+1} / (1 - alpha_i) and the
    colour S_i composited behind Gaussian i (background included):
      dC/dc_i = alpha_i T_i,  dC/dalpha_i = c_i T_i - S_i / (1 - alpha_i),
      dA/dalpha_i = T_final / (1 - alpha_i),  dC/dbackground = T_final,
    then alpha_i = min(0.999, o_i exp(-sigma_i)) and sigma_i = 0.5 d^T conic_i d, d = mean_i - pixel.
    Gaussian-major per tile like the forward, so each Gaussian's gradient is summed in registers.
    ``tile_order`` [T] is the order tiles are handed to threads (see ``interleaved_tiles``).
    Returns per-intersection gradients [I,9] (dmx, dmy, da, db, dc, dr, dg, db, dopacity) and the
    background gradient [3].
    """
    n_tiles = offsets.shape[0] - 1
    grads = np.zeros((ids.shape[0], 9))
    v_bg_tiles = np.zeros((n_tiles, 3))
    for i in numba.prange(n_tiles):
        t = tile_order[i]
        start = offsets[t]
        px0 = (t % tiles_x) * TILE
        py0 = (t // tiles_x) * TILE
        tw = min(TILE, width - px0)
        th = min(TILE, height - py0)
        trans = np.empty(TILE * TILE)
        behind = np.empty((TILE * TILE, 3))
        stop = np.zeros(TILE * TILE, np.int32)
        n_max = _start_tile_backward(
            t, px0, py0, tw, th, background, t_final, n_last, v_image, trans, behind, stop, v_bg_tiles
        )
        for j in range(n_max - 1, -1, -1):
            _gaussian_backward(
                ids[start + j], j, start + j, px0, py0, tw, th, means2d, conics, colors, opacities, t_final,
                v_image, v_alpha, trans, behind, stop, grads,
            )
    v_bg = np.zeros(3)
    for t in range(n_tiles):
        v_bg[0] += v_bg_tiles[t, 0]
        v_bg[1] += v_bg_tiles[t, 1]
        v_bg[2] += v_bg_tiles[t, 2]
    return grads, v_bg


def interleaved_tiles(n_tiles: int, n_threads: int) -> np.ndarray:
    """Tile order for the parallel loops: their static schedule gives each thread a contiguous block,
    so interleave tiles (thread r gets tiles r, r + n_threads, ...) to spread dense regions evenly."""
    n_threads = max(1, n_threads)
    return np.concatenate([np.arange(r, n_tiles, n_threads) for r in range(n_threads)]).astype(np.int64)


@numba.njit(cache=True, nogil=True)
def sum_per_gaussian(grads, ids, n):
    """Sum per-intersection gradients [I,9] into per-Gaussian ones [n,9]."""
    out = np.zeros((n, 9))
    for k in range(ids.shape[0]):
        g = ids[k]
        for c in range(9):
            out[g, c] += grads[k, c]
    return out
