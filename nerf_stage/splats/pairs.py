"""Drawing a view as (pixel, splat) pairs in PyTorch: each splat's ellipse walked row by
row (a band of the view's rows at a time on a CPU), the pairs sorted by pixel, then front
to back, and blended by their transmittance (a float64 running sum of logarithms); a
custom backward that keeps 12 bytes a pair. CUDA draws so, and makes the palette stage's
footprints so (``draw(..., keep_pairs=True)``); a CPU with ``rasterise.TILED`` off too.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch

from ..data.cameras import Intrinsics
from .projection import project
from .tiles import MAX_ALPHA, MIN_TRANSMITTANCE

#: Pixels of a view whose pairs are found at once on a CPU (``_band``): the pairs tried are
#: held for a band, not the view, and their sorts stay short
#: (docs/decisions/0013-rasteriser-bands.md). On CUDA a view is one band: its memory holds
#: the pairs, and every band would add its kernel launches and synchronisations to a step.
BAND_PIXELS = 1 << 14


class PairComposite(torch.autograd.Function):
    """(pixels, M) values and (pixels,) opacity of a view's ``window``, blended from its
    pairs: (P,) ``pixel`` (of the window) and ``ids`` (of the projections ``table``, (F, 6):
    ``_alpha``'s; of the splats ``index``), sorted by pixel, then front to back, with
    ``light`` (P,) the transmittance in front of each; ``counts``: the pairs of each band.

    Only the pairs' pixel, projection and light are kept for the backward (12 bytes a
    pair): alpha and the blend are made again a band at a time (``_blends``), so that what a
    step holds grows with its pairs by that much and no more. The backward is 3D Gaussian
    splatting's: d/d alpha_i of a pixel's sum is light_i x q_i minus what the pairs behind i
    send, over 1 - alpha_i (q: the upstream gradient's product with the pair's values, plus
    the opacity's), then through ``_alpha`` by hand."""

    @staticmethod
    def forward(ctx, table, values, index, pixel, ids, light, counts, window):
        ctx.save_for_backward(table, values, index, pixel, ids, light)
        ctx.counts, ctx.window = counts, window
        return draw_bands(table, values, index, pixel, ids, light, counts, window)

    @staticmethod
    def backward(ctx, grad_drawn, grad_opacity):
        table, values, index, pixel, ids, light = ctx.saved_tensors
        geometry = ctx.needs_input_grad[0]  # False: the geometry is frozen
        grad_values = torch.zeros_like(values)
        grad_table = torch.zeros_like(table) if geometry else None
        for blend in _blends(table, index, pixel, ids, light, ctx.counts, ctx.window):
            upstream = grad_drawn.index_select(0, blend.pixel)  # (p, M)
            contribution = blend.light * blend.alpha
            grad_values.index_add_(0, blend.splat, contribution[:, None] * upstream)
            if not geometry:
                continue
            q = ((upstream * values.index_select(0, blend.splat)).sum(1)
                 + grad_opacity.index_select(0, blend.pixel))
            # what the pairs behind each one send: its pixel's running sum at its last pair,
            # less its own (a band's pairs are whole pixels')
            running = torch.cumsum((contribution * q).double(), 0)
            local = blend.pixel - blend.pixel[0]
            last = _first_pair(local, int(local[-1]) + 1, last=True)
            behind = (running.index_select(0, last) - running).to(q.dtype)
            grad_alpha = blend.light * q - behind / (1 - blend.alpha)
            # through the clamp at MAX_ALPHA, the peak opacity and the Gaussian's exponent
            _, _, a, b, c, peak = blend.rows.unbind(1)
            dx, dy = blend.dx, blend.dy
            grad_peak = torch.where(blend.alpha < MAX_ALPHA, grad_alpha * blend.gaussian, 0)
            grad_power = grad_peak * peak
            grad_table.index_add_(0, blend.ids, torch.stack([
                grad_power * (a * dx + b * dy), grad_power * (b * dx + c * dy),
                -0.5 * grad_power * dx * dx, -grad_power * dx * dy,
                -0.5 * grad_power * dy * dy, grad_peak], 1))
        return grad_table, grad_values, None, None, None, None, None, None


class _Blend(NamedTuple):
    """One band's pairs made again from what ``PairComposite`` keeps: (p,) pixel (of the
    window), projection (of the table) and splat indices, light in front, alpha; (p, 6)
    rows of the table; (p,) offsets dx, dy from the splat's centre and its Gaussian
    (``_alpha``)."""

    pixel: torch.Tensor
    ids: torch.Tensor
    splat: torch.Tensor
    light: torch.Tensor
    alpha: torch.Tensor
    rows: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    gaussian: torch.Tensor


def _blends(table, index, pixel, ids, light, counts, window) -> Iterator[_Blend]:
    """``PairComposite``'s pairs, a band (of ``counts``) at a time."""
    first = 0
    for count in counts:
        # int64 indices: index_add_ of rows takes a slow path with int32 ones
        part, band = pixel[first:first + count].long(), ids[first:first + count].long()
        rows = table.index_select(0, band)
        alpha, dx, dy, gaussian = _alpha(rows, *_position(part, window))
        yield _Blend(part, band, index.index_select(0, band), light[first:first + count],
                     alpha, rows, dx, dy, gaussian)
        first += count


def draw_bands(table, values, index, pixel, ids, light, counts, window,
                keep: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``PairComposite``'s (pixels, M) values and (pixels,) opacity, a band at a time; with
    ``keep``, each pair's ``light`` is replaced by its contribution (in place)."""
    pixels = window[2] * window[3]
    drawn, opacity = values.new_zeros(pixels, values.shape[1]), values.new_zeros(pixels)
    for blend in _blends(table, index, pixel, ids, light, counts, window):
        contribution = blend.light * blend.alpha
        drawn.index_add_(0, blend.pixel,
                         contribution[:, None] * values.index_select(0, blend.splat))
        opacity.index_add_(0, blend.pixel, contribution)
        if keep:
            blend.light.copy_(contribution)  # a view of ``light``
    return drawn, opacity


def _position(pixel: torch.Tensor, window: tuple[int, int, int, int]):
    """(P,) x and (P,) y in the view of pixels of its ``window`` (x, y, width, height)."""
    left, top, width, _ = window
    return pixel % width + left, torch.div(pixel, width, rounding_mode="floor") + top


def _first_pair(pixel: torch.Tensor, pixels: int, last: bool = False) -> torch.Tensor:
    """(P,) index of the first (or ``last``) pair of each pair's pixel, of ``pixels``
    (``pixel`` sorted): from the pixels' counts of pairs."""
    counts = torch.bincount(pixel, minlength=pixels)
    ends = torch.cumsum(counts, 0)
    return (ends - 1 if last else ends - counts).index_select(0, pixel)


def _transmittance(pixel: torch.Tensor, alpha: torch.Tensor, pixels: int) -> torch.Tensor:
    """(P,) light left in front of each pair (``pixel``, of ``pixels``; ``alpha``), sorted
    by pixel, then front to back: a product over its pixel's earlier pairs, summed as
    logarithms in float64 (a view's running sum spans all of its pairs)."""
    log_keep = torch.log1p(-alpha).double()
    running = torch.cumsum(log_keep, 0) - log_keep  # up to each pair, itself excluded
    before = running - running.index_select(0, _first_pair(pixel, pixels))
    return torch.exp(before.to(alpha.dtype))  # local sums: float32 holds them


def pairs(centres, covariances, opacities, pose, camera: Intrinsics, reach: int | None,
           info: dict | None, window: tuple[int, int, int, int]):
    """The (pixel, splat, alpha) pairs of one view's ``window`` above 1/255 with at least
    ``MIN_TRANSMITTANCE`` of light left in front of them, sorted by pixel (of the window),
    then front to back, and that light (detached); None when no splat shows (``draw``'s
    ``info`` filled on the way)."""
    projected = project(centres, covariances, opacities, pose, camera, reach, info, window)
    if projected is None:
        return None
    table, box, index, drawn = projected
    left, top, width, height = window
    rows = height if centres.is_cuda else max(1, BAND_PIXELS // width)
    bands = [_band(table, box, drawn, window, y, min(y + rows, top + height))
             for y in range(top, top + height, rows)]
    bands = [band for band in bands if band is not None]
    if not bands:
        return None
    pixel, ids, light = (torch.cat(part) for part in zip(*bands))
    return table, index, pixel, ids, light, tuple(len(band[0]) for band in bands)


@torch.no_grad()
def _band(table: torch.Tensor, box: torch.Tensor, drawn: torch.Tensor,
          window: tuple[int, int, int, int], first: int, end: int):
    """The pairs that show in rows ``first`` to ``end`` (excluded) of the view's ``window``:
    (P,) int32 pixel of the window, int32 splat of ``table`` and the light in front,
    sorted by pixel, then front to back; None when there are none. ``table`` (F, 6): each
    splat's projection (``_alpha``); ``box`` (F, 5): its x0, x1, y0, y1 and the Mahalanobis
    ``level`` of 1/255; ``drawn``: the splats to draw, front to back. A band at a time, the
    pairs tried are held for the band's rows only."""
    left, top, width, height = window
    x0, x1, y0, y1, level = box.T
    y0, y1 = y0.clamp(first, end), y1.clamp(first, end)
    drawn = drawn[(y1.index_select(0, drawn) > y0.index_select(0, drawn))]
    if not len(drawn):
        return None
    # the rows of each splat's box, and in each row the pixels inside its ellipse
    row_splat, py = _spans(drawn, y0.index_select(0, drawn).long(),
                           y1.index_select(0, drawn).long())
    row_u, row_v, ca, cb, cc, peak = table.index_select(0, row_splat).T
    row_x0, row_x1, row_level = torch.stack([x0, x1, level], 1).index_select(0, row_splat).T
    dy = py + 0.5 - row_v
    room = (cb * dy) ** 2 - ca * (cc * dy * dy - row_level ** 2)
    half = torch.sqrt(room.clamp(min=0)) / ca
    middle = row_u - 0.5 - cb * dy / ca  # pixel x + 0.5 - u = dx
    first_x = torch.maximum(torch.ceil(middle - half), row_x0).long()
    last_x = torch.minimum(torch.floor(middle + half), row_x1 - 1).long()
    row, px = _spans(torch.arange(len(py), device=py.device), first_x,
                     torch.where(room >= 0, torch.maximum(last_x + 1, first_x), first_x))
    # alpha along a row: the row's peak times a Gaussian in px - middle (the ellipse's
    # quadratic form with the square completed in dx)
    row_peak = peak * torch.exp(-0.5 * (cc - cb * cb / ca) * dy * dy)
    at_middle, spread, at_peak = torch.stack([middle, ca, row_peak], 1).index_select(0, row).T
    alpha = torch.clamp(at_peak * torch.exp(-0.5 * spread * (px - at_middle) ** 2),
                        max=MAX_ALPHA)
    alpha = torch.where(alpha >= 1 / 255, alpha, 0)  # no light kept: dropped below
    pixel = (((py - top) * width - left).index_select(0, row) + px).int()
    pixel, order = torch.sort(pixel, stable=True)  # by pixel, still front to back
    alpha = alpha.index_select(0, order)
    light = _transmittance(pixel, alpha, width * height)
    # the light kept is a prefix of each pixel's pairs: their light stays as it is
    kept = torch.nonzero((light >= MIN_TRANSMITTANCE) & (alpha > 0))[:, 0]
    if not len(kept):
        return None
    row = row.index_select(0, order.index_select(0, kept))
    return (pixel.index_select(0, kept), row_splat.index_select(0, row).int(),
            light.index_select(0, kept))


def _spans(owners: torch.Tensor, start: torch.Tensor,
           stop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each of ``owners`` (N,) with the whole numbers from its ``start`` to its ``stop``
    (N,; excluded), in order: (owner, number) pairs as two (P,) tensors."""
    count = stop - start
    which = torch.repeat_interleave(torch.arange(len(owners), device=owners.device), count)
    offset = torch.arange(len(which), device=owners.device) - (torch.cumsum(count, 0)
                                                              - count).index_select(0, which)
    return owners.index_select(0, which), start.index_select(0, which) + offset


def _alpha(rows: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """(P,) opacity at pixels (``px``, ``py``) of splats projected as ``rows`` (P, 6): centre
    u, v, inverse covariance (a, b, c), peak opacity; and the offsets dx, dy and the
    Gaussian exp(-d^T (a b; b c) d / 2) that make it."""
    u, v, a, b, c, peak = rows.unbind(1)
    dx = px + 0.5 - u
    dy = py + 0.5 - v
    gaussian = torch.exp(-0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy))
    return torch.clamp(peak * gaussian, max=MAX_ALPHA), dx, dy, gaussian
