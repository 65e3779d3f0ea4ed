"""Palette extraction: simplification, degenerate colour sets, tolerances."""

import numpy as np
import pytest
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, Delaunay

from palette_core import (
    InputError,
    extract_palette,
    polytope_rmse,
    rgb_to_mvc_weights,
    simplification_levels,
)
from palette_core.hull import (
    _SLACK_PENALTY,
    _edges,
    _facet_measures,
    _facets_touching,
    _solve_collapses,
)

from .helpers import weight_invariants


def encloses(vertices, points, tol=1e-9):
    hull = Delaunay(vertices)
    return (hull.find_simplex(points, tol=tol) >= 0).all()


@pytest.mark.parametrize("d", [2, 3])
def test_levels_shrink_and_enclose(rng, d):
    """A rounded colour set (a ball or disc): collapses keep every colour inside."""
    points = rng.normal(size=(400, d))
    points *= rng.random((400, 1)) ** (1 / d) / np.linalg.norm(points, axis=1, keepdims=True)
    sizes = []
    for level in simplification_levels(points):
        if len(level) > d + 3:  # the last few steps of a round set may need slack
            assert encloses(level, points, tol=1e-7)
        sizes.append(len(level))
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] == d + 1


@pytest.mark.parametrize("d", [2, 3])
def test_box_like_sets_still_reach_a_simplex(rng, d):
    """A cube's (square's) edges cannot collapse with all points kept inside; it still ends."""
    levels = list(simplification_levels(rng.random((300, d))))
    assert len(levels[-1]) == d + 1


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("shape", ["ball", "flat", "cube"])
def test_collapse_lps_agree_with_a_general_solver(rng, d, shape):
    """Every edge's collapse LP, solved by enumerating bases, has HiGHS's optimum (volume plus
    penalised slack). A cube's edges cannot collapse without letting points out, a ball's can;
    a flat ball's least volume lies beyond the box for some edges, which stop at its sides."""
    points = rng.normal(size=(300, d))
    if shape == "flat":
        points[:, -1] *= 0.01
    if shape == "cube":
        corners = np.stack(np.meshgrid(*[[0.0, 1.0]] * d), -1).reshape(-1, d)
        points = np.r_[corners, rng.random((300, d))]
    hull = ConvexHull(points)
    normals, offsets = hull.equations[:, :d], hull.equations[:, d]
    measures = _facet_measures(points[hull.simplices])
    touching = _facets_touching(hull.simplices, len(points))
    blocks = [sorted(set(touching[a] + touching[b])) for a, b in _edges(hull.simplices)]
    box = np.stack([points.min(0) - 1, points.max(0) + 1], -1)
    ours = _solve_collapses(blocks, normals, offsets, measures, box, _SLACK_PENALTY)
    unsolved = _solve_collapses(blocks, normals, offsets, measures, box, 0.0)
    for block, (slack, volume, v), (lazy_slack, _, _) in zip(blocks, ours, unsolved):
        a = np.c_[-normals[block], -np.ones(len(block))]
        c = np.r_[measures[block] @ normals[block] / d, _SLACK_PENALTY]
        best = linprog(c, A_ub=a, b_ub=offsets[block], bounds=[*box, (0, None)], method="highs",
                       options={"primal_feasibility_tolerance": 1e-10})  # 1e-7 lowers flat fans
        constant = measures[block] @ offsets[block] / d
        assert volume + _SLACK_PENALTY * slack == pytest.approx(best.fun + constant, rel=1e-6,
                                                                 abs=1e-9)
        assert (normals[block] @ v + offsets[block] + slack >= -1e-9).all()
        assert (slack > 1e-9) == np.isnan(lazy_slack)  # unsolved without a penalty
    needs_slack = np.mean([slack > 1e-9 for slack, _, _ in ours])
    assert needs_slack == 1 if shape == "cube" else needs_slack < 0.5
    if shape == "flat" and d == 3:  # some least volumes lie beyond the box: its sides hold them
        assert any(np.isclose(v, box.T).any() for slack, _, v in ours if slack <= 1e-9)


@pytest.mark.parametrize("k", [4, 5, 7])
def test_palette_size_and_cube(rng, k):
    colours = rng.random((2000, 3))
    poly = extract_palette(colours, np.ones(2000, int), k=k)
    assert len(poly.vertices) == k
    assert poly.vertices.min() >= 0 and poly.vertices.max() <= 1


@pytest.mark.parametrize(
    "colours, dim",
    [
        (np.full((10, 3), 0.3), 0),
        (np.array([[0.1, 0.2, 0.3], [0.9, 0.5, 0.1]]), 1),
        (np.linspace(0, 1, 50)[:, None].repeat(3, 1), 1),
        (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0]]), 2),
        (np.array([[0.2, 0.3, 0.4], [0.9, 0.1, 0.5], [0.4, 0.8, 0.1]]), 2),
    ],
    ids=["one colour", "two colours", "greys", "coplanar", "three pixels"],
)
def test_degenerate_colour_sets(colours, dim):
    poly = extract_palette(colours, np.ones(len(colours), int), k=6)
    assert poly.dim == dim
    weights = rgb_to_mvc_weights(colours, poly)
    weight_invariants(weights, poly.vertices, colours)


def test_coplanar_many_colours_simplified(rng):
    ab = rng.random((500, 2))
    colours = np.c_[ab, 0.5 * ab[:, 0] + 0.25]
    poly = extract_palette(colours, np.ones(500, int), k=5)
    assert len(poly.vertices) <= 5  # clipping to the cube may lift it off the plane
    weight_invariants(rgb_to_mvc_weights(colours, poly), poly.vertices, None)


def test_max_error_picks_smallest_palette_within_tolerance(rng):
    colours = rng.random((3000, 3))
    counts = np.ones(3000, int)
    loose = extract_palette(colours, counts, k=None, max_error=40.0)
    tight = extract_palette(colours, counts, k=None, max_error=0.5)
    assert len(loose.vertices) <= len(tight.vertices)
    assert polytope_rmse(colours, counts, tight) <= 0.5
    assert polytope_rmse(colours, counts, loose) <= 40.0
    exact = extract_palette(colours, counts, k=None, max_error=0.0)
    assert polytope_rmse(colours, counts, exact) == 0.0


def test_transparent_colours_do_not_shape_palette(rng):
    colours = np.vstack([rng.random((200, 3)) * 0.5, [[1.0, 1.0, 1.0]]])
    counts = np.r_[np.ones(200, int), 0]
    with_hidden = extract_palette(colours, counts, k=5)
    without = extract_palette(colours[:200], counts[:200], k=5)
    np.testing.assert_array_equal(with_hidden.vertices, without.vertices)


def test_rejects_bad_options(rng):
    colours = rng.random((100, 3))
    with pytest.raises(InputError, match="k must be at least 4"):
        extract_palette(colours, np.ones(100, int), k=3)
    with pytest.raises(InputError, match="max_error"):
        extract_palette(colours, np.ones(100, int), k=None, max_error=-1.0)
