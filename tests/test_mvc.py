"""Mean value coordinates: oracle, invariants and exact boundary cases."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls
from scipy.spatial import Delaunay

from palette_core import InputError, polytope_from_points, rgb_to_mvc_weights
from palette_core.constants import FACE_TOL
from palette_core.polytope import project_to_polytope

from .helpers import weight_invariants

CUBE = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
seeds = st.integers(0, 2**32 - 1)


def inside_samples(vertices, n, rng):
    return rng.dirichlet(np.ones(len(vertices)) * 0.5, size=n) @ vertices


def check(poly, colours):
    weights = rgb_to_mvc_weights(colours, poly)
    projected = poly.from_local(project_to_polytope(colours, poly))
    weight_invariants(weights, poly.vertices, projected)
    return weights


@settings(max_examples=30, deadline=None)
@given(seeds)
def test_tetrahedron_equals_barycentric(seed):
    rng = np.random.default_rng(seed)
    poly = polytope_from_points(rng.random((4, 3)))
    if poly.dim < 3:
        return
    colours = inside_samples(poly.vertices, 50, rng)
    tri = Delaunay(poly.vertices)
    simplex = tri.find_simplex(colours, tol=1e-9)
    b = np.einsum("nij,nj->ni", tri.transform[simplex, :3], colours - tri.transform[simplex, 3])
    oracle = np.zeros((len(colours), 4))
    np.put_along_axis(oracle, tri.simplices[simplex], np.c_[b, 1 - b.sum(1)], axis=1)
    # a colour within FACE_TOL of a face is put on it, which moves the weight of the opposite
    # vertex by up to FACE_TOL / (that vertex's altitude): tiny, unless the tetrahedron is thin
    v = poly.vertices
    volume = abs(np.linalg.det(v[1:] - v[0])) / 6
    largest_face = max(np.linalg.norm(np.cross(v[j] - v[i], v[k] - v[i])) / 2
                       for i, j, k in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)))
    atol = max(1e-8, 2 * FACE_TOL * largest_face / (3 * volume))
    np.testing.assert_allclose(rgb_to_mvc_weights(colours, poly), oracle, atol=atol)


@settings(max_examples=30, deadline=None)
@given(seeds, st.integers(5, 40), st.sampled_from([1.0, 1e-2, 1e-4, 1e-6]))
def test_random_and_thin_polytopes(seed, n, thickness):
    rng = np.random.default_rng(seed)
    points = rng.random((n, 3))
    points[:, 2] *= thickness
    poly = polytope_from_points(points)
    colours = np.vstack([inside_samples(poly.vertices, 200, rng), rng.random((50, 3)) * 1.4 - 0.2])
    check(poly, colours)


def test_cube_interior_vertices_edges_faces(rng):
    poly = polytope_from_points(CUBE)
    w = check(poly, CUBE)
    assert (np.sort(w, axis=1)[:, -1] == 1).all()  # a vertex takes its own weight alone
    edge = rng.random((200, 3))
    edge[:, 1], edge[:, 2] = 0.0, 1.0
    assert ((check(poly, edge) > 0).sum(1) <= 2).all()
    face = rng.random((200, 3))
    face[:, 0] = 1.0
    assert ((check(poly, face) > 0).sum(1) <= 3).all()
    check(poly, rng.random((2000, 3)))


@pytest.mark.parametrize("distance", [1e-3, 1e-6, 1e-8, 1e-10, 1e-12, 0.0])
def test_close_to_a_face(rng, distance):
    colours = rng.random((500, 3))
    colours[:, 2] = distance
    check(polytope_from_points(CUBE), colours)


def test_clipped_channels(rng):
    """Image colours at 0 and 255 lie exactly on faces of a hull that touches the cube."""
    colours = np.round(rng.random((3000, 3)) * 255) / 255
    colours[:1000, 0] = 0.0
    colours[1000:2000, 1] = 1.0
    colours[2000:, :2] = 0.0
    check(polytope_from_points(colours), colours)


def test_projection_is_the_closest_point(rng):
    """Colours outside go to the polytope's closest point: the least distance over all convex
    combinations of the vertices (NNLS with a heavily weighted sum-to-one row)."""
    poly = polytope_from_points(rng.random((20, 3)))
    colours = rng.random((300, 3)) * 3 - 1
    projected = poly.from_local(project_to_polytope(colours, poly))
    rows = np.r_[poly.vertices.T, np.full((1, len(poly.vertices)), 1e4)]
    for colour, point in zip(colours, projected):
        weights, _ = nnls(rows, np.r_[colour, 1e4])
        assert np.linalg.norm(colour - point) == pytest.approx(
            np.linalg.norm(colour - weights @ poly.vertices), abs=1e-6)


def test_lower_dimensional_polytopes(rng):
    single = polytope_from_points(np.full((5, 3), 0.4))
    assert single.dim == 0
    np.testing.assert_array_equal(check(single, np.array([[0.4] * 3])), [[1.0]])
    greys = polytope_from_points(np.linspace(0.1, 0.9, 9)[:, None].repeat(3, 1))
    assert greys.dim == 1
    check(greys, np.linspace(0, 1, 20)[:, None].repeat(3, 1))
    plane = rng.random((50, 3))
    plane[:, 2] = 1.0 - plane[:, 0] * 0.5  # coplanar colours
    flat = polytope_from_points(plane)
    assert flat.dim == 2
    colours = np.vstack([plane, inside_samples(flat.vertices, 300, rng), flat.vertices])
    w = check(flat, colours)
    assert (np.sort(w[-len(flat.vertices):], axis=1)[:, -1] == 1).all()


def test_any_leading_shape(rng):
    poly = polytope_from_points(CUBE)
    colours = rng.random((2, 3, 4, 3))
    flat = rgb_to_mvc_weights(colours.reshape(-1, 3), poly)
    np.testing.assert_array_equal(rgb_to_mvc_weights(colours, poly), flat.reshape(2, 3, 4, 8))


@pytest.mark.parametrize("bad", [np.zeros((4, 2)), np.array([[np.nan, 0, 0]]),
                                 np.array([[np.inf, 0, 0]])])
def test_rejects_bad_colours(bad):
    with pytest.raises(InputError, match="rgb"):
        rgb_to_mvc_weights(bad, polytope_from_points(CUBE))


@pytest.mark.parametrize("flat", [False, True])
def test_a_stacks_weights_come_again_for_its_own_colours_in_its_palettes_order(photo_dir, flat,
                                                                             tmp_path, rng):
    """``palette_weights`` gives a stored palette's weights of other colours: for the
    stack's own pixels, the weights it holds (a solid palette, and a flat one whose
    polytope orders its vertices otherwise)."""
    from PIL import Image

    from palette_core.decompose import decompose
    from palette_core.io import load_image
    from palette_core.weights import palette_weights

    if flat:  # colours of the plane blue = 0
        photo_dir = tmp_path / "flat"
        photo_dir.mkdir()
        pixels = (rng.random((12, 12, 3)) * [255, 255, 0]).astype(np.uint8)
        Image.fromarray(pixels).save(photo_dir / "a.png")
    stack = decompose([str(photo_dir)], k=6).stack
    assert (len(stack.hull_faces) == 0) == flat
    image = load_image(photo_dir / stack.names[0])
    weights = palette_weights(image.rgb.reshape(-1, 3), stack.palette, stack.hull_faces)
    assert np.allclose(weights, stack.weights[0].reshape(len(weights), -1), atol=2e-3)
