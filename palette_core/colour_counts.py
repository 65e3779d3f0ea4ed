"""Pass one of a collection: exact colour counts of frames added one at a time, their
merge, and the index of each pixel's colour among the counted ones (pass two).

Colours are packed at 16 bits per channel (``colour_set.pack_codes``); a count table
is sparse: sorted codes and counts.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from .colour_set import pack_codes
from .errors import InputError

_MASK = (1 << 16) - 1


def decode_codes(codes: np.ndarray) -> np.ndarray:
    """(D,) codes -> (D, 3) float64 colours in [0, 1]."""
    return np.stack([codes >> 32, (codes >> 16) & _MASK, codes & _MASK], axis=-1) / float(_MASK)


class ColourCounter:
    """Exact colour counts of frames added one at a time.

    8-bit frames go into a dense table of all 2^24 colours (128 MiB), which costs a
    ``bincount`` per frame; 16-bit frames into sparse sorted tables. ``result`` gives
    one sparse table: sorted codes (16 bits per channel) and opaque pixel counts, with
    count 0 for colours seen only in transparent pixels.
    """

    def __init__(self):
        self.dense = self.seen = None
        self.sparse = (np.zeros(0, np.int64), np.zeros(0, np.int64))

    def add(self, pixels: np.ndarray, opaque: np.ndarray) -> None:
        opaque = opaque.ravel()
        if pixels.dtype == np.uint8:
            codes = pack_codes(pixels, 8)
            if self.dense is None:
                self.dense = np.zeros(1 << 24, np.int64)
                self.seen = np.zeros(1 << 24, bool)
            self.dense += np.bincount(codes[opaque], minlength=1 << 24)
            self.seen[codes[~opaque]] = True
            return
        codes = pack_codes(pixels, 16)
        seen, counts = np.unique(codes[opaque], return_counts=True)
        hidden = np.unique(codes[~opaque])
        self.sparse = merge_counts(self.sparse, merge_counts(
            (seen, counts), (hidden, np.zeros(len(hidden), np.int64))))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        if self.dense is None:
            return self.sparse
        present = np.flatnonzero((self.dense > 0) | self.seen)
        widened = ((present >> 16) * 257 << 32) | (((present >> 8) & 255) * 257 << 16) \
            | ((present & 255) * 257)
        return merge_counts(self.sparse, (widened.astype(np.int64), self.dense[present]))


def merge_counts(a: tuple[np.ndarray, np.ndarray],
                 b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Sum of two sparse count tables (sorted codes, counts)."""
    if len(a[0]) == 0:
        return b
    if len(b[0]) == 0:
        return a
    codes, inverse = np.unique(np.concatenate([a[0], b[0]]), return_inverse=True)
    return codes, np.bincount(inverse, np.concatenate([a[1], b[1]]), len(codes)).astype(np.int64)


class ColourIndex:
    """Index of each pixel's colour among the sorted distinct codes of pass 1: a lookup table
    of all 2^24 8-bit colours (64 MiB, one gather per frame), binary search for 16-bit."""

    def __init__(self, codes: np.ndarray):
        self.codes = codes
        channels = np.stack([codes >> 32, (codes >> 16) & _MASK, codes & _MASK], -1)
        eight = np.all(channels % 257 == 0, axis=1)
        small = channels[eight] // 257
        self.table = np.full(1 << 24, -1, np.int32)
        self.table[(small[:, 0] << 16) | (small[:, 1] << 8) | small[:, 2]] = \
            np.flatnonzero(eight).astype(np.int32)

    _built: ClassVar[dict[int, ColourIndex]] = {}

    @classmethod
    def of(cls, codes: np.ndarray) -> ColourIndex:
        """The index of ``codes``, built once per process for the same array (a dask worker
        gets the scattered codes once and runs many tasks on them)."""
        index = cls._built.get(id(codes))
        if index is None or index.codes is not codes:
            cls._built.clear()  # one collection at a time: the 64 MiB table of the last
            index = cls._built[id(codes)] = cls(codes)
        return index

    def __call__(self, pixels: np.ndarray, source) -> np.ndarray:
        """(H W,) indices of a frame's colours; ``source`` (a ``sources.Source``) names the
        file in errors."""
        if pixels.dtype == np.uint8:
            index = self.table[pack_codes(pixels, 8)]
            if (index < 0).any():
                raise InputError(f"{source.path} changed between the two passes")
            return index
        frame_codes = pack_codes(pixels, 16)
        index = np.minimum(np.searchsorted(self.codes, frame_codes), len(self.codes) - 1)
        if not np.array_equal(self.codes[index], frame_codes):
            raise InputError(f"{source.path} changed between the two passes")
        return index
