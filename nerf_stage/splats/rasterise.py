"""The differentiable splat rasteriser: EWA splatting of 3D Gaussians blended front to back
per pixel, as 3D Gaussian splatting draws them. The splats are projected
(``projection``), then drawn on a CPU by the numba tile kernels (``tiles``), which also
give the palette stage's footprints their pairs, and on CUDA as (pixel, splat) pairs in
PyTorch (``pairs``).
Pairs below 1/255 or behind ``MIN_TRANSMITTANCE`` of light are dropped, and each pixel's
values are the sum of its pairs' transmittance x alpha x values.

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (projection of the covariances, front-to-back blending, the low-pass filter).
M. Zwicker et al. EWA splatting. IEEE TVCG 8(3), 2002.
Z. Yu et al. Mip-Splatting: alias-free 3D Gaussian splatting. CVPR 2024 (the 2D filter).
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from ..data.cameras import Intrinsics
from . import tiles
from .model import Splats
from .pairs import BAND_PIXELS, PairComposite, draw_bands, pairs
from .projection import LOW_PASS, project
from .tiles import MAX_ALPHA, MIN_TRANSMITTANCE

__all__ = ["LOW_PASS", "MAX_ALPHA", "MIN_TRANSMITTANCE", "TILED", "draw", "render_splats",
           "splat_tensors"]

#: Whether a CPU draws (and finds a footprint's pairs) through the tile kernels (``tiles``);
#: False: through pairs in PyTorch, a band at a time, as CUDA does.
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
    if TILED and not centres.is_cuda:
        projected = project(centres, covariances, opacities, pose, camera, reach, info, window)
        if projected is not None and keep_pairs:
            return _tile_pairs(values, *projected, window, info)
        if projected is not None:
            table, box, index, order = projected
            return _TileComposite.apply(table, values, box, index, order, window, info)
        found = None
    else:
        found = pairs(centres, covariances, opacities, pose, camera, reach, info, window)
    if found is None:
        if info is not None:
            info["drawn"] = torch.zeros(0, dtype=torch.long, device=centres.device)
        return values.new_zeros(pixels, values.shape[1]), values.new_zeros(pixels)
    table, index, pixel, ids, light, counts = found
    if info is not None:
        info["drawn"] = index.index_select(0, torch.nonzero(
            torch.bincount(ids, minlength=len(index)))[:, 0])
    if not keep_pairs:
        return PairComposite.apply(table, values, index, pixel, ids, light, counts, window)
    with torch.no_grad():  # the pairs' own tensors become the kept ones: none held twice
        blended = draw_bands(table, values, index, pixel, ids, light, counts, window,
                              keep=True)
        for first in range(0, len(ids), BAND_PIXELS):  # each splat over its projection
            part = ids[first:first + BAND_PIXELS]
            part.copy_(index.index_select(0, part))
    info["pairs"] = (pixel, ids, light)
    return blended


def _binned(table, box, index, order, values, window):
    """What the tile kernels read of a view's projections: each gathered row's splat (D,),
    the rows with ``values`` (``tiles.gathered``), each tile's rows (``tiles.bin_tiles``) and
    the tiles across the ``window``."""
    left, top, width, height = window
    tiles_x, tiles_y = -(-width // tiles.TILE), -(-height // tiles.TILE)
    splats = index.index_select(0, order)
    arrays = tiles.gathered(table.detach().numpy(), box.numpy(),
                            values.detach().index_select(0, splats).numpy(), order.numpy())
    return splats, arrays, *tiles.bin_tiles(arrays[1], left, top, tiles_x, tiles_y), tiles_x


@torch.no_grad()
def _tile_pairs(values, table, box, index, order, window, info):
    """``draw`` with ``keep_pairs`` through the tile kernels: ``info["pairs"]`` and
    ``info["drawn"]`` from ``tiles.forward``'s pairs, counted, then kept; the view's values
    and opacity summed from them."""
    pixels = window[2] * window[3]
    splats, arrays, starts, ids, tiles_x = _binned(table, box, index, order,
                                                   values.new_zeros(len(values), 0), window)
    shown = np.zeros(len(order), np.bool_)

    def walk(pairs):
        tiles.forward(*arrays, starts, ids, window, tiles_x, tiles.chunks(),
                      np.zeros((pixels, 0)), np.zeros(pixels), np.empty(pixels, np.int64),
                      np.empty(pixels), shown, pairs)

    offsets = np.zeros(pixels + 1, np.int64)
    walk((tiles.COUNT_PAIRS, offsets, *tiles.no_pairs()[2:]))
    offsets = np.cumsum(offsets)
    pixel, row = np.empty(offsets[-1], np.int32), np.empty(offsets[-1], np.int32)
    contribution = np.empty(offsets[-1])
    walk((tiles.KEEP_PAIRS, offsets[:-1].copy(), pixel, row, contribution))
    pixel, splat = torch.from_numpy(pixel), splats.index_select(0, torch.from_numpy(row)).int()
    contribution = torch.from_numpy(contribution).to(values.dtype)
    info["pairs"] = (pixel, splat, contribution)
    info["drawn"] = splats[torch.from_numpy(shown)]
    drawn = values.new_zeros(pixels, values.shape[1]).index_add_(
        0, pixel, contribution[:, None] * values.index_select(0, splat))
    return drawn, values.new_zeros(pixels).index_add_(0, pixel, contribution)


class _TileComposite(torch.autograd.Function):
    """``_Composite`` on a CPU through the tile kernels of ``tiles``: (pixels, M) values and
    (pixels,) opacity of a view's ``window`` from the projections ``table`` (F, 6), their
    ``box`` (F, 5), the splats' ``index`` (F,) and the ``order`` (D,) of the rows that
    show, front to back (gathered in that order for the kernels, ``tiles.gathered``);
    nothing is held per pair, the backward walks the tiles again. ``info["drawn"]``
    receives the splats with a pair."""

    @staticmethod
    def forward(ctx, table, values, box, index, order, window, info):
        splats, arrays, starts, ids, tiles_x = _binned(table, box, index, order, values, window)
        pixels = window[2] * window[3]
        drawn, opacity = np.zeros((pixels, values.shape[1])), np.zeros(pixels)
        last, final = np.empty(pixels, np.int64), np.empty(pixels)
        shown = np.zeros(len(order), np.bool_)
        tiles.forward(*arrays, starts, ids, window, tiles_x, tiles.chunks(), drawn, opacity, last,
                      final, shown, tiles.no_pairs())
        if info is not None:
            info["drawn"] = splats[torch.from_numpy(shown)]
        ctx.kernel = (*arrays, starts, ids, window, tiles_x, last, final)
        ctx.rows = order, splats, table.shape, values.shape
        return (torch.from_numpy(drawn).to(values.dtype),
                torch.from_numpy(opacity).to(values.dtype))

    @staticmethod
    def backward(ctx, grad_drawn, grad_opacity):
        geometry = ctx.needs_input_grad[0]
        (order, splats, table_shape, values_shape), chunks = ctx.rows, tiles.chunks()
        grad_rows = np.zeros((chunks if geometry else 1, len(order), 6))
        grad_row_values = np.zeros((chunks, len(order), values_shape[1]))
        tiles.backward(*ctx.kernel, np.ascontiguousarray(grad_drawn.numpy(), np.float64),
                       np.ascontiguousarray(grad_opacity.numpy(), np.float64), geometry,
                       grad_rows, grad_row_values)
        dtype = grad_drawn.dtype
        grad_values = grad_drawn.new_zeros(values_shape).index_copy_(
            0, splats, torch.from_numpy(grad_row_values.sum(0)).to(dtype))
        grad_table = (grad_drawn.new_zeros(table_shape).index_copy_(
            0, order, torch.from_numpy(grad_rows.sum(0)).to(dtype)) if geometry else None)
        return grad_table, grad_values, None, None, None, None, None
