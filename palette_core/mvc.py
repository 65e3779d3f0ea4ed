"""Mean value coordinates of colours with respect to the palette polytope.

References
----------
Ju, Schaefer, Warren. Mean value coordinates for closed triangular meshes. SIGGRAPH 2005.
Wang, Liu, Xu. An improved geometric approach for palette-based image decomposition
and recoloring. Computer Graphics Forum 2019 (MVC weights for palettes).
"""

from __future__ import annotations

import numba
import numpy as np

from .errors import InputError
from .kernels import mean_value
from .polytope import Polytope, project_to_polytope


def rgb_to_mvc_weights(rgb: np.ndarray, poly: Polytope) -> np.ndarray:
    """Additive weights of colours: mean value coordinates in the palette polytope.

    Colours outside the polytope are first moved to its closest point; colours on
    a vertex, an edge or a face take exact one-, two- or three-colour weights.
    Polytopes of lower dimension use 2-D mean value coordinates (Hormann and
    Floater 2006), linear weights on a segment, or weight one for a single colour.

    Parameters
    ----------
    rgb : (..., 3) float
        Colours in [0, 1]; any leading shape.
    poly : Polytope
        The palette polytope (``hull.extract_palette``).

    Returns
    -------
    (..., K) float64
        Non-negative weights summing to one with ``weights @ poly.vertices``
        equal to the projected colour.

    Raises
    ------
    InputError
        If ``rgb`` does not end in 3 channels or holds NaN or infinity.

    Examples
    --------
    >>> from palette_core.polytope import polytope_from_points
    >>> poly = polytope_from_points(np.eye(3, k=0).tolist() + [[0, 0, 0]])
    >>> rgb_to_mvc_weights([0.2, 0.3, 0.1], poly).round(6).tolist()
    [0.2, 0.3, 0.1, 0.4]
    """
    rgb = np.asarray(rgb, np.float64)
    if rgb.shape[-1:] != (3,):
        raise InputError(f"rgb must have shape (..., 3), got {rgb.shape}")
    if not np.isfinite(rgb).all():
        raise InputError("rgb holds NaN or infinite values")
    flat = rgb.reshape(-1, 3)
    local = project_to_polytope(flat, poly)
    corners = np.ascontiguousarray(poly.to_local(poly.vertices))
    weights = np.empty((len(flat), len(poly.vertices)))
    if poly.dim == 3:
        normals, offsets = poly.planes
        n_chunks = min(len(local), 64 * numba.get_num_threads())
        mean_value.mvc_polyhedron(local, corners, poly.faces, normals, offsets, n_chunks,
                                        weights)
    elif poly.dim == 2:
        mean_value.mvc_polygon(local, corners, weights)
    elif poly.dim == 1:
        t = (local[:, 0] - corners[0, 0]) / (corners[1, 0] - corners[0, 0])
        weights[:, 0], weights[:, 1] = 1.0 - t, t
    else:
        weights[:] = 1.0
    return weights.reshape(rgb.shape[:-1] + (len(poly.vertices),))
