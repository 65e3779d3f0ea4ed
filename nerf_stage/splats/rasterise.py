"""A differentiable splat rasteriser in plain PyTorch (CPU and CUDA): EWA splatting of 3D
Gaussians, sorted front to back per pixel, as 3D Gaussian splatting blends them.

A view is a list of (pixel, splat, alpha) pairs: each splat's screen-space ellipse is
walked row by row (a band of the view's rows at a time), pairs below 1/255 or behind
``MIN_TRANSMITTANCE`` of light are dropped, and each pixel's values are the sum of its
pairs' transmittance x alpha x values.

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (projection of the covariances, front-to-back blending, the low-pass filter).
M. Zwicker et al. EWA splatting. IEEE TVCG 8(3), 2002.
Z. Yu et al. Mip-Splatting: alias-free 3D Gaussian splatting. CVPR 2024 (the 2D filter).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from ..data.cameras import Intrinsics
from . import tiles
from .model import Splats
from .tiles import MAX_ALPHA, MIN_TRANSMITTANCE

#: Pixels^2 added to every projected covariance: Mip-Splatting's 2D filter. (3D Gaussian
#: splatting's 0.3, which viser adds at the screen's resolution, let splats fitted at the
#: training views' resolution lean on that blur to cover surfaces: holes where a browser
#: draws them finer; docs/splats.md.)
LOW_PASS = 0.1
#: Splats nearer to the camera than this (in the splats' units; the scene box's half size
#: for a splat run) are not drawn: their projection's Jacobian grows as 1 / depth^2.
NEAR = 0.01
FOV_CLAMP = 1.3  # of the view's half angle, where the Jacobian is taken at most
#: Pixels of a view whose pairs are found at once on a CPU (``_band``): the pairs tried are
#: held for a band, not the view, and their sorts stay short
#: (docs/decisions/0013-rasteriser-bands.md). On CUDA a view is one band: its memory holds
#: the pairs, and every band would add its kernel launches and synchronisations to a step.
BAND_PIXELS = 1 << 14
#: Whether a CPU draws through the tile kernels (``tiles``); False: through pairs in PyTorch,
#: a band at a time, as CUDA does and as the palette stage's footprints are made.
TILED = True


@torch.no_grad()
def render_splats(splats: Splats, poses: np.ndarray, camera: Intrinsics,
                  progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``splats`` from (N, 4, 4) ``poses`` (OpenGL camera-to-world) with ``camera``,
    each view with the weights seen from its camera (``Splats.view_weights``), each splat
    whole (``draw`` without a reach), as a splat run renders and the browser draws them.

    Returns
    -------
    weights : (N, H, W, M) float32
        Composited palette weights, premultiplied by opacity (a weight render).
    opacity : (N, H, W) float32
    """
    centres, covariances, weights, opacities = splat_tensors(splats)
    h, w = camera.height, camera.width
    out_weights, out_opacity = [], []
    for pose in tqdm(poses, desc="draw splats", unit="view", disable=not progress):
        if splats.residual is not None:
            weights = torch.as_tensor(splats.view_weights(pose[:3, 3]))
        drawn, opacity = draw(centres, covariances, weights, opacities, torch.as_tensor(pose),
                              camera, None)
        out_weights.append(drawn.view(h, w, -1).float().numpy())
        out_opacity.append(opacity.view(h, w).float().numpy())
    return np.stack(out_weights), np.stack(out_opacity)


def splat_tensors(splats: Splats) -> tuple[torch.Tensor, ...]:
    """Centres, covariances, editable weights and opacities as float32 tensors."""
    return (torch.as_tensor(splats.centres), torch.as_tensor(splats.covariances()).float(),
            torch.as_tensor(splats.weights), torch.as_tensor(splats.opacities))


def draw(centres, covariances, values, opacities, pose: torch.Tensor, camera: Intrinsics,
         reach: int | None = 32, info: dict | None = None,
         window: tuple[int, int, int, int] | None = None,
         keep_pairs: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(H W, M) composited ``values`` and (H W,) opacity of one view (differentiable in the
    splats' parameters), each splat drawn at most ``reach`` pixels from its centre (None:
    whole, however near the camera; training cuts splats off at a reach that bounds a
    view's pairs, and splits those it cuts); with a ``window`` (x, y, width, height) of the
    view, that part of it only (W x H of it).

    With an ``info`` dict, it receives what densification needs: ``means2d`` (F, 2), the
    pixel positions of the F splats in front of the camera (gradients retained), their
    indices ``front`` (F,), ``drawn`` (D,), the splats with a pixel in the view, and
    ``clipped``, those in the view wider than ``reach`` (drawn cut off); with
    ``keep_pairs`` too (a draw without gradients), ``pairs``: (P,) int32 pixel, int32 splat
    and contribution (transmittance x alpha) of every pair drawn, by pixel, front to back."""
    window = window or (0, 0, camera.width, camera.height)
    pixels = window[2] * window[3]
    if TILED and not centres.is_cuda and not keep_pairs:
        projected = _project(centres, covariances, opacities, pose, camera, reach, info, window)
        if projected is not None:
            table, box, index, order = projected
            return _TileComposite.apply(table, values, box, index, order, window, info)
        found = None
    else:
        found = _pairs(centres, covariances, opacities, pose, camera, reach, info, window)
    if found is None:
        if info is not None:
            info["drawn"] = torch.zeros(0, dtype=torch.long, device=centres.device)
        return values.new_zeros(pixels, values.shape[1]), values.new_zeros(pixels)
    table, index, pixel, ids, light, counts = found
    if info is not None:
        info["drawn"] = index.index_select(0, torch.nonzero(
            torch.bincount(ids, minlength=len(index)))[:, 0])
    if not keep_pairs:
        return _Composite.apply(table, values, index, pixel, ids, light, counts, window)
    with torch.no_grad():  # the pairs' own tensors become the kept ones: none held twice
        blended = _draw_bands(table, values, index, pixel, ids, light, counts, window,
                              keep=True)
        for first in range(0, len(ids), BAND_PIXELS):  # each splat over its projection
            part = ids[first:first + BAND_PIXELS]
            part.copy_(index.index_select(0, part))
    info["pairs"] = (pixel, ids, light)
    return blended


class _Composite(torch.autograd.Function):
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
        return _draw_bands(table, values, index, pixel, ids, light, counts, window)

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


class _TileComposite(torch.autograd.Function):
    """``_Composite`` on a CPU through the tile kernels of ``tiles``: (pixels, M) values and
    (pixels,) opacity of a view's ``window`` from the projections ``table`` (F, 6), their
    ``box`` (F, 5), the splats' ``index`` (F,) and the ``order`` (D,) of the rows that
    show, front to back; nothing is held per pair, the backward walks the tiles again.
    ``info["drawn"]`` receives the splats with a pair."""

    @staticmethod
    def forward(ctx, table, values, box, index, order, window, info):
        left, top, width, height = window
        tiles_x, tiles_y = -(-width // tiles.TILE), -(-height // tiles.TILE)
        arrays = (table.detach().numpy(), np.ascontiguousarray(box[:, :4].numpy(), np.float64),
                  values.detach().numpy(), index.numpy())
        starts, ids = tiles.bin_tiles(arrays[1], order.numpy(), left, top, tiles_x, tiles_y)
        pixels = width * height
        drawn, opacity = np.zeros((pixels, values.shape[1])), np.zeros(pixels)
        last, final = np.empty(pixels, np.int64), np.empty(pixels)
        shown = np.zeros(len(table), np.bool_)
        tiles.forward(*arrays, starts, ids, window, tiles_x, drawn, opacity, last, final, shown)
        if info is not None:
            info["drawn"] = index[torch.from_numpy(shown)]
        ctx.kernel = (*arrays, starts, ids, window, tiles_x, last, final)
        ctx.shapes = table.shape, values.shape
        return (torch.from_numpy(drawn).to(values.dtype),
                torch.from_numpy(opacity).to(values.dtype))

    @staticmethod
    def backward(ctx, grad_drawn, grad_opacity):
        geometry = ctx.needs_input_grad[0]
        (table_shape, values_shape), chunks = ctx.shapes, tiles.chunks()
        grad_table = np.zeros((chunks if geometry else 1, *table_shape))
        grad_values = np.zeros((chunks, *values_shape))
        tiles.backward(*ctx.kernel, np.ascontiguousarray(grad_drawn.numpy(), np.float64),
                       np.ascontiguousarray(grad_opacity.numpy(), np.float64), geometry,
                       grad_table, grad_values)
        dtype = grad_drawn.dtype
        return (torch.from_numpy(grad_table.sum(0)).to(dtype) if geometry else None,
                torch.from_numpy(grad_values.sum(0)).to(dtype), None, None, None, None, None)


class _Blend(NamedTuple):
    """One band's pairs made again from what ``_Composite`` keeps: (p,) pixel (of the
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
    """``_Composite``'s pairs, a band (of ``counts``) at a time."""
    first = 0
    for count in counts:
        # int64 indices: index_add_ of rows takes a slow path with int32 ones
        part, band = pixel[first:first + count].long(), ids[first:first + count].long()
        rows = table.index_select(0, band)
        alpha, dx, dy, gaussian = _alpha(rows, *_position(part, window))
        yield _Blend(part, band, index.index_select(0, band), light[first:first + count],
                     alpha, rows, dx, dy, gaussian)
        first += count


def _draw_bands(table, values, index, pixel, ids, light, counts, window,
                keep: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``_Composite``'s (pixels, M) values and (pixels,) opacity, a band at a time; with
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


def _pairs(centres, covariances, opacities, pose, camera: Intrinsics, reach: int | None,
           info: dict | None, window: tuple[int, int, int, int]):
    """The (pixel, splat, alpha) pairs of one view's ``window`` above 1/255 with at least
    ``MIN_TRANSMITTANCE`` of light left in front of them, sorted by pixel (of the window),
    then front to back, and that light (detached); None when no splat shows (``draw``'s
    ``info`` filled on the way)."""
    projected = _project(centres, covariances, opacities, pose, camera, reach, info, window)
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


def _project(centres, covariances, opacities, pose, camera: Intrinsics, reach: int | None,
             info: dict | None, window: tuple[int, int, int, int]):
    """Each splat in front of the camera projected (``table`` (F, 6): centre u, v, inverse
    covariance a, b, c, peak opacity; with gradients), its ``box`` (F, 5): x0, x1, y0, y1
    in the ``window`` and the Mahalanobis ``level`` of alpha 1/255, the splats' ``index``
    (F,) and the rows that show, front to back; None when none shows."""
    left, top, width, height = window
    pose = pose.to(centres.dtype)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    local = (centres - origin) @ rotation  # camera axes: x right, y up, looking down -z
    depth = -local[:, 2]
    index = torch.nonzero(depth > NEAR)[:, 0]
    local, depth = local.index_select(0, index), depth.index_select(0, index)
    covariances = covariances.index_select(0, index)
    fx, fy = camera.fx, camera.fy
    u = camera.cx + fx * local[:, 0] / depth
    v = camera.cy - fy * local[:, 1] / depth
    if info is not None and u.requires_grad:
        means2d = torch.stack([u, v], 1)
        means2d.retain_grad()
        u, v = means2d.unbind(1)
        info.update(means2d=means2d, front=index)
    # the projection's Jacobian, at the centre's direction held within 1.3 times the view's
    # half angle (3D Gaussian splatting's clamp: splats far outside the view stay finite)
    x = depth * torch.clamp(local[:, 0] / depth, -FOV_CLAMP * camera.width / (2 * fx),
                            FOV_CLAMP * camera.width / (2 * fx))
    y = depth * torch.clamp(local[:, 1] / depth, -FOV_CLAMP * camera.height / (2 * fy),
                            FOV_CLAMP * camera.height / (2 * fy))
    jacobian = depth.new_zeros(len(depth), 2, 3)
    jacobian[:, 0, 0] = fx / depth
    jacobian[:, 0, 2] = fx * x / depth ** 2
    jacobian[:, 1, 1] = -fy / depth
    jacobian[:, 1, 2] = -fy * y / depth ** 2
    transform = jacobian @ rotation.T
    projected = transform @ covariances @ transform.transpose(1, 2)
    a, b, c = projected[:, 0, 0] + LOW_PASS, projected[:, 0, 1], projected[:, 1, 1] + LOW_PASS
    determinant = a * c - b * b
    conic = torch.stack([c, -b, a], 1) / determinant[:, None]  # the inverse, per splat
    # the box around the ellipse outside which a splat's alpha is below 1/255
    opacities = opacities.index_select(0, index)
    level = torch.sqrt(2 * torch.log((255 * opacities.detach()).clamp(min=1)))
    rx, ry = level * torch.sqrt(a.detach()), level * torch.sqrt(c.detach())
    if reach is not None:
        wide = (rx > reach) | (ry > reach)
        rx, ry = rx.clamp(max=reach), ry.clamp(max=reach)
    x0 = (u.detach() - rx).floor().clamp(left, left + width)
    x1 = (u.detach() + rx).ceil().clamp(left, left + width)
    y0 = (v.detach() - ry).floor().clamp(top, top + height)
    y1 = (v.detach() + ry).ceil().clamp(top, top + height)
    shown = (x1 > x0) & (y1 > y0)
    if info is not None and reach is not None:  # cut off square: densification splits them
        info["clipped"] = index[wide & shown]
    if not shown.any():
        return None
    drawn = torch.nonzero(shown)[:, 0]
    drawn = drawn[torch.argsort(depth.detach()[drawn])]  # front to back: pairs come so
    # each splat's projection (u, v, conic, opacity), gathered with gradients only for the
    # pairs that show
    table = torch.cat([u[:, None], v[:, None], conic, opacities[:, None]], 1)
    return table, torch.stack([x0, x1, y0, y1, level], 1), index, drawn


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
