"""Pictures of results: palette swatches and weight maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .folders import inside
from .palette_file import palette_to_hex


def palette_swatch(palette: np.ndarray, size: int = 96) -> Image.Image:
    """One square per palette colour, its hex code beneath; (K, 3) floats in [0, 1]."""
    labels = palette_to_hex(palette)
    sheet = Image.new("RGB", (size * len(labels), size + 20), "white")
    draw = ImageDraw.Draw(sheet)
    for i, label in enumerate(labels):
        draw.rectangle([i * size, 0, (i + 1) * size - 1, size - 1], fill=label)
        draw.text((i * size + 6, size + 4), label, fill="black")
    return sheet


def layer_paths(folder: Path, name: str, k: int) -> list[Path]:
    """Paths of the K weight-map PNGs of image ``name`` (its relative path) in ``folder``."""
    stem = Path(name).with_suffix("").as_posix()
    return [inside(folder, f"{stem}_w{j}.png") for j in range(k)]
