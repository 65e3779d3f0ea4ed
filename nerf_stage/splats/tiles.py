"""The CPU rasteriser's kernels: splats binned into tiles of the view, then each tile's pixels
blended front to back and, backwards, their gradients, compiled with numba and run in
parallel over tiles (gsplat's design, on the CPU).

Splats come as ``projection.project`` makes them, gathered front to back (``gathered``): a
``table`` (D, 9) of rows U, V (centre), A, B, C (inverse covariance), PEAK (opacity), and
what every tile needs of a splat once: LEVEL (the ellipse's level at alpha 1/255), STEP
(exp(-a)) and INV_A (1 / a); ``box`` (D, 4) the pixels x0 <= x < x1, y0 <= y < y1 a splat
may touch (its ellipse's box at alpha 1/255, cut at a reach); ``values`` (D, M) each row's
values. Rows in depth order keep a tile's reads ascending in memory.

A pair (pixel, splat) counts when its alpha is at least 1/255 and at least
``MIN_TRANSMITTANCE`` of the pixel's light is left in front of it, as in ``pairs._band``.
Within a tile the splats are taken in depth order, each over the pixels of its ellipse
only, the tile's pixels keeping their light (gsplat walks pixels and tests every splat;
without a GPU's threads, testing only the ellipse's pixels is what bounds the work by the
pairs); backwards, from the last splat any of its pixels blended. Arithmetic is float64;
nothing is allocated per pair.

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
#: Pixels of slack at each end of a row's span in the ellipse (rounding; alpha decides).
SPAN_SLACK = 1e-6
U, V, A, B, C, PEAK, LEVEL, STEP, INV_A = range(9)  # the columns of a gathered table
NO_PAIRS, COUNT_PAIRS, KEEP_PAIRS = range(3)  # what ``forward`` records of its pairs


@njit(cache=True, parallel=True)
def gathered(table, box, values, rows):
    """The ``rows`` (D,) of a projection's ``table`` (F, 6) and ``box`` (F, >= 4), with the
    columns LEVEL, STEP and INV_A added, and ``values`` (D, M) already of those rows, all
    float64 and contiguous: what ``forward`` and ``backward`` read."""
    out, out_box = np.empty((len(rows), 9)), np.empty((len(rows), 4))
    out_values = np.empty(values.shape)
    for d in prange(len(rows)):
        r = rows[d]
        for n in range(6):
            out[d, n] = table[r, n]
        for n in range(4):
            out_box[d, n] = box[r, n]
        for m in range(values.shape[1]):
            out_values[d, m] = values[d, m]
        peak = out[d, PEAK]
        out[d, LEVEL] = 2.0 * math.log(255.0 * peak) if 255.0 * peak > 1.0 else -1.0
        out[d, STEP] = math.exp(-out[d, A])
        out[d, INV_A] = 1.0 / out[d, A]
    return out, out_box, out_values


@njit(cache=True)
def bin_tiles(box, left, top, tiles_x, tiles_y):
    """Each tile's rows, front to back: ``starts`` (T + 1,) offsets into ``ids`` (I,), the
    rows of ``box`` (D, 4, in depth order) that touch the tile (tiles row-major over the
    window from (left, top))."""
    counts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    for d in range(len(box)):
        tx0, tx1, ty0, ty1 = _tile_range(box, d, left, top, tiles_x, tiles_y)
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                counts[ty * tiles_x + tx + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    ids = np.empty(starts[-1], np.int32)
    for d in range(len(box)):
        tx0, tx1, ty0, ty1 = _tile_range(box, d, left, top, tiles_x, tiles_y)
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                ids[fill[ty * tiles_x + tx]] = d
                fill[ty * tiles_x + tx] += 1
    return starts, ids


@njit(cache=True, inline="always")
def _tile_range(box, d, left, top, tiles_x, tiles_y):
    """The tiles x0 <= tx < x1, y0 <= ty < y1 that row ``d``'s box (x0, x1, y0, y1)
    touches."""
    if box[d, 1] <= box[d, 0] or box[d, 3] <= box[d, 2]:
        return 0, 0, 0, 0
    tx0 = max(int(box[d, 0] - left) // TILE, 0)
    tx1 = min((int(box[d, 1] - left) - 1) // TILE + 1, tiles_x)
    ty0 = max(int(box[d, 2] - top) // TILE, 0)
    ty1 = min((int(box[d, 3] - top) - 1) // TILE + 1, tiles_y)
    return tx0, tx1, ty0, ty1


@njit(cache=True, inline="always")
def _row_gaussian(table, d, dx, dy):
    """Row ``d``'s Gaussian exp(-(a dx^2 + 2 b dx dy + c dy^2) / 2) at offset (dx, dy) and
    the ratio to it of the Gaussian one pixel to the right; that ratio changes by exp(-a) a
    pixel further: along a row, two products a pixel instead of an exponential."""
    a, b, c = table[d, A], table[d, B], table[d, C]
    gaussian = math.exp(-0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))
    return gaussian, math.exp(-a * dx - 0.5 * a - b * dy)


@njit(cache=True, inline="always")
def _tile_rect(tile, tiles_x, window):
    """The pixels x0 <= x < x1, y0 <= y < y1 of ``tile`` in ``window``."""
    left, top, width, height = window
    x0, y0 = left + (tile % tiles_x) * TILE, top + (tile // tiles_x) * TILE
    return x0, min(x0 + TILE, left + width), y0, min(y0 + TILE, top + height)


@njit(cache=True, inline="always")
def _span(table, box, d, py, x0, x1):
    """The pixels xa <= x < xb of row ``py`` (within x0..x1 and row ``d``'s box) whose
    centres lie in its ellipse at alpha ``MIN_ALPHA``: where a dx^2 + 2 b dx dy + c dy^2
    <= LEVEL, 2 ln(255 peak)."""
    dy = py + 0.5 - table[d, V]
    b_dy = table[d, B] * dy
    room = b_dy * b_dy - table[d, A] * (table[d, C] * dy * dy - table[d, LEVEL])
    if room < 0.0:
        return 0, 0
    half = math.sqrt(room) * table[d, INV_A]
    middle = table[d, U] - 0.5 - b_dy * table[d, INV_A]  # pixel x at dx = -b dy / a
    xa = max(x0, int(box[d, 0]), int(math.ceil(middle - half - SPAN_SLACK)))
    xb = min(x1, int(box[d, 1]), int(math.floor(middle + half + SPAN_SLACK)) + 1)
    return xa, xb


@njit(cache=True, parallel=True)
def forward(table, box, values, starts, ids, window, tiles_x, chunks, drawn, opacity, last,
            final, shown, pairs):
    """Blend every pixel of ``window`` (left, top, width, height) front to back: ``drawn``
    (pixels, M) and ``opacity`` (pixels,) receive the sums of transmittance x alpha x
    ``values`` (D, M); ``last`` (pixels,) the end in ``ids`` of each pixel's pairs,
    ``final`` its transmittance behind them, for the backward; ``shown`` (D,) is set where
    a row has a pair. A tile's rows are taken in depth order, each over the pixels of its
    ellipse (``_span``), the tile's pixels keeping their light: a pixel is left once its
    light is below ``MIN_TRANSMITTANCE``. The tiles are dealt to ``chunks`` threads in turn.

    ``pairs`` (``NO_PAIRS``, ``COUNT_PAIRS`` or ``KEEP_PAIRS``, offsets (pixels + 1,),
    pixel, row, contribution (P,)) records the pairs: counted by pixel into offsets at
    pixel + 1, or, from offsets (their running sum), each pair's pixel (of the window),
    row and contribution (transmittance x alpha) kept, by pixel, front to back."""
    record, offsets, kept_pixel, kept_row, kept_contribution = pairs
    left, top, width, _ = window
    channels, n_tiles = values.shape[1], len(starts) - 1
    for chunk in prange(chunks):
        light = np.empty(TILE * TILE)
        end = np.empty(TILE * TILE, np.int64)
        tile_drawn = np.empty((TILE * TILE, channels))
        tile_opacity = np.empty(TILE * TILE)
        for tile in range(chunk, n_tiles, chunks):
            x0, x1, y0, y1 = _tile_rect(tile, tiles_x, window)
            light[:], end[:], tile_drawn[:], tile_opacity[:] = 1.0, starts[tile], 0.0, 0.0
            open_pixels = (x1 - x0) * (y1 - y0)
            for j in range(starts[tile], starts[tile + 1]):
                if open_pixels == 0:
                    break
                d = ids[j]
                if table[d, LEVEL] < 0.0:
                    continue
                peak, step, hit = table[d, PEAK], table[d, STEP], False
                for py in range(max(y0, int(box[d, 2])), min(y1, int(box[d, 3]))):
                    xa, xb = _span(table, box, d, py, x0, x1)
                    if xa >= xb:
                        continue
                    gaussian, ratio = _row_gaussian(table, d, xa + 0.5 - table[d, U],
                                                    py + 0.5 - table[d, V])
                    first = (py - y0) * TILE - x0
                    for px in range(xa, xb):
                        k = first + px
                        alpha = min(MAX_ALPHA, peak * gaussian)
                        gaussian, ratio = gaussian * ratio, ratio * step
                        t = light[k]
                        if t < MIN_TRANSMITTANCE or alpha < MIN_ALPHA:
                            continue
                        weight = t * alpha
                        for m in range(channels):
                            tile_drawn[k, m] += weight * values[d, m]
                        tile_opacity[k] += weight
                        if record != NO_PAIRS:
                            place = (py - top) * width + px - left
                            if record == COUNT_PAIRS:
                                offsets[place + 1] += 1
                            else:
                                at = offsets[place]
                                kept_pixel[at], kept_row[at] = place, d
                                kept_contribution[at], offsets[place] = weight, at + 1
                        t *= 1.0 - alpha
                        light[k], end[k], hit = t, j + 1, True
                        if t < MIN_TRANSMITTANCE:
                            open_pixels -= 1
                if hit:
                    shown[d] = True
            for py in range(y0, y1):
                for px in range(x0, x1):
                    k, pixel = (py - y0) * TILE + px - x0, (py - top) * width + px - left
                    last[pixel], final[pixel] = end[k], light[k]
                    opacity[pixel] = tile_opacity[k]
                    for m in range(channels):
                        drawn[pixel, m] = tile_drawn[k, m]


@njit(cache=True, parallel=True)
def backward(table, box, values, starts, ids, window, tiles_x, last, final, grad_drawn,
             grad_opacity, geometry, grad_table, grad_values):
    """The gradients of ``forward``'s sums with respect to the rows' projections and
    values, from the upstream ``grad_drawn`` (pixels, M) and ``grad_opacity`` (pixels,):
    into ``grad_values`` (T, D, M) and, with ``geometry``, ``grad_table`` (T, D, 6; else
    one unused slice), a slice for each of the T threads (summed by the caller).

    A tile's rows are walked back to front from the last that any of its pixels blended,
    each over its ellipse's pixels, each pixel
    from its final transmittance: the light in front of pair i is that behind it over
    1 - alpha_i, and d/d alpha_i of the pixel's sum is light_i x q_i less what the pairs
    behind i send over 1 - alpha_i (q: the upstream gradient's product with the pair's
    values, plus the opacity's); then through the clamp at ``MAX_ALPHA``, the peak opacity
    and the Gaussian's exponent."""
    left, top, width, _ = window
    channels, n_tiles, chunks = values.shape[1], len(starts) - 1, grad_values.shape[0]
    for chunk in prange(chunks):
        g_table = grad_table[0] if grad_table.shape[0] == 1 else grad_table[chunk]
        g_values = grad_values[chunk]
        light, behind = np.empty(TILE * TILE), np.empty(TILE * TILE)
        tile_last = np.empty(TILE * TILE, np.int64)
        tile_up = np.empty((TILE * TILE, channels + 1))  # upstream, opacity's last
        splat_grad, value_grad = np.empty(6), np.empty(channels)
        for tile in range(chunk, n_tiles, chunks):
            x0, x1, y0, y1 = _tile_rect(tile, tiles_x, window)
            end = starts[tile]  # behind the last pair of any of the tile's pixels
            for py in range(y0, y1):
                for px in range(x0, x1):
                    k, pixel = (py - y0) * TILE + px - x0, (py - top) * width + px - left
                    light[k], behind[k], tile_last[k] = final[pixel], 0.0, last[pixel]
                    end = max(end, last[pixel])
                    for m in range(channels):
                        tile_up[k, m] = grad_drawn[pixel, m]
                    tile_up[k, channels] = grad_opacity[pixel]
            for j in range(end - 1, starts[tile] - 1, -1):
                d = ids[j]
                if table[d, LEVEL] < 0.0:
                    continue
                peak, step = table[d, PEAK], table[d, STEP]
                splat_grad[:] = 0.0
                value_grad[:] = 0.0
                for py in range(max(y0, int(box[d, 2])), min(y1, int(box[d, 3]))):
                    xa, xb = _span(table, box, d, py, x0, x1)
                    if xa >= xb:
                        continue
                    dy = py + 0.5 - table[d, V]
                    next_gaussian, ratio = _row_gaussian(table, d, xa + 0.5 - table[d, U], dy)
                    first = (py - y0) * TILE - x0
                    for px in range(xa, xb):
                        gaussian = next_gaussian
                        alpha = min(MAX_ALPHA, peak * gaussian)
                        next_gaussian, ratio = gaussian * ratio, ratio * step
                        k = first + px
                        if j >= tile_last[k] or alpha < MIN_ALPHA:
                            continue
                        keep = 1.0 / (1.0 - alpha)
                        light[k] *= keep
                        weight = light[k] * alpha
                        q = tile_up[k, channels]
                        for m in range(channels):
                            value_grad[m] += weight * tile_up[k, m]
                            q += tile_up[k, m] * values[d, m]
                        if geometry and alpha < MAX_ALPHA:
                            _add_table_gradient(splat_grad, table, d, px + 0.5 - table[d, U],
                                                dy, gaussian,
                                                light[k] * q - behind[k] * keep)
                        behind[k] += weight * q
                for m in range(channels):
                    g_values[d, m] += value_grad[m]
                if geometry:
                    for n in range(6):
                        g_table[d, n] += splat_grad[n]


@njit(cache=True, inline="always")
def _add_table_gradient(out, table, d, dx, dy, gaussian, grad_alpha):
    """Add to ``out`` (6,) d alpha / d row ``d`` (below the clamp at ``MAX_ALPHA``) times
    ``grad_alpha``: through the peak opacity and the Gaussian's exponent."""
    grad_peak = grad_alpha * gaussian
    power = grad_peak * table[d, PEAK]
    a, b, c = table[d, A], table[d, B], table[d, C]
    out[0] += power * (a * dx + b * dy)
    out[1] += power * (b * dx + c * dy)
    out[2] += -0.5 * power * dx * dx
    out[3] += -power * dx * dy
    out[4] += -0.5 * power * dy * dy
    out[5] += grad_peak


def chunks() -> int:
    """How many slices ``backward`` sums its gradients in: one a thread."""
    return numba.get_num_threads()


def no_pairs() -> tuple:
    """``forward``'s ``pairs`` when none are recorded."""
    return (NO_PAIRS, np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int32),
            np.zeros(0))
