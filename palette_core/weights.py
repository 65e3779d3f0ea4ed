"""Weight methods: per-pixel additive weights of every image for a palette polytope.

``WEIGHT_METHODS`` maps a name to a method of one of two forms:

- per colour, ``(colours (D, 3), poly, *, options) -> (D, K)``: a colour's weights
  depend on the colour alone (``mvc``), so they are computed once per distinct colour
  and scattered to the pixels; such methods also stream into Zarr stacks
  (``collection``);
- spatial, marked ``@spatial``, ``(colour_set, poly, *, options) -> iterator of
  (H, W, K)``, one array per image in stitch order: the weights follow image
  position too (``rgbxy``), so the method needs whole images and does not stream.

Adding a method is one such function and one entry here (docs/architecture.md).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .colour_set import ColourSet
from .errors import InputError
from .mvc import rgb_to_mvc_weights
from .polytope import Polytope, polytope_from_points
from .registry import check_options, is_spatial
from .rgbxy import rgbxy_image_weights

WEIGHT_METHODS = {"mvc": rgb_to_mvc_weights, "rgbxy": rgbxy_image_weights}


def image_weights(colour_set: ColourSet, poly: Polytope, method: str = "mvc",
                  **options) -> Iterator[np.ndarray]:
    """(H, W, K) weights per image by ``method`` with its keyword ``options``.

    Raises
    ------
    InputError
        If the method is unknown, an option is not the method's, or its value is invalid.
    """
    function = check_options(WEIGHT_METHODS, method, "weight method", options)
    if is_spatial(function):
        return function(colour_set, poly, **options)
    unique = function(colour_set.colours, poly, **options)
    return (unique[colour_set.image_indices(i)].reshape(*image.opaque.shape, -1)
            for i, image in enumerate(colour_set.images))


def colour_weights(colours: np.ndarray, poly: Polytope, method: str = "mvc",
                   **options) -> np.ndarray:
    """(D, K) weights of (D, 3) distinct colours by a per-colour ``method``: what a stream
    of frames needs (``collection``).

    Raises
    ------
    InputError
        If the method is unknown, an option is not its own, or it is spatial.
    """
    function = check_weight_method(method, options, stream=True)
    return function(colours, poly, **options)


def per_colour(method: str) -> bool:
    """Whether ``method`` is a weight method whose weights follow the colour alone, so that a
    stack's weights can be computed again for other colours (``palette_weights``)."""
    return method in WEIGHT_METHODS and not is_spatial(WEIGHT_METHODS[method])


def palette_weights(colours: np.ndarray, palette: np.ndarray, hull_faces: np.ndarray,
                    method: str = "mvc", **options) -> np.ndarray:
    """(D, K) weights of (D, 3) colours against a stored (K, 3) ``palette`` and its
    (F, 3) ``hull_faces`` (a stack's; empty for a flat palette) by a per-colour ``method``,
    in the palette's order: the weights a stack would hold for pixels of those colours.

    Raises
    ------
    InputError
        If the method is unknown, an option is not its own, or it is spatial.
    """
    palette = np.asarray(palette, np.float64)
    if len(hull_faces):
        poly = Polytope(palette, 3, np.zeros(3), np.eye(3), np.asarray(hull_faces, np.int64))
    else:  # a flat palette's polytope orders its vertices around the polygon
        poly = polytope_from_points(palette)
    weights = colour_weights(colours, poly, method, **options)
    columns = [int(np.flatnonzero((palette == vertex).all(1))[0]) for vertex in poly.vertices]
    ordered = np.zeros((len(weights), len(palette)))
    ordered[:, columns] = weights
    return ordered


def stack_colour_weights(stack, colours: np.ndarray) -> np.ndarray:
    """(D, K) weights of (D, 3) colours as the ``WeightStack`` ``stack`` would hold them for
    pixels of those colours: its per-colour method with its own options
    (``palette_weights``); mean value coordinates for a stack of a spatial method."""
    method, options = ((stack.method, stack.meta.get("method_options", {}))
                       if per_colour(stack.method) else ("mvc", {}))
    return palette_weights(colours, stack.palette, stack.hull_faces, method,
                           **(options if isinstance(options, dict) else {}))


def check_weight_method(method: str, options: dict, stream: bool = False):
    """The method ``method``, after checking that it exists, that every option is one of its
    own and, for a ``stream`` of frames, that it is not spatial.

    Raises
    ------
    InputError
        Naming the method or option.
    """
    function = check_options(WEIGHT_METHODS, method, "weight method", options)
    if stream and is_spatial(function):
        raise InputError(f"weight method {method} needs whole images (its weights follow image "
                         "position), so it cannot stream into a Zarr stack: write an NPZ stack")
    return function
