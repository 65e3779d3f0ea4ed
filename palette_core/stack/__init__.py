"""Weight stacks: the palette and per-image weights that every command exchanges.

``read_stack`` and ``write_stack`` choose the container by the path: an NPZ file
(``npz.py``), or a Zarr store for collections beyond memory (``zarr.py``); ``base.py``
holds the ``WeightStack`` record and the checks every reader applies.
"""

from __future__ import annotations

import os

from .base import (
    DEFAULT_STACK,
    FLOAT16_SUM_TOL,
    FORMAT,
    MAX_FPS,
    WeightStack,
    check_dtype,
    check_meta,
    check_names,
    default_stack,
    frame_name,
    is_zarr,
    stored_weights,
    video_of,
)
from .npz import NpzReader, read_npz_stack, write_npz_stack


def read_stack(path: str | os.PathLike) -> WeightStack:
    """Read and validate a weight stack: an NPZ file (``npz.read_npz_stack``) or a Zarr store
    (``zarr.read_zarr_stack``, whose weights are read lazily).

    Raises
    ------
    InputError
        If it is missing or malformed; the message names what is wrong.
    """
    if is_zarr(path):
        from .zarr import read_zarr_stack

        return read_zarr_stack(str(path))
    return read_npz_stack(path)


def write_stack(stack: WeightStack, file, dtype: str | None = None, force: bool = False) -> None:
    """Write ``stack`` to ``file``: a Zarr store for a ``.zarr`` path (``zarr.write_zarr_stack``,
    replacing one only with ``force``), else NPZ to a path or binary file object
    (``npz.write_npz_stack``, weights converted to ``dtype``)."""
    if isinstance(file, (str, os.PathLike)) and is_zarr(file):
        from .zarr import write_zarr_stack

        write_zarr_stack(stack, file, force)
        return
    write_npz_stack(stack, file, dtype)


__all__ = [
    "DEFAULT_STACK",
    "default_stack",
    "FLOAT16_SUM_TOL",
    "FORMAT",
    "MAX_FPS",
    "NpzReader",
    "WeightStack",
    "check_dtype",
    "check_meta",
    "check_names",
    "frame_name",
    "is_zarr",
    "read_npz_stack",
    "read_stack",
    "stored_weights",
    "video_of",
    "write_npz_stack",
    "write_stack",
]
