"""Splats as files other viewers open: the 3D Gaussian splatting PLY."""

from __future__ import annotations

import os

import numpy as np

from .model import Splats

#: The spherical-harmonics constant of degree 0: a colour c is stored as (c - 0.5) / SH_C0.
SH_C0 = 0.28209479177387814


def write_ply(splats: Splats, path: str | os.PathLike, colours: np.ndarray | None = None) -> None:
    """Write the splats with (S, 3) ``colours`` (default ``splats.colours()``) as a 3D
    Gaussian splatting PLY (binary, little endian): x, y, z, nx, ny, nz, f_dc_0..2 (degree-0
    spherical harmonics), opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z), the
    layout splat viewers read."""
    colours = (splats.colours() if colours is None else colours).astype(np.float64)
    opacity = splats.opacities.astype(np.float64)
    fields = {
        "x": splats.centres[:, 0], "y": splats.centres[:, 1], "z": splats.centres[:, 2],
        "nx": 0.0, "ny": 0.0, "nz": 0.0,
        **{f"f_dc_{i}": (colours[:, i] - 0.5) / SH_C0 for i in range(3)},
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

