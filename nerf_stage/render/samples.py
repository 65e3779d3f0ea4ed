"""Where the light of each pixel of a render comes from: the samples behind it, kept with a
render so that regions of the scene can split its weights later without the network
(``edit.regions``; docs/selections.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Samples below this compositing weight are not kept (``PixelSamples``), but for each ray's
#: strongest: together they hold a negligible share of any pixel that is not all fog.
KEEP_WEIGHT = 1e-3


@dataclass
class PixelSamples:
    """Where the light of each pixel of some views comes from: its rays' samples, ordered by
    pixel (stably: in marching order within a pixel; the rays of a supersampled pixel
    interleave, so their first half of light is the pixel's, roughly).

    Attributes
    ----------
    pixel : (P,) int64
        Each sample's pixel, an index into the views' flattened (N, H, W) pixels.
    point : (P, 3) float32
        World positions (the sky of an unbounded scene lies a thousand box sizes away).
    weight : (P,) float32
        Compositing weights T_i alpha_i, averaged over the pixel's rays; samples below
        ``KEEP_WEIGHT`` are dropped, but for each ray's strongest.
    """

    pixel: np.ndarray
    point: np.ndarray
    weight: np.ndarray
    front: np.ndarray = field(init=False, repr=False)
    """(P,) which samples lie in front of their pixel's median termination (the one that
    crosses it included): those that bring the first half of its light."""

    def __post_init__(self):
        order = np.argsort(self.pixel, kind="stable")
        self.pixel, self.point = self.pixel[order], self.point[order]
        self.weight = self.weight[order]
        if not len(self.pixel):
            self.front = np.zeros(0, bool)
            return
        first = np.r_[0, np.flatnonzero(np.diff(self.pixel)) + 1]  # each pixel's first sample
        before = np.cumsum(self.weight, dtype=np.float64) - self.weight
        before -= np.repeat(before[first], np.diff(np.r_[first, len(self.pixel)]))
        total = np.bincount(self.pixel, self.weight)
        self.front = before < 0.5 * total[self.pixel]

    def median_points(self, n: int) -> np.ndarray:
        """(n, 3) float32 where each of ``n`` pixels' light reaches half its total: the
        position of the sample that crosses it (the surface the pixel shows); NaN where a
        pixel has no samples."""
        points = np.full((n, 3), np.nan, np.float32)
        pixel, point = self.pixel[self.front], self.point[self.front]
        last = np.r_[pixel[1:] != pixel[:-1], True] if len(pixel) else np.zeros(0, bool)
        points[pixel[last]] = point[last]
        return points

    def shares(self, regions: list, shape: tuple[int, ...]) -> np.ndarray:
        """(shape) float32 in [0, 1]: for views of ``shape`` (N, H, W), each pixel's share of
        the first half of its light from samples inside any of ``regions`` (anything with
        ``contains(points)``: ``edit.regions``, whose docstring says why the first half);
        0 where a pixel has no samples."""
        n = math.prod(shape)
        pixel, point, weight = (x[self.front] for x in (self.pixel, self.point, self.weight))
        inside = np.zeros(len(pixel), bool)
        for region in regions:
            inside |= region.contains(point)
        total = np.bincount(pixel, weight, minlength=n)
        within = np.bincount(pixel[inside], weight[inside], minlength=n)
        share = np.divide(within, total, out=np.zeros(n), where=total > 0)
        return np.clip(share, 0, 1).astype(np.float32).reshape(shape)
