"""RGBXY weights: oracle on small inputs, star coordinates, invariants, degenerate sets."""

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import ConvexHull, Delaunay

from palette_core import decompose, polytope_from_points
from palette_core import rgbxy as rgbxy_module
from palette_core.cli import decompose as decompose_cli
from palette_core.colour_set import ColourSet
from palette_core.hull import extract_palette
from palette_core.io import LoadedImage
from palette_core.rgbxy import canvas_offsets, rgbxy_image_weights, star_coordinates

from .helpers import expect_error, weight_invariants


def loaded(pixels):
    pixels = np.asarray(pixels, np.uint8)
    return LoadedImage("x.png", pixels, np.ones(pixels.shape[:2], bool))


def rgbxy_weights(images, k=6, **options):
    colour_set = ColourSet.from_images(images)
    poly = extract_palette(colour_set.colours, colour_set.counts, k, None)
    return poly, list(rgbxy_image_weights(colour_set, poly, **options))


def test_matches_a_brute_force_oracle(rng, monkeypatch):
    monkeypatch.setattr(rgbxy_module, "CHUNK_PIXELS", 9)  # many hull merges
    image = loaded(rng.integers(0, 256, (7, 6, 3)))
    poly, (weights,) = rgbxy_weights([image], k=5)
    yy, xx = np.mgrid[0:7, 0:6]
    points = np.hstack([image.pixels.reshape(-1, 3) / 255.0,
                        np.stack([xx.ravel(), yy.ravel()], 1) / 7.0])
    vertices = points[ConvexHull(points).vertices]
    tri = Delaunay(vertices)
    simplex = tri.find_simplex(points, tol=1e-9)
    assert (simplex >= 0).all()
    transform = tri.transform[simplex]
    partial = np.einsum("nij,nj->ni", transform[:, :5], points - transform[:, 5])
    bary = np.hstack([partial, 1 - partial.sum(1, keepdims=True)])
    expected = np.einsum("nj,njk->nk", bary,
                         star_coordinates(vertices[:, :3], poly)[tri.simplices[simplex]])
    np.testing.assert_allclose(weights.reshape(-1, len(poly.vertices)), expected, atol=1e-5)


@pytest.mark.parametrize("kind", ["random", "cube"])
def test_star_coordinates_reproduce_colours_sparsely(rng, kind):
    # The cube has facets in planes through its darkest corner: flat simplices.
    corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1]), -1).reshape(-1, 3)
    poly = polytope_from_points(rng.random((30, 3)) if kind == "random" else corners)
    inside = rng.dirichlet(np.ones(len(poly.vertices)), 200) @ poly.vertices
    weights = star_coordinates(inside, poly)
    weight_invariants(weights, poly.vertices, inside)
    assert ((weights > 1e-12).sum(axis=1) <= 4).all()
    # Outside colours are projected first, then expressed exactly.
    outside = star_coordinates(np.array([[2.0, 2.0, 2.0], [-1, 0.5, 0.5]]), poly)
    weight_invariants(outside, poly.vertices, None)


@pytest.mark.parametrize("palette_points", [
    [[0.5, 0.5, 0.5]],                                  # a point
    [[0, 0, 0], [1, 1, 1]],                             # a segment (greys)
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]],       # a polygon
])
def test_star_coordinates_in_flat_palettes(palette_points, rng):
    poly = polytope_from_points(np.array(palette_points, float))
    colours = rng.dirichlet(np.ones(len(poly.vertices)), 50) @ poly.vertices
    weight_invariants(star_coordinates(colours, poly), poly.vertices, colours)


def test_canvas_places_images_in_rows():
    offsets, side = canvas_offsets([(10, 20)] * 5)
    assert offsets.tolist() == [[0, 0], [0, 20], [0, 40], [10, 0], [10, 20]]
    assert side == 60


def test_photos_of_different_sizes(photo_dir):
    result = decompose([photo_dir], k=5, method="rgbxy")
    stack = result.stack
    assert stack.method == "rgbxy"
    assert [w.shape[:2] for w in stack.weights] == [(12, 16), (10, 9), (7, 11)]
    for w in stack.weights:
        weight_invariants(w.reshape(-1, w.shape[-1]), stack.palette, None)
    # With the whole hull as palette every pixel is reproduced exactly.
    exact = decompose([photo_dir], k=None, max_error=0.0, method="rgbxy")
    assert exact.rmse_overall < 1e-3


def grey_ramp(h, w):
    return np.repeat(np.linspace(0, 255, w, dtype=np.uint8)[None, :, None], h, 0).repeat(3, 2)


@pytest.mark.parametrize("pixels", [
    np.full((1, 1, 3), 77),                                   # 1x1 image: one point
    np.full((5, 6, 3), 200),                                  # one colour: flat in RGB
    grey_ramp(4, 9),                                          # greys: colours on a line
    np.array([[[10, 20, 30], [200, 100, 50]]]),               # two pixels: a segment
    np.stack([np.arange(48).reshape(6, 8) * 5,                # coplanar colours (B = 60)
              np.arange(48).reshape(6, 8)[::-1] * 4,
              np.full((6, 8), 60)], -1),
], ids=["1x1", "one-colour", "greys", "two-pixels", "coplanar"])
def test_degenerate_inputs(pixels):
    image = loaded(pixels)
    colour_set = ColourSet.from_images([image])
    poly = extract_palette(colour_set.colours, colour_set.counts, 6, None)
    (weights,) = rgbxy_image_weights(colour_set, poly)
    assert weights.shape == (*pixels.shape[:2], len(poly.vertices))
    flat = weights.reshape(-1, len(poly.vertices))
    weight_invariants(flat, poly.vertices, image.pixels.reshape(-1, 3) / 255.0)


def test_spatial_scale_option(photo_dir, tmp_path, capsys):
    out = tmp_path / "w.npz"
    assert decompose_cli.main([str(photo_dir), "--method", "rgbxy", "--spatial-scale", "4",
                               "-o", str(out)]) == 0
    expect_error(decompose_cli.main, [str(photo_dir), "--spatial-scale", "2", "-o",
                                      str(tmp_path / "m.npz")], "rgbxy only", capsys)
    expect_error(decompose_cli.main, [str(photo_dir), "--method", "rgbxy", "--spatial-scale",
                                      "0", "-o", str(tmp_path / "z.npz")],
                 "must be a positive number", capsys)


def test_image_sizes_from_files(tmp_path, rng):
    Image.fromarray(rng.integers(0, 256, (1, 1, 3), dtype=np.uint8)).save(tmp_path / "a.png")
    Image.fromarray(rng.integers(0, 256, (5, 3, 3), dtype=np.uint8)).save(tmp_path / "b.png")
    stack = decompose([tmp_path], k=4, method="rgbxy").stack
    assert [w.shape for w in stack.weights] == [(1, 1, 4), (5, 3, 4)]
