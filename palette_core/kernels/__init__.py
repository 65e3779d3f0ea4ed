"""Numba kernels of the palette step, one family a module: closest points on convex
polytopes (``closest_points``), mean value coordinates (``mean_value``) and the edge-collapse
LPs of hull simplification (``collapse_lp``).

Arrays in, arrays out, no validation: every array is C-contiguous float64 (index arrays
int64) so each kernel compiles once. The wrappers in ``polytope.py``, ``mvc.py`` and
``hull.py`` validate, cast and restore shapes.
"""
