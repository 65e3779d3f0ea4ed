"""The CPU rasteriser's kernels: splats binned into tiles of the view, then each tile's pixels
blended front to back and, backwards, their gradients, compiled with numba and run in
parallel over tiles (gsplat's design, on the CPU).

Splats come as ``projection.project`` makes them: ``table`` (F, 6) rows of centre u, v, inverse
covariance a, b, c and peak opacity; ``box`` (F, 4) the pixels x0 <= x < x1, y0 <= y < y1
a splat may touch (its ellipse's box at alpha 1/255, cut at a reach); ``order`` the rows to
draw, front to back. A pair (pixel, splat) counts when its alpha is at least 1/255 and at
least ``MIN_TRANSMITTANCE`` of the pixel's light is left in front of it, as in
``pairs._band``. Within a tile the splats are taken in depth order, each over the
pixels of its ellipse only, the tile's pixels keeping their light (gsplat walks pixels
and tests every splat; without a GPU's threads, testing only the ellipse's pixels is what
bounds the work by the pairs). Arithmetic is float64; nothing is allocated per pair.

Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering, SIGGRAPH 2023
(tiles, per-tile depth order, the backward from the pixels' final transmittance); gsplat's
``rasterize_to_pixels`` (the same, in CUDA).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

TILE = 16  # pixels on a tile's side
MAX_ALPHA = 0.99  # no splat is more opaque than this at its peak (3D Gaussian splatting's)
MIN_ALPHA = 1.0 / 255.0  # a pair fainter than this is not drawn
#: Pairs behind which less light than this is left are not drawn (3D Gaussian splatting's
#: early stop): a pixel changes by less than this.
MIN_TRANSMITTANCE = 1e-4


@njit(cache=True)
def bin_tiles(box, order, left, top, tiles_x, tiles_y):
    """Each tile's splats, front to back: ``starts`` (T + 1,) offsets into ``ids`` (I,), the
    rows of ``order`` whose box touches the tile (tiles row-major over the window from
    (left, top))."""
    counts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    for s in order:
        tx0, tx1, ty0, ty1 = _tile_range(box[s], left, top, tiles_x, tiles_y)
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                counts[ty * tiles_x + tx + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    ids = np.empty(starts[-1], np.int64)
    for s in order:
        tx0, tx1, ty0, ty1 = _tile_range(box[s], left, top, tiles_x, tiles_y)
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                ids[fill[ty * tiles_x + tx]] = s
                fill[ty * tiles_x + tx] += 1
    return starts, ids


@njit(cache=True, inline="always")
def _tile_range(b, left, top, tiles_x, tiles_y):
    """The tiles x0 <= tx < x1, y0 <= ty < y1 that box ``b`` (x0, x1, y0, y1) touches."""
    if b[1] <= b[0] or b[3] <= b[2]:
        return 0, 0, 0, 0
    tx0 = max(int(b[0] - left) // TILE, 0)
    tx1 = min((int(b[1] - left) - 1) // TILE + 1, tiles_x)
    ty0 = max(int(b[2] - top) // TILE, 0)
    ty1 = min((int(b[3] - top) - 1) // TILE + 1, tiles_y)
    return tx0, tx1, ty0, ty1


@njit(cache=True, inline="always")
def _row_gaussian(row, dx, dy):
    """The splat's Gaussian exp(-(a dx^2 + 2 b dx dy + c dy^2) / 2) at offset (dx, dy) and
    the ratio to it of the Gaussian one pixel to the right; that ratio changes by exp(-a) a
    pixel further: along a row, two products a pixel instead of an exponential."""
    a, b, c = row[2], row[3], row[4]
    gaussian = math.exp(-0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))
    return gaussian, math.exp(-a * dx - 0.5 * a - b * dy)


@njit(cache=True, inline="always")
def _tile_rect(tile, tiles_x, window):
    """The pixels x0 <= x < x1, y0 <= y < y1 of ``tile`` in ``window``."""
    left, top, width, height = window
    x0, y0 = left + (tile % tiles_x) * TILE, top + (tile // tiles_x) * TILE
    return x0, min(x0 + TILE, left + width), y0, min(y0 + TILE, top + height)


@njit(cache=True, inline="always")
def _span(row, b, level, py, x0, x1):
    """The pixels xa <= x < xb of row ``py`` (within x0..x1 and the splat's box ``b``) whose
    centres may lie in the splat's ellipse at alpha ``MIN_ALPHA`` (one pixel of margin each
    side; the alpha of each decides): where a dx^2 + 2 b dx dy + c dy^2 <= ``level``,
    2 ln(255 peak)."""
    dy = py + 0.5 - row[1]
    room = (row[3] * dy) ** 2 - row[2] * (row[4] * dy * dy - level)
    if room < 0.0:
        return 0, 0
    half = math.sqrt(room) / row[2]
    middle = row[0] - 0.5 - row[3] * dy / row[2]  # pixel x at dx = -b dy / a
    xa = max(x0, int(b[0]), int(math.floor(middle - half)) - 1)
    xb = min(x1, int(b[1]), int(math.ceil(middle + half)) + 2)
    return xa, xb


@njit(cache=True, inline="always")
def _level(row):
    """2 ln(255 peak): the ellipse's level at alpha ``MIN_ALPHA``; below 0 the splat shows
    nowhere."""
    return 2.0 * math.log(255.0 * row[5]) if row[5] * 255.0 > 1.0 else -1.0


@njit(cache=True, parallel=True)
def forward(table, box, values, index, starts, ids, window, tiles_x, drawn, opacity, last,
            final, shown):
    """Blend every pixel of ``window`` (left, top, width, height) front to back: ``drawn``
    (pixels, M) and ``opacity`` (pixels,) receive the sums of transmittance x alpha x
    values (``values`` (N, M) by splat, ``index`` (F,) a row's splat); ``last`` (pixels,)
    the end in ``ids`` of each pixel's pairs, ``final`` its transmittance behind them, for
    the backward; ``shown`` (F,) is set where a splat has a pair. A tile's splats are taken
    in depth order, each over the pixels of its ellipse (``_span``), the tile's pixels
    keeping their light: a pixel is left once its light is below ``MIN_TRANSMITTANCE``."""
    left, top, width, _ = window
    for tile in prange(len(starts) - 1):
        x0, x1, y0, y1 = _tile_rect(tile, tiles_x, window)
        light = np.ones(TILE * TILE)
        end = np.full(TILE * TILE, starts[tile])
        tile_drawn = np.zeros((TILE * TILE, values.shape[1]))
        tile_opacity = np.zeros(TILE * TILE)
        open_pixels = (x1 - x0) * (y1 - y0)
        for j in range(starts[tile], starts[tile + 1]):
            if open_pixels == 0:
                break
            s = ids[j]
            row, b, splat = table[s], box[s], index[s]
            level = _level(row)
            if level < 0.0:
                continue
            step = math.exp(-row[2])
            for py in range(max(y0, int(b[2])), min(y1, int(b[3]))):
                xa, xb = _span(row, b, level, py, x0, x1)
                if xa >= xb:
                    continue
                gaussian, ratio = _row_gaussian(row, xa + 0.5 - row[0], py + 0.5 - row[1])
                for px in range(xa, xb):
                    k = (py - y0) * TILE + px - x0
                    alpha = min(MAX_ALPHA, row[5] * gaussian)
                    gaussian, ratio = gaussian * ratio, ratio * step
                    if light[k] < MIN_TRANSMITTANCE or alpha < MIN_ALPHA:
                        continue
                    weight = light[k] * alpha
                    for m in range(values.shape[1]):
                        tile_drawn[k, m] += weight * values[splat, m]
                    tile_opacity[k] += weight
                    light[k] *= 1.0 - alpha
                    end[k] = j + 1
                    shown[s] = True
                    if light[k] < MIN_TRANSMITTANCE:
                        open_pixels -= 1
        for py in range(y0, y1):
            for px in range(x0, x1):
                k, pixel = (py - y0) * TILE + px - x0, (py - top) * width + px - left
                last[pixel], final[pixel] = end[k], light[k]
                drawn[pixel] = tile_drawn[k]
                opacity[pixel] = tile_opacity[k]


@njit(cache=True, parallel=True)
def backward(table, box, values, index, starts, ids, window, tiles_x, last, final,
             grad_drawn, grad_opacity, geometry, grad_table, grad_values):
    """The gradients of ``forward``'s sums with respect to the projections and the values,
    from the upstream ``grad_drawn`` (pixels, M) and ``grad_opacity`` (pixels,): into
    ``grad_values`` (C, N, M) and, with ``geometry``, ``grad_table`` (C, F, 6; else one
    unused slice), one slice for each of C chunks of the tiles (summed by the caller).

    A tile's splats are walked back to front, each over its ellipse's pixels, each pixel
    from its final transmittance: the light in front of pair i is that behind it over
    1 - alpha_i, and d/d alpha_i of the pixel's sum is light_i x q_i less what the pairs
    behind i send over 1 - alpha_i (q: the upstream gradient's product with the pair's
    values, plus the opacity's); then through the clamp at ``MAX_ALPHA``, the peak opacity
    and the Gaussian's exponent."""
    left, top, width, _ = window
    chunks = grad_values.shape[0]
    n_tiles = len(starts) - 1
    for chunk in prange(chunks):
        g_table = grad_table[0] if grad_table.shape[0] == 1 else grad_table[chunk]
        g_values = grad_values[chunk]
        light, behind = np.empty(TILE * TILE), np.empty(TILE * TILE)
        tile_last = np.empty(TILE * TILE, np.int64)
        tile_up = np.empty((TILE * TILE, values.shape[1] + 1))  # upstream, opacity's last
        splat_grad, value_grad = np.empty(6), np.empty(values.shape[1])
        for tile in range(chunk, n_tiles, chunks):
            x0, x1, y0, y1 = _tile_rect(tile, tiles_x, window)
            for py in range(y0, y1):
                for px in range(x0, x1):
                    k, pixel = (py - y0) * TILE + px - x0, (py - top) * width + px - left
                    light[k], behind[k], tile_last[k] = final[pixel], 0.0, last[pixel]
                    tile_up[k, :-1] = grad_drawn[pixel]
                    tile_up[k, -1] = grad_opacity[pixel]
            for j in range(starts[tile + 1] - 1, starts[tile] - 1, -1):
                s = ids[j]
                row, b, splat = table[s], box[s], index[s]
                level = _level(row)
                if level < 0.0:
                    continue
                step = math.exp(-row[2])
                splat_grad[:] = 0.0
                value_grad[:] = 0.0
                for py in range(max(y0, int(b[2])), min(y1, int(b[3]))):
                    xa, xb = _span(row, b, level, py, x0, x1)
                    if xa >= xb:
                        continue
                    dy = py + 0.5 - row[1]
                    next_gaussian, ratio = _row_gaussian(row, xa + 0.5 - row[0], dy)
                    for px in range(xa, xb):
                        gaussian = next_gaussian
                        alpha = min(MAX_ALPHA, row[5] * gaussian)
                        next_gaussian, ratio = gaussian * ratio, ratio * step
                        k = (py - y0) * TILE + px - x0
                        if j >= tile_last[k] or alpha < MIN_ALPHA:
                            continue
                        keep = 1.0 / (1.0 - alpha)
                        light[k] *= keep
                        weight = light[k] * alpha
                        q = tile_up[k, -1]
                        for m in range(values.shape[1]):
                            value_grad[m] += weight * tile_up[k, m]
                            q += tile_up[k, m] * values[splat, m]
                        if geometry:
                            _add_table_gradient(splat_grad, row, alpha, px + 0.5 - row[0], dy,
                                                gaussian, light[k] * q - behind[k] * keep)
                        behind[k] += weight * q
                for m in range(values.shape[1]):
                    g_values[splat, m] += value_grad[m]
                if geometry:
                    for n in range(6):
                        g_table[s, n] += splat_grad[n]


@njit(cache=True, inline="always")
def _add_table_gradient(out, row, alpha, dx, dy, gaussian, grad_alpha):
    """Add to ``out`` (6,) d alpha / d row times ``grad_alpha``: through the clamp at
    ``MAX_ALPHA``, the peak opacity and the Gaussian's exponent."""
    if alpha >= MAX_ALPHA:
        return
    grad_peak = grad_alpha * gaussian
    power = grad_peak * row[5]
    out[0] += power * (row[2] * dx + row[3] * dy)
    out[1] += power * (row[3] * dx + row[4] * dy)
    out[2] += -0.5 * power * dx * dx
    out[3] += -power * dx * dy
    out[4] += -0.5 * power * dy * dy
    out[5] += grad_peak


def chunks() -> int:
    """How many slices ``backward`` sums its gradients in: one a thread."""
    return numba.get_num_threads()
