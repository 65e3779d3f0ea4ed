"""Palette methods: the palette polytope of a colour set.

``PALETTE_METHODS`` maps a name to a function ``(colours, counts, k, max_error, *,
options) -> Polytope`` (see ``hull.extract_palette`` for the meaning of ``k`` and
``max_error``; every method validates them with ``check_palette_size``). Adding a
method is one such function and one entry here (docs/architecture.md).
"""

from __future__ import annotations

import numpy as np

from .hull import check_palette_size, extract_palette
from .polytope import Polytope
from .refine import refined_palette
from .registry import call_method

PALETTE_METHODS = {"hull": extract_palette, "refined": refined_palette}

__all__ = ["PALETTE_METHODS", "check_palette_size", "palette_polytope"]


def palette_polytope(colours: np.ndarray, counts: np.ndarray, k: int | None = 6,
                     max_error: float | None = None, method: str = "refined",
                     **options) -> Polytope:
    """The palette polytope of (n, 3) distinct ``colours`` with (n,) pixel ``counts``.

    Raises
    ------
    InputError
        If the method is unknown, an option is not the method's, or ``k`` /
        ``max_error`` is invalid.
    """
    return call_method(PALETTE_METHODS, method, "palette method", colours, counts, k,
                       max_error, **options)
