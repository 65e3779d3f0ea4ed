"""Numba kernels: closest points on convex polytopes, mean value coordinates, and the
edge-collapse LPs of hull simplification.

Arrays in, arrays out, no validation: every array is C-contiguous float64 (index
arrays int64) so each kernel compiles once. The wrappers in ``polytope.py``,
``mvc.py`` and ``hull.py`` validate, cast and restore shapes.

References
----------
Ju, Schaefer, Warren. Mean value coordinates for closed triangular meshes. SIGGRAPH 2005.
Hormann, Floater. Mean value coordinates for arbitrary planar polygons. ACM TOG 2006.
Ericson. Real-Time Collision Detection, Sec. 5.1.5 (closest point on a triangle). 2004.
"""

import math

import numpy as np
from numba import njit, prange

from .constants import (
    EDGE_TOL,
    FACE_TOL,
    INSIDE_TOL,
    LP_FEASIBILITY_TOL,
    LP_OPTIMALITY_TOL,
    LP_PIVOT_TOL,
    VERTEX_TOL,
)


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
        # The closest point lies on a face whose plane has p in front: one of the
        # faces around it has n . (p - q) > 0, or |p - q|^2 = sum lambda_f n_f . (p - q)
        # would not be positive.
        best = np.inf
        q = np.empty(3)
        for f in range(faces.shape[0]):
            if _dot3(normals[f], p) + offsets[f] <= 0.0:
                continue
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
def _mvc_polyhedron_point(x, vertices, faces, normals, offsets, ends, face_edges, d, u, cross,
                          scaled, w):
    """Mean value coordinates of one point x inside a convex polyhedron, into w (K,).

    ends (E, 2) are the polyhedron's edges, face_edges (F, 3) each face's edges (id + 1,
    negative where the face runs the edge backwards: ``edge_table``); d (K,), u (K, 3),
    cross and scaled (E, 3) are scratch space.
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
    # A point on an edge or a face lies on a face plane: far from all of them (most
    # points), skip both tests.
    on_a_plane = False
    for f in range(faces.shape[0]):
        if abs(_dot3(normals[f], x) + offsets[f]) < 2.0 * max(EDGE_TOL, FACE_TOL):
            on_a_plane = True
            break
    # On an edge: linear weights of its two ends.
    for f in range(faces.shape[0] if on_a_plane else 0):
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
    for f in range(faces.shape[0] if on_a_plane else 0):
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
    # a face, unlike the arcsin/sin form of their Fig. 4. Each edge's terms are
    # computed once for the two faces that share it (a face running it backwards
    # negates them, exactly).
    for e in range(ends.shape[0]):
        a, b = ends[e, 0], ends[e, 1]
        cx = cross[e, 0] = u[a, 1] * u[b, 2] - u[a, 2] * u[b, 1]
        cy = cross[e, 1] = u[a, 2] * u[b, 0] - u[a, 0] * u[b, 2]
        cz = cross[e, 2] = u[a, 0] * u[b, 1] - u[a, 1] * u[b, 0]
        sine = math.sqrt(cx * cx + cy * cy + cz * cz)
        half_angle = 0.5 * math.atan2(sine, u[a, 0] * u[b, 0] + u[a, 1] * u[b, 1]
                                      + u[a, 2] * u[b, 2]) / sine
        scaled[e, 0], scaled[e, 1], scaled[e, 2] = half_angle * cx, half_angle * cy, half_angle * cz
    for f in range(faces.shape[0]):
        mx = my = mz = 0.0
        for e in range(3):
            edge = abs(face_edges[f, e]) - 1
            if face_edges[f, e] > 0:
                mx, my, mz = mx + scaled[edge, 0], my + scaled[edge, 1], mz + scaled[edge, 2]
            else:
                mx, my, mz = mx - scaled[edge, 0], my - scaled[edge, 1], mz - scaled[edge, 2]
        for e in range(3):
            edge = abs(face_edges[f, e]) - 1
            o = faces[f, (e + 2) % 3]  # the corner off edge e
            # (u_a x u_b) . m / ((u_a x u_b) . u_o): the normal's length and sign cancel.
            cx, cy, cz = cross[edge, 0], cross[edge, 1], cross[edge, 2]
            w[o] += ((cx * mx + cy * my + cz * mz)
                     / ((cx * u[o, 0] + cy * u[o, 1] + cz * u[o, 2]) * d[o]))
    total = w.sum()
    for j in range(k):
        w[j] /= total


@njit(cache=True, parallel=True)
def mvc_polyhedron(points, vertices, faces, normals, offsets, n_chunks, out):
    """Mean value coordinates of points (n, 3) inside a convex polyhedron; out (n, K).

    Points go in n_chunks chunks, each with its own scratch arrays.
    """
    k = vertices.shape[0]
    ends, face_edges = edge_table(faces, k)
    for c in prange(n_chunks):
        d = np.empty(k)
        u = np.empty((k, 3))
        cross = np.empty((ends.shape[0], 3))
        scaled = np.empty((ends.shape[0], 3))
        for i in range(c * points.shape[0] // n_chunks, (c + 1) * points.shape[0] // n_chunks):
            _mvc_polyhedron_point(points[i], vertices, faces, normals, offsets, ends, face_edges,
                                  d, u, cross, scaled, out[i])


@njit(cache=True)
def edge_table(faces, k):
    """The edges of a triangle mesh with k vertices: ends (E, 2), lower id first, and for each
    face (F, 3) its edges in order as id + 1, negated where the face runs it backwards."""
    edge_id = np.full((k, k), -1, np.int64)
    ends = np.empty((3 * faces.shape[0], 2), np.int64)
    face_edges = np.empty((faces.shape[0], 3), np.int64)
    n_edges = 0
    for f in range(faces.shape[0]):
        for e in range(3):
            a, b = faces[f, e], faces[f, (e + 1) % 3]
            low, high = min(a, b), max(a, b)
            if edge_id[low, high] < 0:
                edge_id[low, high] = n_edges
                ends[n_edges, 0], ends[n_edges, 1] = low, high
                n_edges += 1
            face_edges[f, e] = (edge_id[low, high] + 1) * (1 if a == low else -1)
    return ends[:n_edges], face_edges


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


@njit(cache=True)
def _solve_square(m, r, x):
    """x = m^-1 r for a small (n, n) m, by Gaussian elimination with partial pivoting
    (m and r are overwritten); False when m is singular."""
    n = m.shape[0]
    for col in range(n):
        p = col
        for i in range(col + 1, n):
            if abs(m[i, col]) > abs(m[p, col]):
                p = i
        if abs(m[p, col]) < LP_PIVOT_TOL:
            return False
        for j in range(n):
            m[col, j], m[p, j] = m[p, j], m[col, j]
        r[col], r[p] = r[p], r[col]
        for i in range(col + 1, n):
            f = m[i, col] / m[col, col]
            for j in range(col, n):
                m[i, j] -= f * m[col, j]
            r[i] -= f * r[col]
    for i in range(n - 1, -1, -1):
        s = r[i]
        for j in range(i + 1, n):
            s -= m[i, j] * x[j]
        x[i] = s / m[i, i]
    return True


@njit(cache=True)
def _lp_vertex(a, b, c, x):
    """Minimise c . x subject to a x >= b, a (m, n), by enumerating bases.

    Runs through the n-row subsets S of a in lexicographic order and stops at the
    first optimal one: dual feasible (c = a_S^T y with y >= 0) and primal feasible
    (its vertex a_S^-1 b_S satisfies every row); by complementary slackness that
    vertex is a minimiser. Writes it into x (n,); False when no basis is both (the
    set is empty, or has no vertex where c is least).
    """
    m, n = a.shape
    if n == 3:
        return _lp_vertex_3d(a, b, c, x)
    if m < n:
        return False
    basis = np.arange(n)
    square = np.empty((n, n))
    rhs = np.empty(n)
    y = np.empty(n)
    while True:
        for i in range(n):
            for j in range(n):
                square[j, i] = a[basis[i], j]
            rhs[i] = c[i]
        if _solve_square(square, rhs, y) and y.min() >= -LP_OPTIMALITY_TOL:
            for i in range(n):
                square[i] = a[basis[i]]
                rhs[i] = b[basis[i]]
            if _solve_square(square, rhs, x) and _feasible(a, b, x):
                return True
        i = n - 1
        while i >= 0 and basis[i] == m - n + i:
            i -= 1
        if i < 0:
            return False
        basis[i] += 1
        for j in range(i + 1, n):
            basis[j] = basis[j - 1] + 1


@njit(cache=True)
def _feasible(a, b, x):
    """a x >= b, row by row, to within ``LP_FEASIBILITY_TOL``."""
    for row in range(a.shape[0]):
        value = -b[row]
        for j in range(a.shape[1]):
            value += a[row, j] * x[j]
        if value < -LP_FEASIBILITY_TOL:
            return False
    return True


@njit(cache=True)
def _lp_vertex_3d(a, b, c, x):
    """``_lp_vertex`` for three variables, the bases in the same order: the dual weights by
    Cramer's rule, from cross products of the basis's first two rows that every third row
    shares."""
    m = a.shape[0]
    square = np.empty((3, 3))
    rhs = np.empty(3)
    for i in range(m):
        for j in range(i + 1, m):
            ij = np.cross(a[i], a[j])
            cj = np.cross(c, a[j])
            ic = np.cross(a[i], c)
            for k in range(j + 1, m):
                det = _dot3(a[k], ij)
                if abs(det) < LP_PIVOT_TOL:
                    continue
                if (_dot3(a[k], cj) / det < -LP_OPTIMALITY_TOL
                        or _dot3(a[k], ic) / det < -LP_OPTIMALITY_TOL
                        or _dot3(c, ij) / det < -LP_OPTIMALITY_TOL):
                    continue
                square[0], square[1], square[2] = a[i], a[j], a[k]
                rhs[0], rhs[1], rhs[2] = b[i], b[j], b[k]
                if _solve_square(square, rhs, x) and _feasible(a, b, x):
                    return True
    return False


@njit(cache=True)
def collapse_points(normals, offsets, measures, rows, starts, box, slack_penalty, out):
    """The edge-collapse LPs of hull simplification, one block of facets each.

    Block i, the facets rows[starts[i]:starts[i + 1]] around an edge, asks for the
    point v in the box (d, 2) outside all its planes (n_f . v + offset_f >= 0) that
    adds the least volume sum_f measure_f (n_f . v + offset_f) / d; normals (F, d)
    unit outward, offsets and measures (F,). When no such point exists, the planes
    move out by a slack s >= 0 that costs slack_penalty per unit; with
    slack_penalty <= 0 that LP is left unsolved. out (B, d + 1): v and s (s = NaN,
    v = NaN: infeasible, unsolved).

    Each LP is tried on the facets alone (fast: few rows), then with the box's
    planes (when the least volume lies beyond it), then with the slack.
    """
    d = normals.shape[1]
    for block in range(starts.shape[0] - 1):
        facets = rows[starts[block]:starts[block + 1]]
        m = facets.shape[0]
        # Rows of a x >= b in the variables (v, s): facets, the box's low and high sides, s >= 0.
        a = np.zeros((m + 2 * d + 1, d + 1))
        b = np.zeros(m + 2 * d + 1)
        c = np.zeros(d + 1)
        for i in range(m):
            f = facets[i]
            a[i, :d] = normals[f]
            a[i, d] = 1.0
            b[i] = -offsets[f]
            c[:d] += measures[f] / d * normals[f]
        for j in range(d):
            a[m + 2 * j, j], b[m + 2 * j] = 1.0, box[j, 0]
            a[m + 2 * j + 1, j], b[m + 2 * j + 1] = -1.0, -box[j, 1]
        a[m + 2 * d, d] = 1.0
        c[d] = slack_penalty
        x = np.zeros(d + 1)
        planes = np.ascontiguousarray(a[:m + 2 * d, :d])
        inside = _lp_vertex(planes[:m], b[:m], c[:d], x[:d])
        for j in range(d):
            inside = inside and box[j, 0] <= x[j] <= box[j, 1]
        if inside or _lp_vertex(planes, b[:m + 2 * d], c[:d], x[:d]):
            x[d] = 0.0
        elif slack_penalty <= 0 or not _lp_vertex(a, b, c, x):
            x[:] = np.nan
        out[block] = x
