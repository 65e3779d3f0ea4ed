"""Splats as files other viewers open: the 3D Gaussian splatting PLY."""

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


def export_ply(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
               regions: Sequence[Region] = (), force: bool = False) -> Path:
    """``write_ply`` to ``path`` (a ``.ply``, written atomically; an existing file is
    replaced only with ``force``): what ``nerf-stage export`` and the studio write."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise InputError(f"a splat export is written as .ply, got {path}")
    check_writable([path], force)
    with atomic_outputs(force) as stage:
        write_ply(splats, stage(path), palette, regions)
    return path


def write_ply(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
              regions: Sequence[Region] = ()) -> None:
    """Write the splats recoloured with ``palette`` (the run's by default; inside
    ``regions`` only, when given: ``Splats.colours``) as a 3D Gaussian splatting PLY
    (binary, little endian): x, y, z, nx, ny, nz, f_dc_0..2 (degree-0 spherical
    harmonics), f_rest_* (the view-dependent residual of a splat run through the basis,
    channel by channel as 3D Gaussian splatting orders them), opacity (logit), scale_0..2
    (log), rot_0..3 (w, x, y, z): the layout splat viewers read."""
    colours = splats.colours(palette, regions).astype(np.float64)
    rest = splats.rest_colours(palette, regions)
    rest = {} if rest is None else {  # (S, B - 1, 3) -> channel-major, as 3DGS flattens
        f"f_rest_{i}": column for i, column in enumerate(rest.transpose(0, 2, 1)
                                                          .reshape(len(splats), -1).T)}
    opacity = splats.opacities.astype(np.float64)
    fields = {
        "x": splats.centres[:, 0], "y": splats.centres[:, 1], "z": splats.centres[:, 2],
        "nx": 0.0, "ny": 0.0, "nz": 0.0,
        **{f"f_dc_{i}": (colours[:, i] - 0.5) / SH_C0 for i in range(3)},
        **rest,
        "opacity": np.log(opacity / (1 - opacity)),
        **{f"scale_{i}": np.log(splats.scales[:, i]) for i in range(3)},
        **{f"rot_{i}": splats.rotations[:, i] for i in range(4)},
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

