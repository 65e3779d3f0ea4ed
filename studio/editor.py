"""The palette being edited: colour changes, harmonisation, reset and undo.

No browser and no viewer here: ``app`` calls these methods from the GUI and
redraws; the tests call them directly.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from harmonize import harmonize_palette
from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_writable
from palette_core.palette_file import write_palette_json

MAX_UNDO = 100  # palettes kept for undo


class PaletteEditor:
    """A palette (K, 3) in [0, 1] with its original and an undo history.

    Parameters
    ----------
    palette : (K, 3) float
        The target's own palette: what ``reset`` returns to.
    shares : callable returning (K,) float
        Each colour's share of all weights (``harmonize.palette_shares``), computed
        on first use by harmonisation only.
    """

    def __init__(self, palette: np.ndarray, shares):
        self.original = np.array(palette, np.float64)
        self.palette = self.original.copy()
        self._shares_of = shares
        self._shares: np.ndarray | None = None
        self._history: list[np.ndarray] = []

    def _change(self, palette: np.ndarray) -> bool:
        """Make ``palette`` current, remembering the old one; False if nothing changed."""
        palette = np.clip(np.asarray(palette, np.float64), 0, 1)
        if np.array_equal(palette, self.palette):
            return False
        self._history = (self._history + [self.palette])[-MAX_UNDO:]
        self.palette = palette
        return True

    def set_colour(self, i: int, rgb) -> bool:
        """Colour ``i`` becomes ``rgb`` (3,) in [0, 1]; False if it already was."""
        if not 0 <= i < len(self.palette):
            raise InputError(f"colour {i} is not in a palette of {len(self.palette)}")
        palette = self.palette.copy()
        palette[i] = rgb
        return self._change(palette)

    def harmonize(self, template: str, strength: float = 1.0) -> str:
        """Harmonise the current palette (``harmonize.harmonize_palette``); the template
        used is returned (the least-cost one for ``"best"``)."""
        if self._shares is None:
            self._shares = np.asarray(self._shares_of(), np.float64)
        result = harmonize_palette(self.palette, self._shares, template, strength)
        self._change(result.palette)
        return result.fit.template.name

    def reset(self) -> bool:
        """Back to the original palette (undoable)."""
        return self._change(self.original)

    def undo(self) -> bool:
        """The palette before the last change; False when there is none."""
        if not self._history:
            return False
        self.palette = self._history.pop()
        return True

    @property
    def can_undo(self) -> bool:
        return bool(self._history)

    def save(self, path: str | os.PathLike, force: bool = False,
             extra: dict | None = None) -> list[Path]:
        """Write the palette as JSON (docs/formats.md), with the keys of ``extra`` beside it,
        atomically; an existing file only with ``force``. Returns the file written."""
        path = Path(path)
        if path.suffix != ".json":
            raise InputError(f"a palette file ends in .json, got {path}")
        check_writable([path], force)
        with atomic_outputs(force) as stage:
            write_palette_json(stage(path), self.palette, extra)
        return [path]
