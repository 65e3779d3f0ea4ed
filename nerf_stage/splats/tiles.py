"""The CPU rasteriser's kernels: splats binned into tiles of the view, then each tile's pixels
blended front to back and, backwards, their gradients, compiled with numba and run in
parallel over tiles (gsplat's design, on the CPU).

Splats come as ``rasterise``'s projections: ``table`` (F, 6) rows of centre u, v, inverse
covariance a, b, c and peak opacity; ``box`` (F, 4) the pixels x0 <= x < x1, y0 <= y < y1
a splat may touch (its ellipse's box at alpha 1/255, cut at a reach); ``order`` the rows to
draw, front to back. A pair (pixel, splat) counts when its alpha is at least 1/255 and at
least ``MIN_TRANSMITTANCE`` of the pixel's light is left in front of it, as in
``rasterise._band``. Arithmetic is float64; nothing is allocated per pair.

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
def _alpha(row, b, px, py):
    """Alpha of the splat projected as ``row`` at pixel (px, py), 0 outside its box ``b``
    or below ``MIN_ALPHA``; and the offsets dx, dy and the Gaussian that make it."""
    if px < b[0] or px >= b[1] or py < b[2] or py >= b[3]:
        return 0.0, 0.0, 0.0, 0.0
    dx = px + 0.5 - row[0]
    dy = py + 0.5 - row[1]
    gaussian = math.exp(-0.5 * (row[2] * dx * dx + 2.0 * row[3] * dx * dy + row[4] * dy * dy))
    alpha = min(MAX_ALPHA, row[5] * gaussian)
    if alpha < MIN_ALPHA:
        return 0.0, dx, dy, gaussian
    return alpha, dx, dy, gaussian


@njit(cache=True, parallel=True)
def forward(table, box, values, index, starts, ids, window, tiles_x, drawn, opacity, last,
            final, shown):
    """Blend every pixel of ``window`` (left, top, width, height) front to back: ``drawn``
    (pixels, M) and ``opacity`` (pixels,) receive the sums of transmittance x alpha x
    values (``values`` (N, M) by splat, ``index`` (F,) a row's splat); ``last`` (pixels,)
    the end in ``ids`` of each pixel's pairs, ``final`` its transmittance behind them, for
    the backward; ``shown`` (F,) is set where a splat has a pair."""
    left, top, width, height = window
    for tile in prange(len(starts) - 1):
        ty, tx = tile // tiles_x, tile % tiles_x
        for py in range(top + ty * TILE, min(top + (ty + 1) * TILE, top + height)):
            for px in range(left + tx * TILE, min(left + (tx + 1) * TILE, left + width)):
                pixel = (py - top) * width + (px - left)
                light, end = 1.0, starts[tile]
                for j in range(starts[tile], starts[tile + 1]):
                    s = ids[j]
                    alpha, _, _, _ = _alpha(table[s], box[s], px, py)
                    if alpha == 0.0:
                        continue
                    if light < MIN_TRANSMITTANCE:
                        break
                    weight = light * alpha
                    splat = index[s]
                    for m in range(values.shape[1]):
                        drawn[pixel, m] += weight * values[splat, m]
                    opacity[pixel] += weight
                    light *= 1.0 - alpha
                    end = j + 1
                    shown[s] = True
                last[pixel], final[pixel] = end, light


@njit(cache=True, parallel=True)
def backward(table, box, values, index, starts, ids, window, tiles_x, last, final,
             grad_drawn, grad_opacity, geometry, grad_table, grad_values):
    """The gradients of ``forward``'s sums with respect to the projections and the values,
    from the upstream ``grad_drawn`` (pixels, M) and ``grad_opacity`` (pixels,): into
    ``grad_values`` (C, N, M) and, with ``geometry``, ``grad_table`` (C, F, 6; else one
    unused slice), one slice for each of C chunks of the tiles (summed by the caller).

    Each pixel's pairs are walked back to front from its final transmittance: the light in
    front of pair i is that behind it over 1 - alpha_i, and d/d alpha_i of the pixel's sum
    is light_i x q_i less what the pairs behind i send over 1 - alpha_i (q: the upstream
    gradient's product with the pair's values, plus the opacity's); then through the clamp
    at ``MAX_ALPHA``, the peak opacity and the Gaussian's exponent."""
    left, top, width, height = window
    chunks = grad_values.shape[0]
    n_tiles = len(starts) - 1
    for chunk in prange(chunks):
        g_table = grad_table[min(chunk, grad_table.shape[0] - 1)]
        g_values = grad_values[chunk]
        for tile in range(chunk, n_tiles, chunks):
            ty, tx = tile // tiles_x, tile % tiles_x
            for py in range(top + ty * TILE, min(top + (ty + 1) * TILE, top + height)):
                for px in range(left + tx * TILE, min(left + (tx + 1) * TILE, left + width)):
                    pixel = (py - top) * width + (px - left)
                    light, behind = final[pixel], 0.0
                    up_opacity = grad_opacity[pixel]
                    for j in range(last[pixel] - 1, starts[tile] - 1, -1):
                        s = ids[j]
                        alpha, dx, dy, gaussian = _alpha(table[s], box[s], px, py)
                        if alpha == 0.0:
                            continue
                        light /= 1.0 - alpha
                        weight = light * alpha
                        splat = index[s]
                        q = up_opacity
                        for m in range(values.shape[1]):
                            g_values[splat, m] += weight * grad_drawn[pixel, m]
                            q += grad_drawn[pixel, m] * values[splat, m]
                        if geometry:
                            grad_alpha = light * q - behind / (1.0 - alpha)
                            _add_table_gradient(g_table[s], table[s], alpha, dx, dy,
                                                gaussian, grad_alpha)
                        behind += weight * q


@njit(cache=True, inline="always")
def _add_table_gradient(out, row, alpha, dx, dy, gaussian, grad_alpha):
    """Add to ``out`` (6,) d alpha / d row times ``grad_alpha`` (``_alpha``'s chain)."""
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
