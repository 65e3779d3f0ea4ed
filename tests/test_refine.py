"""The refined palette: count-weighted fidelity on hard stitched sets, the box QP, consistency
of -k and --max-error."""

import numpy as np
import pytest

from palette_core import ColourSet, LoadedImage, polytope_rmse
from palette_core.palettes import palette_polytope
from palette_core.polytope import polytope_from_points
from palette_core.refine import (
    _alternate,
    _box_qp,
    binned_colours,
    common_colours,
    refined_palette,
)

from .helpers import weight_invariants


def colour_set(*pixel_arrays) -> ColourSet:
    return ColourSet.from_images([LoadedImage(f"i{n}", p, np.ones(p.shape[:2], bool))
                                  for n, p in enumerate(pixel_arrays)])


def per_image_rmse(cs: ColourSet, poly) -> list[float]:
    rmse = []
    for i in range(len(cs.images)):
        index, counts = np.unique(cs.image_indices(i), return_counts=True)
        rmse.append(polytope_rmse(cs.colours[index], counts, poly))
    return rmse


@pytest.fixture
def black_and_rainbow(rng):
    """A nearly black photo stitched with a colour-rich one whose hull is almost the cube."""
    night = np.clip(rng.normal(6, 3, (60, 60, 3)), 0, 255).astype(np.uint8)
    night[:2, :2] = 250  # two bright stars
    rainbow = rng.integers(30, 256, (60, 60, 3), dtype=np.uint8)
    rainbow[0, :8] = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [255, 0, 255],
                      [0, 255, 255], [255, 255, 255], [30, 30, 30]]
    return colour_set(night, rainbow)


def test_a_black_photo_keeps_black(black_and_rainbow):
    cs = black_and_rainbow
    hull = palette_polytope(cs.colours, cs.counts, 6, method="hull")
    refined = palette_polytope(cs.colours, cs.counts, 6, method="refined")
    night_hull, _ = per_image_rmse(cs, hull)
    night, rainbow = per_image_rmse(cs, refined)
    assert night < 3.0 < night_hull  # loose: the hull method drops black (about 17 here)
    assert polytope_rmse(cs.colours, cs.counts, refined) <= polytope_rmse(cs.colours, cs.counts,
                                                                          hull)
    assert np.sqrt(((refined.vertices[:, None] - cs.colours[cs.counts > 0][None]) ** 2)
                   .sum(-1)).min(1).min() < 2 / 255  # one colour is black itself


def test_the_whole_cube(rng):
    cube = rng.integers(0, 256, (80, 80, 3), dtype=np.uint8)
    cube[0, :8] = np.array(np.meshgrid([0, 255], [0, 255], [0, 255])).reshape(3, -1).T
    cs = colour_set(cube)
    for k in (4, 6, 8):
        poly = refined_palette(cs.colours, cs.counts, k)
        assert poly.vertices.shape == (k, 3)
        assert ((poly.vertices >= 0) & (poly.vertices <= 1)).all()
        assert polytope_rmse(cs.colours, cs.counts, poly) <= polytope_rmse(
            cs.colours, cs.counts, palette_polytope(cs.colours, cs.counts, k, method="hull"))
    assert polytope_rmse(cs.colours, cs.counts, poly) < 1e-9  # eight corners hold the cube


def test_never_worse_than_the_hull_method(black_and_rainbow, rng):
    greens = np.stack([rng.integers(0, 60, (40, 40)), rng.integers(100, 256, (40, 40)),
                       rng.integers(0, 90, (40, 40))], -1).astype(np.uint8)
    for cs in (black_and_rainbow, colour_set(greens)):
        for k in (4, 5, 7, 10):
            hull = palette_polytope(cs.colours, cs.counts, k, method="hull")
            refined = palette_polytope(cs.colours, cs.counts, k, method="refined")
            assert len(refined.vertices) == k  # the hull method's clip may merge colours
            assert polytope_rmse(cs.colours, cs.counts, refined) <= polytope_rmse(
                cs.colours, cs.counts, hull) + 1e-9


def test_k_and_max_error_agree(black_and_rainbow):
    cs = black_and_rainbow
    for k in (4, 5, 6):
        by_k = refined_palette(cs.colours, cs.counts, k)
        error = polytope_rmse(cs.colours, cs.counts, by_k)
        by_error = refined_palette(cs.colours, cs.counts, None, error)
        if len(by_error.vertices) == k:
            assert np.array_equal(by_k.vertices, by_error.vertices)
        assert len(by_error.vertices) <= k


@pytest.mark.parametrize("pixels", [
    np.full((4, 4, 3), 128, np.uint8),  # one colour
    np.repeat(np.arange(0, 256, 16, dtype=np.uint8)[:, None, None], 3, 2).repeat(2, 1),  # greys
    np.stack([*np.meshgrid(np.arange(0, 256, 32), np.arange(0, 256, 32)),
              np.full((8, 8), 99)], -1).astype(np.uint8),  # one plane
])
def test_degenerate_sets_get_their_exact_hull(pixels):
    cs = colour_set(pixels)
    poly = refined_palette(cs.colours, cs.counts, 6)
    assert poly.dim < 3 and polytope_rmse(cs.colours, cs.counts, poly) < 1e-9
    from palette_core import rgb_to_mvc_weights
    weight_invariants(rgb_to_mvc_weights(cs.colours, poly), poly.vertices, cs.colours)


def test_box_qp_matches_brute_force(rng):
    for _ in range(20):
        m = rng.normal(size=(6, 6))
        a, b = m @ m.T + 0.1 * np.eye(6), rng.normal(size=6) * 3
        x = _box_qp(a, b, rng.uniform(0, 1, 6))
        best = min(_objective(a, b, y) for y in rng.uniform(0, 1, (20000, 6)))
        assert _objective(a, b, x) <= best + 1e-12
        gradient = a @ x - b  # KKT
        assert np.all(gradient[(x > 1e-12) & (x < 1 - 1e-12)] ** 2 < 1e-16)
        assert np.all(gradient[x <= 1e-12] >= -1e-9) and np.all(gradient[x >= 1 - 1e-12] <= 1e-9)


def _objective(a, b, x):
    return 0.5 * x @ a @ x - b @ x


def test_extrapolated_steps_report_their_palettes_error(rng):
    """Steps that overshoot fall back to the plain update: the palette returned has the error
    returned (the binned RMSE), below the start's."""
    colours = rng.dirichlet(np.full(6, 0.3), 4000) @ rng.random((6, 3))
    bins, shares = binned_colours(colours, np.ones(len(colours), int))
    start = rng.random((6, 3))
    palette, error = _alternate(start, bins, shares)
    assert error == pytest.approx(polytope_rmse(bins, shares, polytope_from_points(palette)))
    assert error < polytope_rmse(bins, shares, polytope_from_points(start))


def test_bins_and_common_colours(rng):
    colours = rng.uniform(0, 1, (1000, 3))
    counts = rng.integers(0, 50, 1000)
    counts[0] = 10**6
    bins, shares = binned_colours(colours, counts)
    assert np.isclose(shares.sum(), 1) and len(bins) <= 1000
    common = common_colours(bins, shares)
    assert np.any(np.all(np.abs(common - colours[0]) < 1 / 32, axis=1))
