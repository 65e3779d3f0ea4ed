"""Palette extraction: convex hull of all colours, simplified by edge collapse.

Progressive hull simplification after Tan, Lien and Gingold (2017), Sec. 3.1:
every hull edge (a, b) gets the point v that, replacing a and b, adds the least
volume while keeping every facet plane around a and b behind it, so the new hull
still encloses all colours. With unit outward facet normals n_f, offsets o_f
(n_f . x + o_f <= 0 inside) and facet measures A_f, that is the linear program

    minimise   sum_f A_f (n_f . v + o_f) / d     over the facets f touching a or b
    subject to n_f . v + o_f >= 0                for the same facets,

solved exactly in ``collapse_lp.collapse_points`` by enumerating the bases of
these few rows (an edge has a dozen facets around it: microseconds an LP, where a
general solver's call costs more than all of them). The cheapest edge collapses, the
hull is recomputed, and so on. An edge's LP depends only on the facets around its two
ends, so its answer is cached under a hash of those facets and only edges near the
last collapse are solved again. The same code simplifies planar colour sets (d = 2:
polygons, facets are edges).

References
----------
Tan, Lien, Gingold. Decomposing images into layers via RGB-space geometry. ACM TOG 2017.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.spatial import ConvexHull

from .errors import InputError
from .kernels import collapse_lp
from .polytope import Polytope, polytope_from_points, polytope_rmse

_MIX = np.uint64(0x9E3779B97F4A7C15)

#: Palette size when neither ``k`` nor ``max_error`` is given.
DEFAULT_K = 6

#: Cost per unit of slack in the collapse LP; far above any added volume
#: (the LP box is a few units wide), so the slack is zero whenever it can be.
_SLACK_PENALTY = 1e6
#: Slack above this means the edge's LP is infeasible (the collapse lets colours out).
_SLACK_TOL = 1e-9
#: One step collapses at most (vertices above target) / this many edges: fewer steps
#: than one edge at a time, with the same error (docs/method.md).
_BATCH_DIVISOR = 12


def simplification_levels(points: np.ndarray, target: int | None = None) -> Iterator[np.ndarray]:
    """Yield the vertices of ever simpler hulls enclosing ``points``.

    While the hull has many more vertices than ``target``, one step collapses
    several of the cheapest edges whose neighbourhoods (the vertices of the
    facets around each edge) do not overlap: their LPs share no facet, so each
    is exactly the LP it would be alone. At most 1/12 of the vertices above
    ``target`` go in one step, so the last steps collapse one edge at a time.

    Parameters
    ----------
    points : (n, d) float, d in {2, 3}
        Full-dimensional point set in local coordinates.
    target : int, optional
        The vertex count the caller is heading for (default d + 1).

    Yields
    ------
    (m, d) float64
        Hull vertices after each collapse, from the hull of ``points`` (m = its
        vertex count) down to a simplex (m = d + 1). Each level encloses the last.
    """
    d = points.shape[1]
    target = d + 1 if target is None else max(target, d + 1)
    lo, hi = points.min(0), points.max(0)
    margin = 2.0 * float(np.max(hi - lo))
    box = np.stack([lo - margin, hi + margin], -1)  # keeps every LP bounded
    positions = np.empty((2 * len(points), d))  # each collapse adds one point
    positions[: len(points)] = points
    n_ids = len(points)
    alive = np.arange(n_ids)
    cache: dict[tuple[int, int, int], tuple[float, np.ndarray]] = {}
    while True:
        hull = ConvexHull(positions[alive])
        facets = alive[hull.simplices]  # (F, d) vertex ids
        alive = alive[hull.vertices]
        yield positions[alive]
        if len(alive) <= d + 1:
            return
        normals, offsets = hull.equations[:, :d], hull.equations[:, d]
        measures = _facet_measures(positions[facets])
        edges = _edges(facets)
        keys = _edge_keys(edges, facets, n_ids)
        touching = _facets_touching(facets, n_ids)
        todo = [i for i, key in enumerate(keys) if key not in cache]
        for penalty in (0.0, _SLACK_PENALTY):  # how far collapses let colours out, if all do
            blocks = [sorted(set(touching[a] + touching[b])) for a, b in edges[todo].tolist()]
            cache.update(zip([keys[i] for i in todo],
                             _solve_collapses(blocks, normals, offsets, measures, box, penalty)))
            slack, volume = np.array([cache[key][:2] for key in keys]).T
            if (slack <= _SLACK_TOL).any():
                break
            todo = np.flatnonzero(np.isnan(slack)).tolist()
        chosen = _independent_cheapest(edges, slack, volume, facets, touching,
                                       max(1, (len(alive) - target) // _BATCH_DIVISOR))
        new_ids = np.arange(n_ids, n_ids + len(chosen))
        positions[new_ids] = [cache[keys[e]][2] for e in chosen]
        alive = np.append(alive[~np.isin(alive, edges[chosen])], new_ids)
        n_ids += len(chosen)


def _independent_cheapest(edges, slack, volume, facets, touching, limit) -> list[int]:
    """Edges to collapse in one step.

    Up to ``limit`` feasible edges (zero slack), least added volume first, no two
    of which share a facet's vertex. When no edge is feasible (box-like hulls:
    a cube's edge cannot collapse with all colours kept inside), the one edge
    that needs the least slack, i.e. lets colours out by the least distance.
    """
    feasible = slack <= _SLACK_TOL
    if not feasible.any():
        return [int(np.lexsort((volume, slack))[0])]
    chosen: list[int] = []
    claimed: set[int] = set()
    for e in np.argsort(np.where(feasible, volume, np.inf), kind="stable"):
        if not feasible[e] or len(chosen) == limit:
            break
        a, b = edges[e]
        ring = set(facets[touching[a] + touching[b]].ravel().tolist())
        if claimed.isdisjoint(ring):
            chosen.append(int(e))
            claimed |= ring
    return chosen


def _facet_measures(corners: np.ndarray) -> np.ndarray:
    """(F, d, d) facet corners -> (F,) facet areas (d = 3) or lengths (d = 2)."""
    if corners.shape[1] == 2:
        return np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return 0.5 * np.linalg.norm(cross, axis=1)


def _edges(facets: np.ndarray) -> np.ndarray:
    """(E, 2) unique sorted vertex-id pairs of the facets (triangles or segments)."""
    if facets.shape[1] == 2:
        return np.sort(facets, axis=1)
    pairs = np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [0, 2]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _edge_keys(edges: np.ndarray, facets: np.ndarray, n_ids: int) -> list[tuple[int, int, int]]:
    """Cache keys: an edge's ends and a 64-bit hash of the facets around them."""
    ids = np.sort(facets, axis=1).astype(np.uint64)
    packed = np.zeros(len(facets), np.uint64)
    for column in ids.T:
        packed = (packed << np.uint64(21)) | column
    mixed = packed * _MIX
    mixed ^= mixed >> np.uint64(29)
    mixed *= _MIX
    around = np.zeros(n_ids, np.uint64)
    np.add.at(around, facets.ravel(), np.repeat(mixed, facets.shape[1]))
    hashes = around[edges[:, 0]] + around[edges[:, 1]]
    return list(zip(edges[:, 0].tolist(), edges[:, 1].tolist(), hashes.tolist()))


def _facets_touching(facets: np.ndarray, n_ids: int) -> list[list[int]]:
    """For every vertex id, the indices of the facets that contain it."""
    touching: list[list[int]] = [[] for _ in range(n_ids)]
    for f, ids in enumerate(facets.tolist()):
        for i in ids:
            touching[i].append(f)
    return touching


def _solve_collapses(blocks, normals, offsets, measures, box, penalty) -> list[tuple]:
    """The collapse LP of each block of facets (``collapse_lp.collapse_points``):
    [(slack, added volume, point)], all NaN where the edge cannot collapse with every
    colour kept inside and ``penalty`` is 0 (its least slack not asked for)."""
    if not blocks:
        return []
    d = normals.shape[1]
    rows = np.concatenate(blocks)
    starts = np.cumsum([0] + [len(block) for block in blocks])
    solution = np.empty((len(blocks), d + 1))
    collapse_lp.collapse_points(np.ascontiguousarray(normals), np.ascontiguousarray(offsets),
                                     measures, rows, starts, box, penalty, solution)
    v, slack = solution[:, :d], solution[:, d]
    block_of_row = np.repeat(np.arange(len(blocks)), np.diff(starts))
    gradient = np.zeros((len(blocks), d))
    np.add.at(gradient, block_of_row, measures[rows, None] * normals[rows] / d)
    constant = np.bincount(block_of_row, measures[rows] * offsets[rows] / d, minlength=len(blocks))
    volume = np.einsum("ij,ij->i", gradient, v) + constant
    return list(zip(slack.tolist(), volume.tolist(), v))


def extract_palette(
    colours: np.ndarray,
    counts: np.ndarray,
    k: int | None = 6,
    max_error: float | None = None,
) -> Polytope:
    """The palette polytope of a colour set: simplified hull, clipped to the RGB cube.

    Parameters
    ----------
    colours : (n, 3) float
        Distinct colours in [0, 1].
    counts : (n,) int
        Pixels per colour; colours with count 0 do not shape the palette.
    k : int or None
        Stop at this many vertices (at least 4). With ``max_error`` too, the
        palette has at most ``k`` colours; with neither, ``DEFAULT_K``.
    max_error : float or None
        Instead: the smallest palette whose reconstruction RMSE (0-255 scale,
        per channel, over all pixels) is at most this.

    Returns
    -------
    Polytope
        Fewer than ``k`` vertices when the hull of the colours has fewer
        (degenerate sets give a point, a segment or a polygon, see
        ``polytope_from_points``).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> colours = rng.random((500, 3))
    >>> poly = extract_palette(colours, np.ones(500, int), k=5)
    >>> poly.vertices.shape, bool(((poly.vertices >= 0) & (poly.vertices <= 1)).all())
    ((5, 3), True)
    """
    k = check_palette_size(k, max_error)
    used = counts > 0
    hull = polytope_from_points(colours[used])
    if max_error is None:
        return simplified_hull(hull, k)
    if hull.dim < 2:
        return hull
    candidates = [lv for lv in simplification_levels(hull.to_local(hull.vertices))
                  if k is None or len(lv) <= k]
    for level in reversed(candidates):  # fewest vertices first
        poly = _clipped(hull, level)
        if polytope_rmse(colours[used], counts[used], poly) <= max_error:
            return poly
    return _clipped(hull, candidates[0])


def simplified_hull(hull: Polytope, k: int) -> Polytope:
    """The hull of the colours simplified to ``k`` vertices and clipped to the RGB cube; the
    hull itself when it has at most ``k`` vertices or is a point or a segment."""
    if hull.dim < 2 or len(hull.vertices) <= k:
        return hull
    level = next(lv for lv in simplification_levels(hull.to_local(hull.vertices), k)
                 if len(lv) <= k)
    return _clipped(hull, level)


def check_palette_size(k: int | None, max_error: float | None) -> int | None:
    """The palette size to aim for (``DEFAULT_K`` when neither is given), validated.

    Raises
    ------
    InputError
        If ``k`` < 4 or ``max_error`` is negative or not a number.
    """
    if k is not None and k < 4:
        raise InputError(f"k must be at least 4, got {k}")
    if max_error is not None and not max_error >= 0:
        raise InputError(f"max_error must be a non-negative number, got {max_error}")
    return DEFAULT_K if k is None and max_error is None else k


def _clipped(frame: Polytope, level: np.ndarray) -> Polytope:
    """Polytope of a simplification level's vertices, clipped to the RGB cube."""
    return polytope_from_points(np.clip(frame.from_local(level), 0.0, 1.0))
