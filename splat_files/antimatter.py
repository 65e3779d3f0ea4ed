"""antimatter15's ``.splat``: 32 bytes a splat and no header (position and linear scales as
float32; colour and opacity as bytes; the rotation (w, x, y, z) as bytes of q * 128 + 128),
diffuse only: the spherical harmonics of degrees 1 and up are not held."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from palette_core.errors import InputError

from .fields import SH_C0, SplatFields, as_fields

RECORD = np.dtype([("means", "<f4", 3), ("scales", "<f4", 3), ("rgba", "u1", 4),
                   ("quats", "u1", 4)])
_EPS = 1e-6  # opacities of 0 and 255 bytes, kept off logit's infinities


def read_splat(path: str | os.PathLike) -> SplatFields:
    """The splats of a ``.splat`` file (its size a whole number of records)."""
    path = Path(path)
    size = path.stat().st_size
    if size == 0 or size % RECORD.itemsize:
        raise InputError(f"{path}: a .splat file is whole records of {RECORD.itemsize} bytes; "
                         f"it has {size} bytes")
    table = np.fromfile(path, RECORD)
    scales = table["scales"].astype(np.float64)
    if not (scales > 0).all():
        raise InputError(f"{path}: splat {int(np.argmax(~(scales > 0).all(1)))}'s scales are "
                         "not positive")
    rgba = table["rgba"] / 255.0
    alpha = np.clip(rgba[:, 3], _EPS, 1 - _EPS)
    return as_fields(table["means"], (rgba[:, :3] - 0.5) / SH_C0,
                     np.zeros((len(table), 0, 3)), np.log(alpha / (1 - alpha)), np.log(scales),
                     (table["quats"].astype(np.float64) - 128) / 128)


def write_splat(fields: SplatFields, path: str | os.PathLike) -> None:
    """``fields`` as a ``.splat`` file (colours and opacities rounded to bytes, rotations to
    q * 128 + 128 of unit q, the higher spherical harmonics dropped)."""
    table = np.empty(len(fields), RECORD)
    table["means"] = fields.means
    table["scales"] = np.exp(fields.scales.astype(np.float64))
    alpha = 1 / (1 + np.exp(-fields.opacities.astype(np.float64)))
    rgba = np.concatenate([fields.colours(), alpha[:, None]], 1)
    table["rgba"] = np.clip(np.round(rgba * 255), 0, 255)
    quats = fields.quats / np.linalg.norm(fields.quats.astype(np.float64), axis=1, keepdims=True)
    table["quats"] = np.clip(np.round(quats * 128 + 128), 0, 255)
    table.tofile(path)
