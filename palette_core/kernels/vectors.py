"""Inline 3-vector helpers shared by the kernels."""

from numba import njit


@njit(cache=True, inline="always")
def dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def cross_dot(ax, ay, az, bx, by, bz, cx, cy, cz):
    """(a x b) . c"""
    return (ay * bz - az * by) * cx + (az * bx - ax * bz) * cy + (ax * by - ay * bx) * cz
