"""Palette files: ``{"palette": ["#rrggbb", ...]}`` (docs/formats.md).

A list of ``[r, g, b]`` floats in [0, 1] is accepted too when reading.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from .errors import InputError

_HEX = re.compile(r"^#?([0-9a-fA-F]{6})$")


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
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
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
