"""The palette polytope: the convex hull of the palette colours, of any dimension.

A colour set need not span RGB space: one colour spans a point, two colours or
greys a segment, colours of one plane a polygon. ``polytope_from_points`` finds
the affine dimension from the singular values of the centred points and builds
the hull in that subspace, so degenerate sets give a valid palette (a point, a
segment or a polygon) instead of a Qhull error. Qhull is asked again with joggle
(``QJ``, as trimesh does) when a nearly flat set defeats it, and the set is
treated as planar when that fails too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .constants import RANK_TOL
from .kernels import closest_points


@dataclass(frozen=True)
class Polytope:
    """A convex polytope given by its vertices, in the affine subspace it spans.

    Attributes
    ----------
    vertices : (K, 3) float64
        The palette colours. For ``dim == 2`` they run counter-clockwise in the
        local frame; for ``dim == 1`` they are the two ends of the segment.
    dim : int
        Affine dimension, 0 to 3.
    origin : (3,) float64
        A point of the affine subspace.
    basis : (dim, 3) float64
        Orthonormal rows; local coordinates are ``(x - origin) @ basis.T``.
    faces : (F, 3) int64
        Outward-oriented triangles when ``dim == 3``, else empty.
    """

    vertices: np.ndarray
    dim: int
    origin: np.ndarray
    basis: np.ndarray
    faces: np.ndarray

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) colours -> (n, dim) coordinates in the polytope's subspace."""
        return (points - self.origin) @ self.basis.T

    def from_local(self, coords: np.ndarray) -> np.ndarray:
        """(n, dim) local coordinates -> (n, 3) colours."""
        return self.origin + coords @ self.basis

    @property
    def planes(self) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3) unit outward normals and (F,) offsets: ``n . x + offset <= 0`` inside."""
        v = self.vertices[self.faces]
        normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return normals, -np.einsum("fi,fi->f", normals, v[:, 0])


def polytope_from_points(points: np.ndarray) -> Polytope:
    """Convex hull of (n, 3) points as a ``Polytope`` of the dimension they span.

    The vertices are input points (not moved); the hull is computed in the local
    frame given by the SVD of the centred points.

    Examples
    --------
    >>> greys = np.linspace(0, 1, 5)[:, None].repeat(3, axis=1)
    >>> poly = polytope_from_points(greys)
    >>> poly.dim, poly.vertices.tolist()
    (1, [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    origin = points.mean(axis=0)
    _, sing, frame = np.linalg.svd(points - origin, full_matrices=False)
    spread = sing[0] / np.sqrt(len(points))  # RMS distance from the centroid
    dim = int(np.sum(sing > RANK_TOL * sing[0])) if spread > RANK_TOL else 0
    no_faces = np.zeros((0, 3), np.int64)
    if dim == 3:
        hull = qhull(points)
        if hull is not None:
            return _polyhedron(points, hull)
        dim = 2
    if dim == 2:
        basis = frame[:2]
        hull = qhull((points - origin) @ basis.T)
        if hull is not None:  # 2-D hull vertices come counter-clockwise
            return Polytope(points[hull.vertices], 2, origin, basis, no_faces)
        dim = 1
    if dim == 1:
        t = (points - origin) @ frame[0]
        ends = points[[np.argmin(t), np.argmax(t)]]
        return Polytope(ends, 1, origin, frame[:1], no_faces)
    return Polytope(points[:1], 0, points[0], np.zeros((0, 3)), no_faces)


def qhull(points: np.ndarray) -> ConvexHull | None:
    """Qhull's hull of (n, d) points, retried with joggle (``QJ``, as trimesh does); None
    when the points are too flat or too few for it."""
    for options in (None, "QJ"):
        try:
            return ConvexHull(points, qhull_options=options)
        except (QhullError, ValueError):
            continue
    return None


def _polyhedron(points: np.ndarray, hull: ConvexHull) -> Polytope:
    """3-D ``Polytope`` from a Qhull hull: outward triangles, zero-area ones dropped."""
    vertices = points[hull.vertices]
    remap = np.full(len(points), -1)
    remap[hull.vertices] = np.arange(len(hull.vertices))
    faces = remap[hull.simplices]
    v = vertices[faces]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("fi,fi->f", normals, hull.equations[:, :3]) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    area2 = np.linalg.norm(normals, axis=1)
    faces = faces[area2 > RANK_TOL * max(area2.max(), 1e-300)]
    return Polytope(vertices, 3, np.zeros(3), np.eye(3), faces.astype(np.int64))


def project_to_polytope(colours: np.ndarray, poly: Polytope) -> np.ndarray:
    """Closest point of the polytope to each colour, in local coordinates.

    Parameters
    ----------
    colours : (n, 3) float
    poly : Polytope

    Returns
    -------
    (n, poly.dim) float64
        Local coordinates (see ``Polytope.to_local``) of the projected colours;
        colours inside the polytope are unchanged.
    """
    local = np.ascontiguousarray(poly.to_local(np.asarray(colours, np.float64)))
    ends = poly.to_local(poly.vertices)
    out = np.empty_like(local)
    if poly.dim == 3:
        normals, offsets = poly.planes
        closest_points.project_to_polyhedron(local, ends, poly.faces, normals, offsets, out)
    elif poly.dim == 2:
        closest_points.project_to_polygon(local, np.ascontiguousarray(ends), out)
    elif poly.dim == 1:
        out[:] = np.clip(local, ends.min(), ends.max())
    return out


def polytope_rmse(colours: np.ndarray, counts: np.ndarray, poly: Polytope) -> float:
    """Per-channel RMSE (0-255 scale) of colours against their closest polytope points.

    This is the reconstruction error of any weights that reproduce projected
    colours exactly; ``counts`` (n,) weights each colour by its pixel count.
    """
    projected = poly.from_local(project_to_polytope(colours, poly))
    sq = np.einsum("ij,ij->i", colours - projected, colours - projected)
    return float(255.0 * np.sqrt(np.dot(counts, sq) / (3.0 * max(counts.sum(), 1))))
