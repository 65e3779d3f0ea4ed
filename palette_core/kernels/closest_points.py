"""Closest points on convex polytopes: of points outside a polyhedron on its boundary, and of
points outside a polygon on its edges.

Ericson. Real-Time Collision Detection, Sec. 5.1.5 (closest point on a triangle). 2004.
"""

import math

import numpy as np
from numba import njit, prange

from ..constants import INSIDE_TOL
from .vectors import dot3


@njit(cache=True)
def _closest_on_triangle(p, a, b, c, out):
    """Write the point of triangle (a, b, c) closest to p into out (Ericson 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1, d2 = dot3(ab, ap), dot3(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        out[:] = a
        return
    bp = p - b
    d3, d4 = dot3(ab, bp), dot3(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        out[:] = b
        return
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        out[:] = a + ab * (d1 / (d1 - d3))
        return
    cp = p - c
    d5, d6 = dot3(ab, cp), dot3(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        out[:] = c
        return
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        out[:] = a + ac * (d2 / (d2 - d6))
        return
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        out[:] = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        return
    denom = 1.0 / (va + vb + vc)
    out[:] = a + ab * (vb * denom) + ac * (vc * denom)


@njit(cache=True, parallel=True)
def project_to_polyhedron(points, vertices, faces, normals, offsets, out):
    """Closest point of a convex polyhedron to each point.

    points (n, 3), vertices (K, 3), faces (F, 3) outward triangles, normals (F, 3)
    unit outward, offsets (F,) with n.x + offset <= 0 inside; out (n, 3).
    """
    for i in prange(points.shape[0]):
        p = points[i]
        outside = False
        for f in range(faces.shape[0]):
            if dot3(normals[f], p) + offsets[f] > INSIDE_TOL:
                outside = True
                break
        if not outside:
            out[i] = p
            continue
        # The closest point lies on a face whose plane has p in front: one of the
        # faces around it has n . (p - q) > 0, or |p - q|^2 = sum lambda_f n_f . (p - q)
        # would not be positive.
        best = np.inf
        q = np.empty(3)
        for f in range(faces.shape[0]):
            if dot3(normals[f], p) + offsets[f] <= 0.0:
                continue
            _closest_on_triangle(p, vertices[faces[f, 0]], vertices[faces[f, 1]],
                                 vertices[faces[f, 2]], q)
            dist = dot3(p - q, p - q)
            if dist < best:
                best = dist
                out[i] = q


@njit(cache=True, parallel=True)
def project_to_polygon(points, polygon, out):
    """Closest point of a convex polygon to each point.

    points (n, 2), polygon (K, 2) counter-clockwise; out (n, 2).
    """
    k = polygon.shape[0]
    for i in prange(points.shape[0]):
        px, py = points[i, 0], points[i, 1]
        outside = False
        for j in range(k):
            ax, ay = polygon[j, 0], polygon[j, 1]
            bx, by = polygon[(j + 1) % k, 0], polygon[(j + 1) % k, 1]
            ex, ey = bx - ax, by - ay
            if ex * (py - ay) - ey * (px - ax) < -INSIDE_TOL * math.hypot(ex, ey):
                outside = True
                break
        if not outside:
            out[i, 0], out[i, 1] = px, py
            continue
        best = np.inf
        for j in range(k):
            ax, ay = polygon[j, 0], polygon[j, 1]
            ex, ey = polygon[(j + 1) % k, 0] - ax, polygon[(j + 1) % k, 1] - ay
            t = ((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey)
            t = min(max(t, 0.0), 1.0)
            qx, qy = ax + t * ex, ay + t * ey
            dist = (px - qx) ** 2 + (py - qy) ** 2
            if dist < best:
                best = dist
                out[i, 0], out[i, 1] = qx, qy
