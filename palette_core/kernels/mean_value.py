"""Mean value coordinates of points inside convex polyhedra (3D) and polygons (2D).

Ju, Schaefer, Warren. Mean value coordinates for closed triangular meshes. SIGGRAPH 2005.
Hormann, Floater. Mean value coordinates for arbitrary planar polygons. ACM TOG 2006.
"""

import math

import numpy as np
from numba import njit, prange

from ..constants import EDGE_TOL, FACE_TOL, VERTEX_TOL
from .vectors import cross_dot, dot3


@njit(cache=True)
def _mvc_polyhedron_point(x, vertices, faces, normals, offsets, ends, face_edges, d, u, cross,
                          scaled, w):
    """Mean value coordinates of one point x inside a convex polyhedron, into w (K,).

    ends (E, 2) are the polyhedron's edges, face_edges (F, 3) each face's edges (id + 1,
    negative where the face runs the edge backwards: ``edge_table``); d (K,), u (K, 3),
    cross and scaled (E, 3) are scratch space. A point on a vertex, an edge or a face gets
    the weights of that vertex, edge or face alone; a point strictly inside, Ju, Schaefer
    and Warren's.
    """
    w[:] = 0.0
    if _on_vertex(x, vertices, d, u, w):
        return
    # A point on an edge or a face lies on a face plane: far from all of them (most
    # points), skip both tests.
    for f in range(faces.shape[0]):
        if abs(dot3(normals[f], x) + offsets[f]) < 2.0 * max(EDGE_TOL, FACE_TOL):
            if _on_edge(x, vertices, faces, w) or _on_face(x, vertices, faces, normals,
                                                            offsets, w):
                return
            break
    _inside(faces, ends, face_edges, d, u, cross, scaled, w)


@njit(cache=True, inline="always")
def _on_vertex(x, vertices, d, u, w):
    """Whether x is on a vertex (then w is that vertex alone); else the distances d (K,) and
    unit directions u (K, 3) from x to the vertices."""
    for j in range(vertices.shape[0]):
        dx, dy, dz = vertices[j, 0] - x[0], vertices[j, 1] - x[1], vertices[j, 2] - x[2]
        d[j] = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d[j] < VERTEX_TOL:
            w[j] = 1.0
            return True
        u[j, 0], u[j, 1], u[j, 2] = dx / d[j], dy / d[j], dz / d[j]
    return False


@njit(cache=True, inline="always")
def _on_edge(x, vertices, faces, w):
    """Whether x is within EDGE_TOL of an edge; then w is linear between its two ends."""
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
                    return True
    return False


@njit(cache=True, inline="always")
def _on_face(x, vertices, faces, normals, offsets, w):
    """Whether x is within FACE_TOL of a face; then w is barycentric on the face whose
    triangle holds it most surely (largest smallest coordinate)."""
    best_face, best_min = -1, -1e-6
    b0 = b1 = 0.0
    for f in range(faces.shape[0]):
        if abs(dot3(normals[f], x) + offsets[f]) >= FACE_TOL:
            continue
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        # Sub-triangle volumes against the unit normal give 2-D barycentrics.
        nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
        full = cross_dot(vertices[i1, 0] - vertices[i0, 0], vertices[i1, 1] - vertices[i0, 1],
                         vertices[i1, 2] - vertices[i0, 2], vertices[i2, 0] - vertices[i0, 0],
                         vertices[i2, 1] - vertices[i0, 1], vertices[i2, 2] - vertices[i0, 2],
                         nx, ny, nz)
        c0 = cross_dot(vertices[i1, 0] - x[0], vertices[i1, 1] - x[1], vertices[i1, 2] - x[2],
                       vertices[i2, 0] - x[0], vertices[i2, 1] - x[1], vertices[i2, 2] - x[2],
                       nx, ny, nz) / full
        c1 = cross_dot(vertices[i2, 0] - x[0], vertices[i2, 1] - x[1], vertices[i2, 2] - x[2],
                       vertices[i0, 0] - x[0], vertices[i0, 1] - x[1], vertices[i0, 2] - x[2],
                       nx, ny, nz) / full
        lowest = min(c0, c1, 1.0 - c0 - c1)
        if lowest > best_min:
            best_face, best_min, b0, b1 = f, lowest, c0, c1
    if best_face < 0:
        return False
    b0, b1 = max(b0, 0.0), max(b1, 0.0)
    b2 = max(1.0 - b0 - b1, 0.0)
    total = b0 + b1 + b2
    w[faces[best_face, 0]] = b0 / total
    w[faces[best_face, 1]] = b1 / total
    w[faces[best_face, 2]] = b2 / total
    return True


@njit(cache=True, inline="always")
def _inside(faces, ends, face_edges, d, u, cross, scaled, w):
    """Ju, Schaefer and Warren's weights (2005, Sec. 3.2) of a point strictly inside, from
    its distances d and unit directions u to the vertices, normalised into w.

    Each face's mean vector m = sum over its edges of theta_e / 2 * n_e (n_e the unit normal
    of the plane through x and the edge, theta_e the edge's angle seen from x) is split
    along the unit vectors to its corners, lambda_i = (n_jk . m) / (n_jk . u_i), and corner
    i gains lambda_i / d_i. The angles come from atan2 and the splits from determinants,
    which stay accurate close to a face, unlike the arcsin/sin form of their Fig. 4. Each
    edge's terms are computed once for the two faces that share it (a face running it
    backwards negates them, exactly).
    """
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
    for j in range(w.shape[0]):
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
