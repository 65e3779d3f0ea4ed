"""RGBXY weights: Delaunay barycentrics in (R, G, B, X, Y) space composed with star coordinates.

Every pixel of the stitched canvas is a 5-D point (its colour and its canvas
position). Its barycentric coordinates in the Delaunay tessellation of the
vertices of the 5-D convex hull express it by at most 6 hull vertices; each hull
vertex colour is in turn expressed by the palette through the star tessellation
of the palette polytope from its darkest vertex. The product of the two sparse
matrices gives the per-pixel palette weights.

Memory stays bounded: the hull is built chunk by chunk (the hull vertices of a
union are among the hull vertices of its parts) and pixels are located chunk by
chunk, so no (pixels x hull vertices) matrix is ever formed.

References
----------
J. Tan, J. Echevarria, Y. Gingold. Efficient palette-based decomposition and
recoloring of images via RGBXY-space geometry. ACM TOG 37(6), 2018.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay

from .colour_set import ColourSet
from .constants import RANK_TOL
from .errors import InputError
from .io import LoadedImage
from .polytope import Polytope, project_to_polytope, qhull
from .registry import spatial

#: Pixels per chunk when building the hull and locating pixels.
CHUNK_PIXELS = 1 << 18

#: Rec. 709 luminance, to pick the darkest palette colour as the star's centre.
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def canvas_offsets(shapes: list[tuple[int, int]]) -> tuple[np.ndarray, int]:
    """Place images on one canvas, row by row, about sqrt(N) to a row.

    Parameters
    ----------
    shapes : list of (H, W)

    Returns
    -------
    offsets : (N, 2) int
        Top-left (row, column) of each image on the canvas.
    side : int
        The canvas's longer side, which normalises X and Y.

    Examples
    --------
    >>> offsets, side = canvas_offsets([(2, 3), (4, 1), (1, 1)])
    >>> offsets.tolist(), side
    ([[0, 0], [0, 3], [4, 0]], 5)
    """
    per_row = int(np.ceil(np.sqrt(len(shapes))))
    offsets, top, height, width = [], 0, 0, 0
    for i, (h, w) in enumerate(shapes):
        if i % per_row == 0:
            top, left = top + height, 0
            height = 0
        offsets.append((top, left))
        left += w
        height, width = max(height, h), max(width, left)
    return np.array(offsets, int).reshape(-1, 2), max(top + height, width, 1)


def _rgbxy_chunks(
    images: list[LoadedImage], spatial_scale: float
) -> Iterator[tuple[int, slice, np.ndarray]]:
    """(image index, flat pixel slice, (n, 5) RGBXY points) in chunks of whole rows."""
    offsets, side = canvas_offsets([im.pixels.shape[:2] for im in images])
    for i, image in enumerate(images):
        h, w = image.pixels.shape[:2]
        rows = max(1, CHUNK_PIXELS // w)
        scale = float(np.iinfo(image.pixels.dtype).max)
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            yy, xx = np.mgrid[r0:r1, 0:w]
            xy = np.stack([(xx + offsets[i, 1]).ravel(), (yy + offsets[i, 0]).ravel()], axis=1)
            rgb = image.pixels[r0:r1].reshape(-1, 3) / scale
            yield i, slice(r0 * w, r1 * w), np.hstack([rgb, xy * (spatial_scale / side)])


@dataclass(frozen=True)
class _Frame:
    """The affine subspace the RGBXY points span: ``local = (p - origin) @ basis.T``."""

    origin: np.ndarray
    basis: np.ndarray

    def local(self, points: np.ndarray) -> np.ndarray:
        return (points - self.origin) @ self.basis.T


def _affine_frame(images: list[LoadedImage], spatial_scale: float) -> _Frame:
    """Two passes (mean, then centred scatter) so that flat directions come out exactly flat."""
    total, count = np.zeros(5), 0
    for _, _, points in _rgbxy_chunks(images, spatial_scale):
        total += points.sum(axis=0)
        count += len(points)
    origin = total / count
    scatter = np.zeros((5, 5))
    for _, _, points in _rgbxy_chunks(images, spatial_scale):
        centred = points - origin
        scatter += centred.T @ centred
    values, vectors = np.linalg.eigh(scatter)
    keep = values > RANK_TOL * max(values[-1], 1e-300)
    return _Frame(origin, vectors[:, keep].T)


def _hull_vertices(local_chunks: Iterator[np.ndarray], dim: int) -> np.ndarray:
    """Vertices of the convex hull of all chunks, merged chunk by chunk.

    While too few points have come for Qhull (a first chunk of one pixel), all of
    them are kept: a superset of the hull vertices tessellates the same hull.
    """
    vertices = np.zeros((0, dim))
    for chunk in local_chunks:
        vertices = np.vstack([vertices, chunk])
        if dim == 1:
            vertices = vertices[[vertices.argmin(), vertices.argmax()]]
        elif len(vertices) > dim + 1 and (hull := qhull(vertices)) is not None:
            vertices = vertices[hull.vertices]  # all points kept when Qhull fails twice
    return vertices


def star_coordinates(colours: np.ndarray, poly: Polytope) -> np.ndarray:
    """Barycentric coordinates of colours in the star tessellation of the palette.

    The polytope is cut into simplices that share its darkest vertex: one per
    boundary facet (triangle, or edge of a polygon) not containing it. Colours
    outside the polytope are projected to it first.

    Parameters
    ----------
    colours : (n, 3) float
    poly : Polytope

    Returns
    -------
    (n, K) float64
        Non-negative, summing to one, at most dim + 1 non-zeros per row.
    """
    k = len(poly.vertices)
    if poly.dim == 0:
        return np.ones((len(colours), 1))
    local = project_to_polytope(colours, poly)  # (n, dim)
    corners = poly.to_local(poly.vertices)  # (K, dim)
    dark = int(np.argmin(poly.vertices @ _LUMINANCE))
    if poly.dim == 1:
        facets = [[i] for i in range(k) if i != dark]
    elif poly.dim == 2:
        facets = [[i, (i + 1) % k] for i in range(k) if dark not in (i, (i + 1) % k)]
    else:
        facets = [list(f) for f in poly.faces if dark not in f]
    simplices = np.array([[dark, *f] for f in facets])  # (S, dim + 1)
    # Barycentrics in every simplex: solve [corners^T; 1] b = [x; 1]. Facets in a
    # plane through the darkest vertex give flat simplices, which cover nothing.
    systems = np.concatenate([np.swapaxes(corners[simplices], 1, 2),
                              np.ones((len(simplices), 1, poly.dim + 1))], axis=1)
    volume = np.abs(np.linalg.det(systems))
    solid = volume > RANK_TOL * volume.max()
    simplices, inverses = simplices[solid], np.linalg.inv(systems[solid])
    rhs = np.hstack([local, np.ones((len(local), 1))])
    coords = np.einsum("sij,nj->nsi", inverses, rhs)  # (n, S, dim + 1)
    best = coords.min(axis=2).argmax(axis=1)
    chosen = np.clip(coords[np.arange(len(local)), best], 0.0, None)
    chosen /= chosen.sum(axis=1, keepdims=True)
    weights = np.zeros((len(local), k))
    np.add.at(weights, (np.arange(len(local))[:, None], simplices[best]), chosen)
    return weights


def _barycentrics(tessellation: Delaunay, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, dim + 1) vertex indices and clipped, renormalised barycentrics of each point."""
    dim = points.shape[1]
    simplex = tessellation.find_simplex(points, tol=1e-9)
    lost = simplex < 0
    if lost.any():  # outside only by round-off: search again with a looser tolerance
        simplex[lost] = tessellation.find_simplex(points[lost], bruteforce=True, tol=1e-6)
    lost = simplex < 0
    simplex[lost] = 0
    transform = tessellation.transform[simplex]  # (n, dim + 1, dim)
    partial = np.einsum("nij,nj->ni", transform[:, :dim], points - transform[:, dim])
    coords = np.clip(np.hstack([partial, 1 - partial.sum(axis=1, keepdims=True)]), 0, None)
    coords /= coords.sum(axis=1, keepdims=True)
    vertices = tessellation.simplices[simplex]
    if lost.any():  # never seen; keep a valid partition of unity: the nearest vertex
        nearest = np.linalg.norm(points[lost, None] - tessellation.points[None], axis=2)
        vertices[lost] = nearest.argmin(axis=1)[:, None]
        coords[lost] = np.eye(dim + 1)[0]
    return vertices, coords


@spatial
def rgbxy_image_weights(
    colour_set: ColourSet, poly: Polytope, *, spatial_scale: float = 1.0
) -> Iterator[np.ndarray]:
    """(H, W, K) RGBXY weights per image (Tan, Echevarria, Gingold 2018).

    Parameters
    ----------
    colour_set : ColourSet
        Its images are stitched into one canvas, row by row.
    poly : Polytope
        The palette polytope.
    spatial_scale : float
        Multiplies the canvas coordinates (normalised by the canvas's longer
        side): larger values make the weights follow image position more closely.

    Raises
    ------
    InputError
        If ``spatial_scale`` is not a positive number (before any work).
    """
    if not 0 < spatial_scale < float("inf"):
        raise InputError(f"spatial_scale must be a positive number, got {spatial_scale}")
    return _rgbxy_weights(colour_set.images, poly, spatial_scale)


def _rgbxy_weights(images: list[LoadedImage], poly: Polytope,
                   spatial_scale: float) -> Iterator[np.ndarray]:
    frame = _affine_frame(images, spatial_scale)
    dim = len(frame.basis)
    if dim == 0:  # one pixel, or one colour at one place: a single vertex
        local_vertices = np.zeros((1, 0))
    else:
        chunks = (frame.local(p) for _, _, p in _rgbxy_chunks(images, spatial_scale))
        local_vertices = _hull_vertices(chunks, dim)
    tessellation = Delaunay(local_vertices) if dim > 1 else None
    vertex_colours = (frame.origin + local_vertices @ frame.basis)[:, :3]
    mixing = star_coordinates(vertex_colours, poly)  # (V, K)

    weights = [np.empty((im.pixels.shape[0] * im.pixels.shape[1], len(poly.vertices)),
                        np.float32) for im in images]
    for i, part, points in _rgbxy_chunks(images, spatial_scale):
        local = frame.local(points)
        if tessellation is not None:
            index, coords = _barycentrics(tessellation, local)
        elif dim == 1:
            ends = local_vertices[:, 0]
            u = np.clip((local[:, 0] - ends[0]) / (ends[1] - ends[0]), 0, 1)
            index, coords = np.tile([0, 1], (len(u), 1)), np.stack([1 - u, u], axis=1)
        else:
            index, coords = np.zeros((len(points), 1), int), np.ones((len(points), 1))
        weights[i][part] = np.einsum("nj,njk->nk", coords, mixing[index])
    for image, w in zip(images, weights):
        yield w.reshape(*image.pixels.shape[:2], -1)
