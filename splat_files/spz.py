"""Niantic's SPZ (versions 2 and 3 in one gzip stream, version 4 in NGSP's zstd streams),
decoded and encoded by PyPI's ``gsply`` after its container is checked here.

SPZ holds its splats in the RUB frame (x right, y up, z back: OpenGL's), the PLY in RDF
(Niantic's spz README, "Coordinate System"); ``gsply`` converts neither way, so the
conversion is here (``flip_axes``): y and z negated, the quaternions' y and z, and the
spherical harmonics odd in y + z (``SH_FLIPS``). What a header declares is checked against
what the file can hold before anything is decompressed: gzip's deflate expands at most
``MAX_RATIO`` times, and the stream is inflated in bounded steps.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from palette_core.errors import InputError

from .fields import (
    MAX_RATIO,
    REST_COEFFICIENTS,
    SplatFields,
    from_gsdata,
    gsply_module,
    unit_quaternions,
)

MAGIC = 0x5053474E  # "NGSP"
#: Sign of each coefficient of degrees 1 to 3 (3D Gaussian splatting's order) under
#: (x, y, z) -> (x, -y, -z): -1 where the basis function is odd in y + z.
SH_FLIPS = np.array([-1, -1, 1,  -1, 1, 1, -1, 1,  -1, 1, -1, -1, 1, -1, 1], np.float32)
_STEP = 1 << 20
#: Positions: signed 24-bit fixed point, at most this many fractional bits.
POSITION_BITS, MAX_FRACTIONAL_BITS = 24, 12


def flip_axes(fields: SplatFields) -> SplatFields:
    """``fields`` carried between SPZ's RUB frame and the PLY's RDF (its own inverse)."""
    flip = np.array([1, -1, -1], np.float32)
    b = fields.shN.shape[1]
    return SplatFields(fields.means * flip, fields.sh0, fields.shN * SH_FLIPS[:b, None],
                       fields.opacities, fields.scales,
                       fields.quats * np.array([1, 1, -1, -1], np.float32),
                       fields.comments, fields.extras)


def read_spz(path: str | os.PathLike) -> SplatFields:
    """The splats of an SPZ file, in the PLY's frame."""
    path = Path(path)
    with open(path, "rb") as file:
        start = file.read(32)
    if start[:2] == b"\x1f\x8b":
        _check_gzip(path)
    elif len(start) >= 4 and struct.unpack_from("<I", start)[0] == MAGIC:
        _check_ngsp(path, start)
    else:
        raise InputError(f"{path} is not an SPZ file (neither gzip nor NGSP)")
    try:
        data = gsply_module("SPZ").read_spz(path)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    return flip_axes(from_gsdata(data))


def _declared(path: Path, version: int, count: int, degree: int, bits: int) -> int:
    """The bytes of splat data that an SPZ header declares, refused when out of range."""
    if degree not in REST_COEFFICIENTS or not 1 <= bits <= 24:
        raise InputError(f"{path}: an SPZ of degree {degree} with {bits} fractional bits is "
                         "not one that is read")
    rotation = 4 if version >= 3 else 3
    return count * (9 + 1 + 3 + 3 + rotation + 3 * REST_COEFFICIENTS[degree])


def _check_gzip(path: Path) -> None:
    """A gzip SPZ (versions 2, 3): its header read, its declared size possible for the file,
    and the stream inflated in steps, never past that size."""
    raw = path.read_bytes()
    inflate = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        head = inflate.decompress(raw, 16)
        if len(head) < 16:
            raise InputError(f"{path}: the SPZ stream ends before its header")
        magic, version, count, degree, bits = struct.unpack_from("<IIIBB", head)
        if magic != MAGIC or version not in (2, 3):
            raise InputError(f"{path}: SPZ version {version} is not read (2, 3 and 4 are)"
                             if magic == MAGIC else f"{path} is not an SPZ file")
        declared = _declared(path, version, count, degree, bits)
        if declared > MAX_RATIO * len(raw):
            raise InputError(f"{path}: its header declares {count} splats, more than "
                             f"{len(raw)} compressed bytes can hold")
        total, tail = 0, inflate.unconsumed_tail
        while True:
            out = inflate.decompress(tail, _STEP)
            total, tail = total + len(out), inflate.unconsumed_tail
            if total > declared + _STEP:
                raise InputError(f"{path}: the SPZ stream inflates beyond the {count} splats "
                                 "its header declares")
            if not out and not tail:
                break
    except zlib.error as exc:
        raise InputError(f"{path}: the SPZ stream is corrupt ({exc})") from None
    if total < declared:
        raise InputError(f"{path}: the SPZ stream holds {total} bytes of splats, its header "
                         f"declares {declared}: it is truncated")


def _check_ngsp(path: Path, start: bytes) -> None:
    """An NGSP SPZ (version 4): the header's count possible for the file's size."""
    if len(start) < 32:
        raise InputError(f"{path}: the SPZ header is cut short")
    _, version, count, degree, bits = struct.unpack_from("<IIIBB", start)
    if version != 4:
        raise InputError(f"{path}: an SPZ of version {version} not in a gzip stream is not read "
                         "(versions 2 and 3 are gzip streams, 4 is NGSP)")
    size = path.stat().st_size
    if _declared(path, version, count, degree, bits) > MAX_RATIO * size:
        raise InputError(f"{path}: its header declares {count} splats, more than {size} "
                         "compressed bytes can hold")


def fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (at most ``MAX_FRACTIONAL_BITS``, Niantic's default) at
    which SPZ's signed 24-bit positions hold every one of ``means``.

    Raises
    ------
    InputError
        If even whole units cannot (a splat 2^23 or more from the origin).

    Examples
    --------
    >>> fractional_bits(np.array([[1.0, -3.0, 2000.0]]))
    12
    >>> fractional_bits(np.array([[1e4, 0.0, 0.0]]))
    9
    """
    reach = float(np.abs(means).max(initial=0.0))
    largest = 2 ** (POSITION_BITS - 1) - 1
    bits = MAX_FRACTIONAL_BITS
    while bits > 0 and round(reach * 2 ** bits) > largest:
        bits -= 1
    if round(reach * 2 ** bits) > largest:
        raise InputError(f"SPZ's 24-bit positions reach {largest} from the origin; the splats "
                         f"reach {reach:.4g}: write .ply")
    return bits


def write_spz(fields: SplatFields, path: str | os.PathLike, version: int = 3) -> None:
    """``fields`` as SPZ (gzip version 3, or NGSP version 4), in SPZ's RUB frame, through
    ``gsply``: 24-bit fixed-point positions of ``fractional_bits``, 8-bit colours, scales
    and opacities, spherical harmonics in 8 bits, rotations as smallest three."""
    gsply = gsply_module("SPZ")
    rub = flip_axes(fields)
    data = gsply.GSData(means=rub.means, sh0=rub.sh0, shN=rub.shN, opacities=rub.opacities,
                        scales=rub.scales, quats=unit_quaternions(rub.quats),
                        _format=gsply.create_ply_format(fields.degree))
    gsply.write_spz(path, data, fractional_bits=fractional_bits(fields.means),
                    version=version)
