"""Palette files: ``{"palette": ["#rrggbb", ...], "rgb": [[r, g, b], ...]}`` (docs/formats.md).

The hex codes are for people; ``rgb`` holds the same colours exactly (floats in [0, 1]),
so that a palette saved by one command or the studio recolours to the same bytes in
another. A colour whose hex code no longer matches its exact value was edited by hand:
its hex code wins. Files with hex codes alone, or with ``[r, g, b]`` floats in
``palette``, are read too.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from .errors import InputError
from .json_file import read_json

_HEX = re.compile(r"^#?([0-9a-fA-F]{6})$")


def palette_to_hex(palette: np.ndarray) -> list[str]:
    """(K, 3) floats in [0, 1] -> ["#rrggbb", ...]."""
    codes = np.round(np.clip(palette, 0, 1) * 255).astype(int)
    return ["#{:02x}{:02x}{:02x}".format(*c) for c in codes]


def palette_paths(stack: str | os.PathLike) -> tuple[Path, Path]:
    """The palette swatch and JSON beside a stack, named after it (``w.npz`` or ``w.zarr``:
    ``w.palette.png``, ``w.palette.json``)."""
    stem = str(stack).rstrip("/")
    stem = stem.rsplit(".", 1)[0] if Path(stem).suffix in (".npz", ".zarr") else stem
    return Path(stem + ".palette.png"), Path(stem + ".palette.json")


def palette_entry(palette: np.ndarray) -> dict:
    """(K, 3) floats -> ``{"palette": ["#rrggbb", ...], "rgb": [[r, g, b], ...]}`` (exact)."""
    exact = np.clip(np.asarray(palette, np.float64), 0, 1)
    return {"palette": palette_to_hex(exact), "rgb": exact.tolist()}


def write_palette_json(file, palette: np.ndarray, extra: dict | None = None) -> None:
    """Write ``palette_entry(palette)``, and the keys of ``extra`` after it (a scene region,
    for instance), to a path or text file object."""
    entry = {**palette_entry(palette), **(extra or {})}
    text = "{\n" + ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in entry.items())
    text += "\n}\n"
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
    data = read_json(path, "palette file")
    return parse_palette(data, f"palette file {path}", k)


def parse_palette(data, where: str, k: int | None = None) -> np.ndarray:
    """The (K, 3) float64 palette of ``palette_entry``'s table ``data`` (from ``where``, for
    messages); InputError as ``read_palette_json``."""
    entries = data.get("palette") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{where} must hold {{\"palette\": [colours...]}}")
    colours = [_parse_colour(entry, where, i) for i, entry in enumerate(entries)]
    palette = np.array(colours, np.float64)
    if "rgb" in data:
        exact = data["rgb"]
        if not isinstance(exact, list) or len(exact) != len(entries):
            raise InputError(f"{where}: rgb must list as many colours as palette")
        exact = np.array([_parse_colour(c if isinstance(c, list) else None, where, i)
                          for i, c in enumerate(exact)], np.float64)
        unedited = np.array(palette_to_hex(exact)) == np.array(palette_to_hex(palette))
        palette[unedited] = exact[unedited]
    if k is not None and len(palette) != k:
        raise InputError(f"{where} has {len(palette)} colours, expected {k}")
    return palette


def _parse_colour(entry, where: str, i: int) -> list[float]:
    if isinstance(entry, str):
        match = _HEX.match(entry.strip())
        if not match:
            raise InputError(f"{where}: colour {i} {entry!r} is not #rrggbb")
        return [int(match.group(1)[j : j + 2], 16) / 255 for j in (0, 2, 4)]
    if (isinstance(entry, list) and len(entry) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in entry)):
        if not all(0.0 <= v <= 1.0 for v in entry):
            raise InputError(f"{where}: colour {i} {entry} has values outside [0, 1]")
        return [float(v) for v in entry]
    raise InputError(f"{where}: colour {i} {entry!r} is neither #rrggbb "
                     "nor [r, g, b] floats in [0, 1]")
