"""All pixels of all images stitched into one set of distinct colours with their counts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .io import LoadedImage


@dataclass
class ColourSet:
    """All pixels of all images stitched together and deduplicated exactly.

    Attributes
    ----------
    colours : (U, 3) float64
        The distinct colours in [0, 1], sorted by packed integer value.
    counts : (U,) int64
        How many opaque pixels have each colour (0 for colours seen only in
        fully transparent pixels: they get weights but do not shape the palette).
    inverse : (N,) int64
        Index into ``colours`` of every stitched pixel.
    offsets : (n_images + 1,) int64
        Image ``i`` owns ``inverse[offsets[i]:offsets[i + 1]]``.
    images : list of LoadedImage
        The images, in stitch order.
    """

    colours: np.ndarray
    counts: np.ndarray
    inverse: np.ndarray
    offsets: np.ndarray
    images: list[LoadedImage]

    @classmethod
    def from_images(cls, images: list[LoadedImage]) -> ColourSet:
        sixteen = any(im.pixels.dtype == np.uint16 for im in images)
        bits = 16 if sixteen else 8
        codes = np.concatenate([pack_codes(im.pixels, bits) for im in images])
        opaque = np.concatenate([im.opaque.ravel() for im in images])
        offsets = np.cumsum([0] + [im.opaque.size for im in images])
        unique, inverse = _unique_codes(codes, bits)
        counts = np.bincount(inverse[opaque], minlength=len(unique)).astype(np.int64)
        mask = (1 << bits) - 1
        channels = np.stack([unique >> (2 * bits), (unique >> bits) & mask, unique & mask], -1)
        return cls(channels / float(mask), counts, inverse, offsets, images)

    def image_indices(self, i: int) -> np.ndarray:
        """Indices into ``colours`` of image ``i``'s pixels, in raster order."""
        return self.inverse[self.offsets[i] : self.offsets[i + 1]]


def pack_codes(pixels: np.ndarray, bits: int) -> np.ndarray:
    """(H, W, 3) integer pixels -> (H*W,) int64 codes of ``bits`` per channel; 8-bit values
    are widened to 16 when ``bits`` is 16."""
    p = pixels.reshape(-1, 3).astype(np.int64)
    if bits == 16 and pixels.dtype == np.uint8:
        p *= 257
    return (p[:, 0] << (2 * bits)) | (p[:, 1] << bits) | p[:, 2]


def _unique_codes(codes: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique codes and the inverse index; O(N) through a table for 8-bit data."""
    if bits == 8 and len(codes) > (1 << 20):
        present = np.bincount(codes, minlength=1 << 24) > 0
        unique = np.flatnonzero(present)
        table = np.empty(1 << 24, np.int64)
        table[unique] = np.arange(len(unique))
        return unique, table[codes]
    return np.unique(codes, return_inverse=True)
