"""Weight methods: per-pixel additive weights of every image for a palette polytope.

``WEIGHT_METHODS`` maps a name to a function ``(colour_set, poly, *, options) ->
iterator of (H, W, K) weights``, one array per image in stitch order. Adding a
method is one such function and one entry here (docs/architecture.md).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .colour_set import ColourSet
from .mvc import mvc_image_weights
from .polytope import Polytope
from .registry import call_method, check_options
from .rgbxy import rgbxy_image_weights

WEIGHT_METHODS = {"mvc": mvc_image_weights, "rgbxy": rgbxy_image_weights}


def image_weights(colour_set: ColourSet, poly: Polytope, method: str = "mvc",
                  **options) -> Iterator[np.ndarray]:
    """(H, W, K) weights per image by ``method`` with its keyword ``options``.

    Raises
    ------
    InputError
        If the method is unknown, an option is not the method's, or its value is invalid.
    """
    return call_method(WEIGHT_METHODS, method, "weight method", colour_set, poly, **options)


def check_weight_method(method: str, options: dict) -> None:
    """InputError if ``method`` is unknown or an option is not one of its own."""
    check_options(WEIGHT_METHODS, method, "weight method", options)
