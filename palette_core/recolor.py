"""Recolouring: weights times palette terms, and palette JSON files.

Palette files are ``{"palette": ["#rrggbb", ...]}``; a list of ``[r, g, b]``
floats in [0, 1] is accepted too.
"""

from __future__ import annotations

import json
import os
import re
from itertools import combinations_with_replacement
from pathlib import Path

import numpy as np

from .errors import InputError

_HEX = re.compile(r"^#?([0-9a-fA-F]{6})$")


def transport_terms(k: int, order: int) -> list[tuple[int, ...]]:
    """Palette indices multiplied in each transport term, in basis order (DESIGN.md).

    Examples
    --------
    >>> transport_terms(2, 2)
    [(), (0,), (1,), (0, 0), (0, 1), (1, 1)]
    """
    return [
        combo
        for degree in range(order + 1)
        for combo in combinations_with_replacement(range(k), degree)
    ]


def transport_basis(palette: np.ndarray, order: int) -> np.ndarray:
    """(M, 3) terms of the light-transport polynomial in the palette colours.

    Constant term first, then degree 1 (v_1..v_K), then the products v_i * v_j
    (i <= j) in lexicographic order, and so on up to ``order`` (DESIGN.md).

    Examples
    --------
    >>> transport_basis(np.array([[0.5, 1, 1], [1, 0.5, 1]]), 2)[:, 0].tolist()
    [1.0, 0.5, 1.0, 0.25, 0.5, 1.0]
    """
    palette = np.asarray(palette, np.float64)
    terms = [
        np.prod(palette[list(combo)], axis=0) if combo else np.ones(3)
        for combo in transport_terms(len(palette), order)
    ]
    return np.array(terms)


def basis_terms(palette: np.ndarray, basis: str = "additive", order: int = 1) -> np.ndarray:
    """(M, 3) colour of each weight channel: the palette itself, or its transport terms."""
    palette = np.asarray(palette, np.float64)
    return palette if basis == "additive" else transport_basis(palette, order)


def weights_to_rgb(
    weights: np.ndarray, palette: np.ndarray, basis: str = "additive", order: int = 1
) -> np.ndarray:
    """Recompose colours from weights: ``weights @ terms(palette)``.

    Parameters
    ----------
    weights : (..., M) float
    palette : (K, 3) float
    basis : {"additive", "transport"}
    order : int
        Transport order (ignored for additive weights).

    Returns
    -------
    (..., 3) float64
        Colours, not clipped.
    """
    terms = basis_terms(palette, basis, order)
    if weights.shape[-1] != len(terms):
        raise InputError(f"weights have {weights.shape[-1]} channels, the palette gives "
                         f"{len(terms)} {basis} terms")
    return np.asarray(weights, np.float64) @ terms


def palette_to_hex(palette: np.ndarray) -> list[str]:
    """(K, 3) floats in [0, 1] -> ["#rrggbb", ...]."""
    codes = np.round(np.clip(palette, 0, 1) * 255).astype(int)
    return ["#{:02x}{:02x}{:02x}".format(*c) for c in codes]


def write_palette_json(file, palette: np.ndarray) -> None:
    """Write ``{"palette": ["#rrggbb", ...]}`` to a path or text file object."""
    text = json.dumps({"palette": palette_to_hex(palette)}, indent=2) + "\n"
    if hasattr(file, "write"):
        file.write(text)
    else:
        Path(file).write_text(text)


def read_palette_json(path: str | os.PathLike, k: int | None = None) -> np.ndarray:
    """Read a palette file into (K, 3) float64 in [0, 1].

    Raises
    ------
    InputError
        If the file is missing or malformed, a colour is invalid or outside
        [0, 1], or ``k`` is given and the palette has another length.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"palette file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"palette file {path} is not valid JSON: {exc}") from None
    entries = data.get("palette") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(f"palette file {path} must hold {{\"palette\": [colours...]}}")
    colours = [_parse_colour(entry, path, i) for i, entry in enumerate(entries)]
    palette = np.array(colours, np.float64)
    if k is not None and len(palette) != k:
        raise InputError(f"palette file {path} has {len(palette)} colours, expected {k}")
    return palette


def _parse_colour(entry, path: Path, i: int) -> list[float]:
    if isinstance(entry, str):
        match = _HEX.match(entry.strip())
        if not match:
            raise InputError(f"palette file {path}: colour {i} {entry!r} is not #rrggbb")
        return [int(match.group(1)[j : j + 2], 16) / 255 for j in (0, 2, 4)]
    if (isinstance(entry, list) and len(entry) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in entry)):
        if not all(0.0 <= v <= 1.0 for v in entry):
            raise InputError(f"palette file {path}: colour {i} {entry} has values outside [0, 1]")
        return [float(v) for v in entry]
    raise InputError(f"palette file {path}: colour {i} {entry!r} is neither #rrggbb "
                     "nor [r, g, b] floats in [0, 1]")
