"""Splats as files other viewers open: the 3D Gaussian splatting PLY, and Niantic's
compressed SPZ (through PyPI's ``gsply``, the ``spz`` extra).

Nothing is lost silently: each writer picks a representation that holds what it is given
(SPZ's fractional bits from the splats' extent; logit opacities and log scales kept
finite), and every file is read back before it is put in place and compared with what was
meant, attribute by attribute, within the format's quantisation (``TOLERANCES``); a file
that does not hold it is refused in one line, naming the attribute, and never written.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_writable

from ..edit.regions import Region
from .model import Splats
from .sh import SH_C0


def export_splats(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
                  regions: Sequence[Region] = (), force: bool = False) -> Path:
    """The splats recoloured (``splat_fields``) to ``path``, in the format its suffix names
    (``WRITERS``: ``.ply`` or ``.spz``), written atomically; an existing file is replaced
    only with ``force``: what ``nerf-stage export`` and the studio write."""
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        raise InputError(f"a splat export is written as {' or '.join(WRITERS)}, got {path}")
    check_writable([path], force)
    with atomic_outputs(force) as stage:
        writer(splats, stage(path), palette, regions)
    return path


#: What each attribute may differ by after a round trip through a format, beyond float32's
#: rounding: PLY stores float32; SPZ quantises (Niantic's spz ``load-spz.cc``): opacities as
#: sigmoids to a 255th, log scales to a 16th, positions to a step of its fractional bits
#: (given apart); half a step each.
TOLERANCES = {
    ".ply": {"means": 0.0, "sh0": 0.0, "shN": 0.0, "opacities": 0.0, "scales": 0.0},
    ".spz": {"sh0": 0.5 / (0.15 * 255), "shN": 0.5 / 128, "opacities": 0.5 / 255,
             "scales": 0.5 / 16},
}
#: Least |q . q'| of a unit rotation and its round trip (SPZ: smallest three, 9 or 10 bits).
ROTATION_AGREEMENT = {".ply": 1 - 1e-6, ".spz": 0.999}
#: SPZ's positions: signed 24-bit fixed point, at most this many fractional bits.
SPZ_BITS, SPZ_MAX_FRACTIONAL_BITS = 24, 12
#: Float32 can hold a logit of +-16.6 and a log scale of -87 exactly: the extremes kept.
_OPACITY_EPS = 2.0 ** -24
_SMALLEST_SCALE = float(np.finfo(np.float32).tiny)


def splat_fields(splats: Splats, palette: np.ndarray | None = None,
                 regions: Sequence[Region] = ()) -> dict[str, np.ndarray]:
    """The splats recoloured with ``palette`` (the run's by default; inside ``regions``
    only, when given: ``Splats.colours``), as 3D Gaussian splatting stores them: (S, 3)
    ``means``, (S, 3) ``sh0`` (degree-0 spherical-harmonic coefficients), (S, B - 1, 3)
    ``shN`` (the view-dependent residual of a splat run through the basis; (S, 0, 3)
    without one), (S,) ``opacities`` (logit), (S, 3) ``scales`` (log), (S, 4) ``quats``
    (w, x, y, z)."""
    rest = splats.rest_colours(palette, regions)
    opacity = np.clip(splats.opacities.astype(np.float64), _OPACITY_EPS, 1 - _OPACITY_EPS)
    quats = splats.rotations.astype(np.float64)
    return {"means": splats.centres,
            "sh0": (splats.colours(palette, regions).astype(np.float64) - 0.5) / SH_C0,
            "shN": np.zeros((len(splats), 0, 3)) if rest is None else rest,
            "opacities": np.log(opacity / (1 - opacity)),
            "scales": np.log(np.maximum(splats.scales.astype(np.float64), _SMALLEST_SCALE)),
            "quats": quats / np.linalg.norm(quats, axis=1, keepdims=True)}


def _float32_fields(splats: Splats, palette, regions) -> dict[str, np.ndarray]:
    """``splat_fields`` as the float32 a file holds; InputError where one does not fit."""
    fields = splat_fields(splats, palette, regions)
    with np.errstate(over="ignore", invalid="ignore"):
        cast = {name: np.ascontiguousarray(value, np.float32) for name, value in fields.items()}
    for name, value in cast.items():
        if not np.isfinite(value).all():
            raise InputError(f"the splats' {name} do not fit in float32 (largest "
                             f"{np.abs(fields[name]).max():.3g}); nothing was written")
    return cast


def check_round_trip(meant: dict[str, np.ndarray], read: dict[str, np.ndarray], suffix: str,
                     position_step: float = 0.0) -> None:
    """InputError naming the first attribute that ``read`` (a file read back) does not hold
    within ``TOLERANCES[suffix]`` of ``meant`` (positions within half of ``position_step``)."""
    what = suffix.lstrip(".").upper()
    if len(read["means"]) != len(meant["means"]):
        raise InputError(f"the {what} file read back holds {len(read['means'])} splats, not "
                         f"{len(meant['means'])}")
    tolerances = {**TOLERANCES[suffix], "means": position_step / 2}
    for name, tolerance in tolerances.items():
        a, b = meant[name].astype(np.float64), read[name].astype(np.float64)
        if name == "opacities":  # held as sigmoids by SPZ: compared as what a viewer draws
            a, b = 1 / (1 + np.exp(-a)), 1 / (1 + np.exp(-b))
        if a.shape != b.shape:
            raise InputError(f"the {what} file read back holds {name} of shape {b.shape}, not "
                             f"{a.shape}")
        error = np.abs(a - b) - tolerance - 1e-6 * np.maximum(np.abs(a), 1.0)
        if a.size and not (error <= 0).all():
            worst = np.unravel_index(np.nanargmax(np.where(np.isnan(error), np.inf, error)),
                                     a.shape)[0]
            raise InputError(f"{what} cannot hold the splats' {name} (splat {worst}: "
                             f"{np.ravel(a[worst])[:3].round(4).tolist()} comes back as "
                             f"{np.ravel(b[worst])[:3].round(4).tolist()}); write .ply, which "
                             "keeps float32")
    agreement = np.abs(np.sum(meant["quats"] * read["quats"], 1))
    if agreement.size and not (agreement >= ROTATION_AGREEMENT[suffix]).all():
        raise InputError(f"{what} cannot hold the splats' rotations (splat "
                         f"{int(np.argmin(agreement))})")


def spz_fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (at most ``SPZ_MAX_FRACTIONAL_BITS``, Niantic's default) at
    which SPZ's signed 24-bit positions hold every one of ``means``.

    Raises
    ------
    InputError
        If even whole units cannot (a splat 2^23 or more from the origin).

    Examples
    --------
    >>> spz_fractional_bits(np.array([[1.0, -3.0, 2000.0]]))
    12
    >>> spz_fractional_bits(np.array([[1e4, 0.0, 0.0]]))
    9
    """
    reach = float(np.abs(means).max(initial=0.0))
    largest = 2 ** (SPZ_BITS - 1) - 1
    bits = SPZ_MAX_FRACTIONAL_BITS
    while bits > 0 and round(reach * 2 ** bits) > largest:
        bits -= 1
    if round(reach * 2 ** bits) > largest:
        raise InputError(f"SPZ's 24-bit positions reach {largest} from the origin; the splats "
                         f"reach {reach:.4g}: write .ply")
    return bits


def write_ply(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
              regions: Sequence[Region] = ()) -> None:
    """Write ``splat_fields`` as a 3D Gaussian splatting PLY (binary, little endian): x, y,
    z, nx, ny, nz, f_dc_0..2, f_rest_* (channel by channel, as 3D Gaussian splatting
    flattens them), opacity, scale_0..2, rot_0..3: the layout splat viewers read."""
    splat = _float32_fields(splats, palette, regions)
    rest = splat["shN"].transpose(0, 2, 1).reshape(len(splats), -1)  # channel-major
    fields = {
        **{axis: splat["means"][:, i] for i, axis in enumerate("xyz")},
        "nx": 0.0, "ny": 0.0, "nz": 0.0,
        **{f"f_dc_{i}": splat["sh0"][:, i] for i in range(3)},
        **{f"f_rest_{i}": column for i, column in enumerate(rest.T)},
        "opacity": splat["opacities"],
        **{f"scale_{i}": splat["scales"][:, i] for i in range(3)},
        **{f"rot_{i}": splat["quats"][:, i] for i in range(4)},
    }
    table = np.zeros(len(splats), [(name, "<f4") for name in fields])
    for name, value in fields.items():
        table[name] = value
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(splats)}\n"
              + "".join(f"property float {name}\n" for name in fields) + "end_header\n")
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(table.tobytes())
    check_round_trip(splat, read_ply_fields(path), ".ply")


def read_ply_fields(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The ``splat_fields`` of a 3D Gaussian splatting PLY as ``write_ply`` writes it (binary
    little endian, float properties of one vertex element), float32.

    Raises
    ------
    InputError
        If the header is not such a one or the body does not hold what it declares.
    """
    with open(path, "rb") as file:
        lines = []
        while len(lines) < 256 and (not lines or lines[-1] != "end_header"):
            lines.append(file.readline(256).decode("ascii", "replace").strip())
        body = file.read()
    names = [line.split()[-1] for line in lines if line.startswith("property float ")]
    counts = [line.split()[-1] for line in lines if line.startswith("element vertex ")]
    if (lines[:2] != ["ply", "format binary_little_endian 1.0"] or lines[-1] != "end_header"
            or len(counts) != 1 or not counts[0].isdigit()
            or int(counts[0]) * 4 * len(names) != len(body)):
        raise InputError(f"{path} is not a binary 3D Gaussian splatting PLY of whole splats")
    table = np.frombuffer(body, [(name, "<f4") for name in names])
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    column = {name: table[name] for name in names}
    return {"means": np.stack([column[a] for a in "xyz"], 1),
            "sh0": np.stack([column[f"f_dc_{i}"] for i in range(3)], 1),
            "shN": np.stack([column[n] for n in rest], 1).reshape(len(table), 3, -1)
            .transpose(0, 2, 1) if rest else np.zeros((len(table), 0, 3), np.float32),
            "opacities": column["opacity"],
            "scales": np.stack([column[f"scale_{i}"] for i in range(3)], 1),
            "quats": np.stack([column[f"rot_{i}"] for i in range(4)], 1)}


def write_spz(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
              regions: Sequence[Region] = ()) -> None:
    """Write ``splat_fields`` as Niantic's SPZ (version 3: gzip, 24-bit fixed-point
    positions with the fractional bits of ``spz_fractional_bits``, 8-bit colours, scales,
    opacities and spherical harmonics; smallest-three rotations), in the PLY's frame,
    through ``gsply``; read back and checked (``check_round_trip``)."""
    try:
        import gsply
    except ImportError:
        raise InputError("writing .spz needs gsply: pip install "
                         "'palette-nerf-toolkit[spz]'") from None
    splat = _float32_fields(splats, palette, regions)
    bits = spz_fractional_bits(splat["means"])
    degree = {0: 0, 3: 1, 8: 2, 15: 3}[splat["shN"].shape[1]]
    gsply.write_spz(path, gsply.GSData(**splat, _format=gsply.create_ply_format(degree)),
                    fractional_bits=bits)
    read = gsply.read_spz(path)
    back = {name: np.asarray(getattr(read, name)) for name in splat if name != "shN"}
    back["shN"] = splat["shN"][:, :0] if read.shN is None else np.asarray(read.shN)
    check_round_trip(splat, back, ".spz", 2.0 ** -bits)


#: Splat file writers by suffix (``export_splats``).
WRITERS = {".ply": write_ply, ".spz": write_spz}
