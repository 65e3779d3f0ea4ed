"""Photo mode: the images of a weight stack (NPZ or Zarr), read on demand.

Only the image on screen and its neighbours' thumbnails are read: a stack of a
hundred photos opens as fast as one. Recolouring is ``weights @ basis(palette)``
(``palette_core.basis``) on weights kept at display size, in float32.
"""

from __future__ import annotations

import os
import tempfile
from collections import OrderedDict
from pathlib import Path

import numpy as np

from harmonize import palette_shares
from palette_core.basis import basis_terms
from palette_core.recolor import recolor_stack
from palette_core.stack import WeightStack, read_stack

from .drawing import Drawing

DISPLAY_PIXELS = 1 << 20  # weights kept per view: about one megapixel
THUMBNAIL_PIXELS = 96 * 72  # weights kept per thumbnail
CACHED_VIEWS = 8


def downsample(weights: np.ndarray, max_pixels: int) -> np.ndarray:
    """(H, W, M) -> every s-th pixel, s the least step that leaves at most ``max_pixels``.

    Strided rather than averaged: weights stay exact values of the stack (and sum to one).
    """
    step = int(np.ceil(np.sqrt(weights.shape[0] * weights.shape[1] / max_pixels)))
    return weights[::max(step, 1), ::max(step, 1)]


class PhotoTarget:
    """A weight stack to recolour in the studio.

    Parameters
    ----------
    stack : WeightStack
    path : Path
        Where it was read from (the default export folder sits beside it).
    """

    mode = "photos"

    def __init__(self, stack: WeightStack, path: Path):
        self.stack = stack
        self.path = path
        self._views: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._sizes: dict[int, tuple[int, int]] = {}

    @classmethod
    def open(cls, path: str | os.PathLike) -> PhotoTarget:
        return cls(read_stack(path), Path(path))

    @property
    def names(self) -> list[str]:
        return self.stack.names

    @property
    def palette(self) -> np.ndarray:
        return self.stack.palette

    def shares(self) -> np.ndarray:
        """(K,) each colour's share of all weights (reads the whole stack once)."""
        return palette_shares(self.stack)

    def weights(self, i: int, max_pixels: int = DISPLAY_PIXELS) -> np.ndarray:
        """(h, w, M) float32 weights of image ``i`` at most ``max_pixels`` (cached)."""
        key = (i, max_pixels)
        if key not in self._views:
            full = self.stack.weights[i]
            self._views[key] = np.ascontiguousarray(downsample(full, max_pixels), np.float32)
            if len(self._views) > CACHED_VIEWS:
                self._views.popitem(last=False)
        self._views.move_to_end(key)
        return self._views[key]

    def terms(self, palette: np.ndarray) -> np.ndarray:
        """(M, 3) float32 colours in 0..255 of the weight channels for ``palette``."""
        return 255 * basis_terms(palette, self.stack.basis, self.stack.order).astype(np.float32)

    def view(self, i: int, palette: np.ndarray, max_pixels: int = DISPLAY_PIXELS,
             drawing: Drawing | None = None) -> np.ndarray:
        """(h, w, 3) uint8 image ``i`` recoloured with ``palette``: ``weights @ basis`` in
        float32, for the screen (exports use ``recolor_stack``); with a ``drawing`` that
        selects something, ``palette`` applies inside its selection and the stack's own
        palette outside (``selection.recolor_local``)."""
        weights = self.weights(i, max_pixels)
        if not drawing:
            rgb = weights @ self.terms(palette)
        else:
            own = self.terms(self.palette)
            rgb = weights @ own
            m = self.selected(i, drawing, rgb / 255, max_pixels)
            if m is not None:
                change = weights @ (self.terms(palette) - own)
                change *= m[..., None]
                rgb += change
        return np.clip(rgb + 0.5, 0, 255, out=rgb).astype(np.uint8)

    def selected(self, i: int, drawing: Drawing, original: np.ndarray,
                 max_pixels: int) -> np.ndarray | None:
        """(h, w) selection of image ``i`` at display size, given its unedited colours
        ``original`` (h, w, 3) in [0, 1]; None where nothing of it is selected."""
        if drawing.near is not None:
            colour, distance = drawing.near
            offset = original - colour.astype(np.float32)
            return (np.einsum("...c,...c->...", offset, offset) <= distance ** 2).astype(
                np.float32)
        mask = drawing.masks.get(i)
        return None if mask is None else downsample(mask[..., None], max_pixels)[..., 0]

    def size(self, i: int) -> tuple[int, int]:
        """(H, W) of image ``i`` at full size."""
        if i not in self._sizes:
            self._sizes[i] = tuple(self.stack.weights[i].shape[:2])
        return self._sizes[i]

    def default_export(self) -> Path:
        return self.path.with_name(f"{self.path.stem}_studio")

    def export(self, folder: str | os.PathLike, palette: np.ndarray, force: bool = False,
               drawing: Drawing | None = None) -> list[Path]:
        """Every image (and video) recoloured into ``folder`` (``recolor_stack``), inside the
        ``drawing``'s selection only when it selects something."""
        if not drawing:
            return recolor_stack(self.stack, palette, folder, force)
        with tempfile.TemporaryDirectory() as masks:
            edits = drawing.local_edits(self.stack, palette, Path(masks))
            return recolor_stack(self.stack, self.palette, folder, force, edits=edits)
