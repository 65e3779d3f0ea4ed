"""Selections drawn on photos in the studio: boxes and brush dabs painted into a soft mask
of each image, at the stack's size, or the colour under the eyedropper
(``palette_core.selection``, docs/selections.md).

Painting keeps the largest value where strokes overlap; an edge is feathered by a linear
ramp ``feather`` pixels wide on either side of it, computed only in the stroke's box.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from palette_core.edit_file import write_edits
from palette_core.errors import InputError
from palette_core.folders import inside
from palette_core.selection import LocalEdit, Selection
from palette_core.stack import video_of


class Drawing:
    """Drawn masks of the images of a stack, (H, W) float32 in [0, 1] each, made on the
    first stroke; and an eyedropper colour, which selects in every image instead.

    Parameters
    ----------
    size : callable
        Image index -> its (H, W).
    count : int
        How many images there are.
    """

    def __init__(self, size, count: int):
        self.size, self.count = size, count  # image index -> (H, W); how many images
        self.masks: dict[int, np.ndarray] = {}
        self.near: tuple[np.ndarray, float] | None = None  # (RGB, distance)

    def __bool__(self) -> bool:
        return bool(self.masks) or self.near is not None

    def clear(self) -> None:
        self.masks.clear()
        self.near = None

    def box(self, i: int, corners: np.ndarray, feather: float) -> None:
        """Paint the box between (2, 2) ``corners`` ((x, y) pixels of image ``i``).

        Raises
        ------
        InputError
            For what no page of ours sends (``_check``).
        """
        corners = self._check(i, corners, (2, 2), feather=feather)
        low, high = corners.min(0), corners.max(0)
        centre, half = (low + high) / 2, (high - low) / 2

        def distance(x, y):  # signed distance to the box's edge, negative inside
            dx, dy = np.abs(x - centre[0]) - half[0], np.abs(y - centre[1]) - half[1]
            outside = np.hypot(np.maximum(dx, 0), np.maximum(dy, 0))
            return outside + np.minimum(np.maximum(dx, dy), 0)

        self._paint(i, low, high, distance, feather)

    def dab(self, i: int, centre: np.ndarray, radius: float, feather: float) -> None:
        """Paint a brush dab of ``radius`` pixels at (x, y) ``centre`` of image ``i``.

        Raises
        ------
        InputError
            For what no page of ours sends (``_check``).
        """
        centre = self._check(i, centre, (2,), radius=radius, feather=feather)

        def distance(x, y):
            return np.hypot(x - centre[0], y - centre[1]) - radius

        self._paint(i, centre - radius, centre + radius, distance, feather)

    def _check(self, i, points, shape: tuple[int, ...], **sizes) -> np.ndarray:
        """(shape) float64 ``points``, InputError unless ``i`` is an image index, the points
        are finite and each of ``sizes`` (pixels) is finite, at least 0 and at most the
        image's diagonal: a message from a browser is checked like a command-line argument."""
        if not isinstance(i, int) or isinstance(i, bool) or i not in range(self.count):
            raise InputError(f"no image {i!r} to draw on")
        try:
            points = np.asarray(points, np.float64).reshape(shape)
        except (TypeError, ValueError):
            raise InputError(f"a stroke's points must be {shape} numbers") from None
        h, w = self.size(i)
        diagonal = float(np.hypot(h, w))
        if not np.isfinite(points).all():
            raise InputError("a stroke's points must be finite")
        for name, value in sizes.items():
            if not (isinstance(value, (int, float)) and 0 <= value <= diagonal):
                raise InputError(f"{name} must be a number in [0, {diagonal:.0f}] pixels "
                                 f"(the image's diagonal), got {value!r}")
        return points

    def _paint(self, i: int, low, high, distance, feather: float) -> None:
        h, w = self.size(i)
        reach = feather + 1
        x0, y0 = (max(int(np.floor(v - reach)), 0) for v in low)
        x1, y1 = min(int(np.ceil(high[0] + reach)), w), min(int(np.ceil(high[1] + reach)), h)
        if x0 >= x1 or y0 >= y1:
            return
        y, x = np.mgrid[y0:y1, x0:x1] + 0.5  # pixel centres
        d = distance(x, y)
        value = (d <= 0).astype(np.float32) if feather <= 0 else np.clip(
            0.5 - d / (2 * feather), 0, 1).astype(np.float32)
        mask = self.masks.setdefault(i, np.zeros((h, w), np.float32))
        np.maximum(mask[y0:y1, x0:x1], value, out=mask[y0:y1, x0:x1])

    def local_edits(self, stack, palette: np.ndarray, folder: Path) -> list[LocalEdit]:
        """The selection as ``recolor_stack``'s edits, ``palette`` inside it (none when
        nothing is selected): the eyedropper's colour, or the drawn masks written into
        ``folder`` as one PNG an image (8 bits; empty where nothing was drawn)."""
        if self.near is not None:
            colour, distance = self.near
            return [LocalEdit(Selection(near=tuple(colour.tolist()), distance=distance),
                              palette)]
        if not self.masks:
            return []
        for i, name in enumerate(stack.names):
            mask = self.masks.get(i, np.zeros(self.size(i), np.float32))
            stem = name if video_of(name) else str(Path(name).with_suffix(""))
            file = inside(folder, stem + ".png")
            file.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.round(mask * 255).astype(np.uint8)).save(file)
        return [LocalEdit(Selection(mask=Path(folder)), palette)]

    def save(self, path: str | os.PathLike, stack, palette: np.ndarray,
             force: bool = False) -> list[Path]:
        """Write the selection with ``palette`` inside it as an edit file (``edit_file``)."""
        with tempfile.TemporaryDirectory() as folder:
            edits = self.local_edits(stack, palette, Path(folder))
            if not edits:
                raise InputError("nothing is selected: draw a box or a brush stroke, or pick "
                                 "a colour with the eyedropper")
            return write_edits(path, stack, edits, force)
