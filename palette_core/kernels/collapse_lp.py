"""The edge-collapse LPs of hull simplification (``hull.py``), solved exactly by enumerating
the bases of their few variables.
"""

import numpy as np
from numba import njit

from ..constants import LP_FEASIBILITY_TOL, LP_OPTIMALITY_TOL, LP_PIVOT_TOL
from .vectors import dot3


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
                det = dot3(a[k], ij)
                if abs(det) < LP_PIVOT_TOL:
                    continue
                if (dot3(a[k], cj) / det < -LP_OPTIMALITY_TOL
                        or dot3(a[k], ic) / det < -LP_OPTIMALITY_TOL
                        or dot3(c, ij) / det < -LP_OPTIMALITY_TOL):
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
