"""Numba kernels: closest points on convex polytopes and mean value coordinates.

Arrays in, arrays out, no validation: every array is C-contiguous float64 (index
arrays int64) so each kernel compiles once. The wrappers in ``polytope.py`` and
``mvc.py`` validate, cast and restore shapes.

References
----------
Ju, Schaefer, Warren. Mean value coordinates for closed triangular meshes. SIGGRAPH 2005.
Hormann, Floater. Mean value coordinates for arbitrary planar polygons. ACM TOG 2006.
Ericson. Real-Time Collision Detection, Sec. 5.1.5 (closest point on a triangle). 2004.
"""

import math

import numpy as np
from numba import njit, prange

from .constants import EDGE_TOL, FACE_TOL, INSIDE_TOL, VERTEX_TOL


@njit(cache=True, inline="always")
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def _closest_on_triangle(p, a, b, c, out):
    """Write the point of triangle (a, b, c) closest to p into out (Ericson 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1, d2 = _dot3(ab, ap), _dot3(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        out[:] = a
        return
    bp = p - b
    d3, d4 = _dot3(ab, bp), _dot3(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        out[:] = b
        return
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        out[:] = a + ab * (d1 / (d1 - d3))
        return
    cp = p - c
    d5, d6 = _dot3(ab, cp), _dot3(ac, cp)
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
            if _dot3(normals[f], p) + offsets[f] > INSIDE_TOL:
                outside = True
                break
        if not outside:
            out[i] = p
            continue
        best = np.inf
        q = np.empty(3)
        for f in range(faces.shape[0]):
            _closest_on_triangle(p, vertices[faces[f, 0]], vertices[faces[f, 1]],
                                 vertices[faces[f, 2]], q)
            dist = _dot3(p - q, p - q)
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


@njit(cache=True, inline="always")
def _cross_dot(ax, ay, az, bx, by, bz, cx, cy, cz):
    """(a x b) . c"""
    return (ay * bz - az * by) * cx + (az * bx - ax * bz) * cy + (ax * by - ay * bx) * cz


@njit(cache=True)
def _mvc_polyhedron_point(x, vertices, faces, normals, offsets, d, u, w):
    """Mean value coordinates of one point x inside a convex polyhedron, into w (K,).

    d (K,) and u (K, 3) are scratch space for distances and unit directions.
    """
    k = vertices.shape[0]
    w[:] = 0.0
    # On a vertex: that vertex alone.
    for j in range(k):
        dx, dy, dz = vertices[j, 0] - x[0], vertices[j, 1] - x[1], vertices[j, 2] - x[2]
        d[j] = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d[j] < VERTEX_TOL:
            w[j] = 1.0
            return
        u[j, 0], u[j, 1], u[j, 2] = dx / d[j], dy / d[j], dz / d[j]
    # On an edge: linear weights of its two ends.
    for f in range(faces.shape[0]):
        for e in range(3):
            a, b = faces[f, e], faces[f, (e + 1) % 3]
            ex, ey, ez = vertices[b, 0] - vertices[a, 0], vertices[b, 1] - vertices[a, 1], \
                vertices[b, 2] - vertices[a, 2]
            px, py, pz = x[0] - vertices[a, 0], x[1] - vertices[a, 1], x[2] - vertices[a, 2]
            t = (px * ex + py * ey + pz * ez) / (ex * ex + ey * ey + ez * ez)
            if 0.0 <= t <= 1.0:
                rx, ry, rz = px - t * ex, py - t * ey, pz - t * ez
                if rx * rx + ry * ry + rz * rz < EDGE_TOL * EDGE_TOL:
                    w[a] = 1.0 - t
                    w[b] = t
                    return
    # On (or within FACE_TOL of) a face: barycentric weights of the face whose
    # triangle holds the point most surely (largest smallest coordinate).
    best_face, best_min = -1, -1e-6
    b0 = b1 = 0.0
    for f in range(faces.shape[0]):
        if abs(_dot3(normals[f], x) + offsets[f]) >= FACE_TOL:
            continue
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        # Sub-triangle volumes against the unit normal give 2-D barycentrics.
        nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
        full = _cross_dot(vertices[i1, 0] - vertices[i0, 0], vertices[i1, 1] - vertices[i0, 1],
                          vertices[i1, 2] - vertices[i0, 2], vertices[i2, 0] - vertices[i0, 0],
                          vertices[i2, 1] - vertices[i0, 1], vertices[i2, 2] - vertices[i0, 2],
                          nx, ny, nz)
        c0 = _cross_dot(vertices[i1, 0] - x[0], vertices[i1, 1] - x[1], vertices[i1, 2] - x[2],
                        vertices[i2, 0] - x[0], vertices[i2, 1] - x[1], vertices[i2, 2] - x[2],
                        nx, ny, nz) / full
        c1 = _cross_dot(vertices[i2, 0] - x[0], vertices[i2, 1] - x[1], vertices[i2, 2] - x[2],
                        vertices[i0, 0] - x[0], vertices[i0, 1] - x[1], vertices[i0, 2] - x[2],
                        nx, ny, nz) / full
        lowest = min(c0, c1, 1.0 - c0 - c1)
        if lowest > best_min:
            best_face, best_min, b0, b1 = f, lowest, c0, c1
    if best_face >= 0:
        b0, b1 = max(b0, 0.0), max(b1, 0.0)
        b2 = max(1.0 - b0 - b1, 0.0)
        total = b0 + b1 + b2
        w[faces[best_face, 0]] = b0 / total
        w[faces[best_face, 1]] = b1 / total
        w[faces[best_face, 2]] = b2 / total
        return
    # Strictly inside: each face's mean vector m = sum over its edges of
    # theta_e / 2 * n_e (n_e the unit normal of the plane through x and the
    # edge, theta_e the edge's angle seen from x) is split along the unit
    # vectors to its corners, lambda_i = (n_jk . m) / (n_jk . u_i), and corner i
    # gains lambda_i / d_i (Ju, Schaefer, Warren 2005, Sec. 3.2). The angles come
    # from atan2 and the splits from determinants, which stay accurate close to
    # a face, unlike the arcsin/sin form of their Fig. 4.
    for f in range(faces.shape[0]):
        mx = my = mz = 0.0
        for e in range(3):
            a, b = faces[f, e], faces[f, (e + 1) % 3]
            cx = u[a, 1] * u[b, 2] - u[a, 2] * u[b, 1]
            cy = u[a, 2] * u[b, 0] - u[a, 0] * u[b, 2]
            cz = u[a, 0] * u[b, 1] - u[a, 1] * u[b, 0]
            sine = math.sqrt(cx * cx + cy * cy + cz * cz)
            half_angle = 0.5 * math.atan2(sine, u[a, 0] * u[b, 0] + u[a, 1] * u[b, 1]
                                          + u[a, 2] * u[b, 2]) / sine
            mx += half_angle * cx
            my += half_angle * cy
            mz += half_angle * cz
        for e in range(3):
            a, b = faces[f, e], faces[f, (e + 1) % 3]
            o = faces[f, (e + 2) % 3]  # the corner off edge e
            # (u_a x u_b) . m / ((u_a x u_b) . u_o): the normal's length cancels.
            w[o] += (_cross_dot(u[a, 0], u[a, 1], u[a, 2], u[b, 0], u[b, 1], u[b, 2], mx, my, mz)
                     / (_cross_dot(u[a, 0], u[a, 1], u[a, 2], u[b, 0], u[b, 1], u[b, 2],
                                   u[o, 0], u[o, 1], u[o, 2]) * d[o]))
    total = w.sum()
    for j in range(k):
        w[j] /= total


@njit(cache=True, parallel=True)
def mvc_polyhedron(points, vertices, faces, normals, offsets, n_chunks, out):
    """Mean value coordinates of points (n, 3) inside a convex polyhedron; out (n, K).

    Points go in n_chunks chunks, each with its own scratch arrays.
    """
    k = vertices.shape[0]
    for c in prange(n_chunks):
        d = np.empty(k)
        u = np.empty((k, 3))
        for i in range(c * points.shape[0] // n_chunks, (c + 1) * points.shape[0] // n_chunks):
            _mvc_polyhedron_point(points[i], vertices, faces, normals, offsets, d, u, out[i])


@njit(cache=True, parallel=True)
def mvc_polygon(points, polygon, out):
    """Mean value coordinates of points (n, 2) inside a convex counter-clockwise polygon (K, 2).

    Uses tan(alpha/2) = A / (r r' + D) = (r r' - D) / A, whichever form is stable
    (Hormann and Floater 2006, Sec. 4); out (n, K).
    """
    k = polygon.shape[0]
    for i in prange(points.shape[0]):
        w = out[i]
        w[:] = 0.0
        sx = polygon[:, 0] - points[i, 0]
        sy = polygon[:, 1] - points[i, 1]
        r = np.sqrt(sx * sx + sy * sy)
        done = False
        for j in range(k):
            if r[j] < VERTEX_TOL:
                w[j] = 1.0
                done = True
                break
        if done:
            continue
        tan_half = np.empty(k)
        for j in range(k):
            jn = (j + 1) % k
            area = sx[j] * sy[jn] - sy[j] * sx[jn]
            dot = sx[j] * sx[jn] + sy[j] * sy[jn]
            length = math.hypot(polygon[jn, 0] - polygon[j, 0], polygon[jn, 1] - polygon[j, 1])
            if area < FACE_TOL * length and dot < 0.0:  # on this edge: linear weights
                w[j] = r[jn] / (r[j] + r[jn])
                w[jn] = r[j] / (r[j] + r[jn])
                done = True
                break
            rr = r[j] * r[jn]
            tan_half[j] = area / (rr + dot) if dot >= 0.0 else (rr - dot) / area
        if done:
            continue
        total = 0.0
        for j in range(k):
            w[j] = (tan_half[j - 1] + tan_half[j]) / r[j]
            total += w[j]
        for j in range(k):
            w[j] /= total
