"""The splat file formats by name (``FORMATS``): each one's reader, writer and what a round
trip through it may change (docs/splat_files.md).

Every file read is checked (``SplatFields.checked``); every file written is staged, read
back and compared with what was meant within its format's quantisation before it is put in
place, so nothing is lost silently: a value the format cannot hold is refused in one line,
naming the attribute, and what a format drops by design (``.splat``'s view-dependent
colour, its colours beyond [0, 1]) is said on stderr.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_writable

from .antimatter import read_splat, write_splat
from .fields import SH_C0, SplatFields
from .ply import read_ply, write_compressed_ply, write_ply
from .sog import read_sog
from .spz import fractional_bits, read_spz, write_spz


@dataclass(frozen=True)
class Format:
    """A splat file format: its ``reader``, its ``writer`` (None: read only) and the
    ``tolerances`` of a round trip, (fields) -> {attribute: largest change}."""

    name: str
    reader: Callable[[Path], SplatFields]
    writer: Callable[[SplatFields, Path], None] | None
    tolerances: Callable[[SplatFields], dict[str, float]]
    #: Least |q . q'| of a unit rotation and its round trip.
    rotations: float


def _exact(fields: SplatFields) -> dict[str, float]:
    return dict.fromkeys(("means", "sh0", "shN", "opacities", "scales"), 0.0)


def _spz(fields: SplatFields) -> dict[str, float]:
    """Niantic's spz ``load-spz.cc``: colours in 8 bits of a range 0.15 wide, opacities as
    sigmoids to a 255th, log scales to a 16th, spherical harmonics to a 128th, positions to
    their fractional bits; half a step each."""
    return {"means": 0.5 * 2.0 ** -fractional_bits(fields.means), "sh0": 0.5 / (0.15 * 255),
            "shN": 0.5 / 128, "opacities": 0.5 / 255, "scales": 0.5 / 16}


def _compressed(fields: SplatFields) -> dict[str, float]:
    """SuperSplat's compressed PLY: positions and log scales in 11, 10, 11 bits of each
    chunk's range (at most the scene's), colours and opacities in 8 bits, spherical
    harmonics in 8 bits of [-4, 4]; half a step each."""
    extent = float(np.ptp(fields.means, 0).max())
    scales = float(np.ptp(fields.scales, 0).max())
    return {"means": extent / 1023, "sh0": 0.5 / 255 / SH_C0, "shN": 4 / 256,
            "opacities": 0.5 / 255, "scales": scales / 1023}


def _splat(fields: SplatFields) -> dict[str, float]:
    """``.splat``: colours and opacities in bytes, scales as float32 of exp."""
    return {"means": 0.0, "sh0": 0.5 / 255 / SH_C0, "opacities": 0.5 / 255, "scales": 1e-6}


#: Formats by the suffix that names them (``.compressed.ply`` before ``.ply``).
FORMATS = {
    ".compressed.ply": Format("compressed PLY", read_ply, write_compressed_ply, _compressed,
                              0.999),
    ".ply": Format("PLY", read_ply, write_ply, _exact, 1 - 1e-6),
    ".spz": Format("SPZ", read_spz, write_spz, _spz, 0.999),
    ".splat": Format(".splat", read_splat, write_splat, _splat, 0.99),
    ".sog": Format("SOG", read_sog, None, _exact, 0.0),
}
#: Formats of other splat tools that are not read, and what to do instead.
UNREAD = {".ksplat": "convert it with splat-transform to .ply first",
          ".glb": "export it from its tool as .ply", ".lcc": "convert it to .ply first"}


def format_of(path: str | os.PathLike) -> Format | None:
    """The format ``path`` names by its suffix (a folder of a SOG's meta.json: SOG)."""
    path = Path(path)
    if path.is_dir() and (path / "meta.json").is_file():
        return FORMATS[".sog"]
    name = path.name.lower()
    return next((f for suffix, f in FORMATS.items() if name.endswith(suffix)), None)


def is_splat_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a splat file we read (by suffix), or one we do not."""
    return format_of(path) is not None or Path(path).suffix.lower() in UNREAD


def read_splat_file(path: str | os.PathLike) -> SplatFields:
    """The checked splats of the file ``path``, in the format its suffix names.

    Raises
    ------
    InputError
        If the format is not read, the file cannot be read, or it does not hold splats a
        renderer can draw (``SplatFields.checked``).
    """
    path = Path(path)
    found = format_of(path)
    if found is None:
        hint = UNREAD.get(path.suffix.lower())
        raise InputError(f"{path}: the {path.suffix or 'suffixless'} format is not read"
                         + (f": {hint}" if hint else f" (read: {', '.join(FORMATS)})"))
    try:
        return found.reader(path).checked(str(path))
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None


def write_splat_file(fields: SplatFields, path: str | os.PathLike,
                     force: bool = False) -> Path:
    """``fields`` written to ``path`` in the format its suffix names: staged, read back and
    checked (``check_round_trip``), then put in place; an existing file is replaced only
    with ``force``.

    Raises
    ------
    InputError
        If the format is not written, or cannot hold the splats (naming the attribute).
    """
    path = Path(path)
    found = format_of(path)
    if found is None or found.writer is None:
        written = [s for s, f in FORMATS.items() if f.writer]
        raise InputError(f"splats are written as {', '.join(written)}, not {path.name}")
    check_writable([path], force)
    meant = _as_format_holds(fields, found)
    with atomic_outputs(force) as stage:
        staged = stage(path)
        found.writer(meant, staged)
        check_round_trip(meant, found.reader(staged), found)
    return path


def _as_format_holds(fields: SplatFields, found: Format) -> SplatFields:
    """``fields`` as ``found`` can hold them by design, what it drops said on stderr:
    ``.splat`` keeps neither view-dependent colour nor colours beyond [0, 1]."""
    if found.name != ".splat":
        return fields
    colours = fields.colours()
    clipped = int((np.abs(colours - 0.5) > 0.5 + 0.5 / 255).any(1).sum())
    if fields.degree or clipped:
        print(f"note: .splat holds colours in [0, 1] without view dependence: "
              f"{'degree ' + str(fields.degree) + ' terms dropped; ' if fields.degree else ''}"
              f"{clipped} colours clipped", file=sys.stderr)
    return fields.with_colour((np.clip(colours, 0, 1) - 0.5) / SH_C0, fields.shN[:, :0])


def check_round_trip(meant: SplatFields, read: SplatFields, found: Format) -> None:
    """InputError naming the first attribute that ``read`` (a file read back) does not hold
    within ``found``'s tolerances of ``meant`` (float32 arithmetic; a tolerance of zero asks
    for the same bits)."""
    if len(read) != len(meant):
        raise InputError(f"the {found.name} file read back holds {len(read)} splats, not "
                         f"{len(meant)}")
    for name, tolerance in found.tolerances(meant).items():
        a, b = getattr(meant, name), getattr(read, name)
        if a.shape != b.shape:
            raise InputError(f"the {found.name} file read back holds {name} of shape "
                             f"{b.shape}, not {a.shape}")
        if tolerance == 0 and np.array_equal(a, b):
            continue
        if name == "opacities":  # compared as what a viewer draws
            a, b = 1 / (1 + np.exp(-a)), 1 / (1 + np.exp(-b))
        error = np.abs(a - b) - np.float32(tolerance) - 1e-6 * np.maximum(np.abs(a), 1)
        if a.size and not (error <= 0).all():
            worst = np.unravel_index(np.nanargmax(np.where(np.isnan(error), np.inf, error)),
                                     a.shape)[0]
            raise InputError(f"{found.name} cannot hold the splats' {name} (splat {worst}: "
                             f"{np.ravel(a[worst])[:3].round(4).tolist()} comes back as "
                             f"{np.ravel(b[worst])[:3].round(4).tolist()}); write .ply, which "
                             "keeps float32")
    unit = [q / np.linalg.norm(q, axis=1, keepdims=True) for q in (meant.quats, read.quats)]
    agreement = np.abs(np.einsum("sq,sq->s", unit[0], unit[1]))
    if not (agreement >= found.rotations).all():
        raise InputError(f"{found.name} cannot hold the splats' rotations (splat "
                         f"{int(np.argmin(agreement))})")
