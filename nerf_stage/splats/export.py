"""Splats as files other viewers open: the 3D Gaussian splatting PLY, and Niantic's
compressed SPZ (through PyPI's ``gsply``, the ``spz`` extra)."""

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


def splat_fields(splats: Splats, palette: np.ndarray | None = None,
                 regions: Sequence[Region] = ()) -> dict[str, np.ndarray]:
    """The splats recoloured with ``palette`` (the run's by default; inside ``regions``
    only, when given: ``Splats.colours``), as 3D Gaussian splatting stores them: (S, 3)
    ``means``, (S, 3) ``sh0`` (degree-0 spherical-harmonic coefficients), (S, B - 1, 3)
    ``shN`` (the view-dependent residual of a splat run through the basis; (S, 0, 3)
    without one), (S,) ``opacities`` (logit), (S, 3) ``scales`` (log), (S, 4) ``quats``
    (w, x, y, z)."""
    rest = splats.rest_colours(palette, regions)
    opacity = splats.opacities.astype(np.float64)
    return {"means": splats.centres,
            "sh0": (splats.colours(palette, regions).astype(np.float64) - 0.5) / SH_C0,
            "shN": np.zeros((len(splats), 0, 3)) if rest is None else rest,
            "opacities": np.log(opacity / (1 - opacity)), "scales": np.log(splats.scales),
            "quats": splats.rotations}


def write_ply(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
              regions: Sequence[Region] = ()) -> None:
    """Write ``splat_fields`` as a 3D Gaussian splatting PLY (binary, little endian): x, y,
    z, nx, ny, nz, f_dc_0..2, f_rest_* (channel by channel, as 3D Gaussian splatting
    flattens them), opacity, scale_0..2, rot_0..3: the layout splat viewers read."""
    splat = splat_fields(splats, palette, regions)
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


def write_spz(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
              regions: Sequence[Region] = ()) -> None:
    """Write ``splat_fields`` as Niantic's SPZ (version 3: gzip, 24-bit fixed-point
    positions with 12 fractional bits, 8-bit colours, scales, opacities and spherical
    harmonics; smallest-three rotations), in the PLY's frame, through ``gsply``."""
    try:
        import gsply
    except ImportError:
        raise InputError("writing .spz needs gsply: pip install "
                         "'palette-nerf-toolkit[spz]'") from None
    splat = {name: np.ascontiguousarray(value, np.float32)
             for name, value in splat_fields(splats, palette, regions).items()}
    degree = {0: 0, 3: 1, 8: 2, 15: 3}[splat["shN"].shape[1]]
    gsply.write_spz(path, gsply.GSData(**splat, _format=gsply.create_ply_format(degree)))


#: Splat file writers by suffix (``export_splats``).
WRITERS = {".ply": write_ply, ".spz": write_spz}
