"""Splats as files other viewers open (``splat_files``: the 3D Gaussian splatting PLY,
SuperSplat's compressed PLY, Niantic's SPZ, ``.splat``): a run's splats, recoloured, as the
``SplatFields`` such files hold.

Nothing is lost silently: ``splat_files.write_splat_file`` reads every file back before it
is put in place and refuses, in one line naming the attribute, one that does not hold what
was meant within its format's quantisation.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from splat_files import FORMATS, SplatFields, write_splat_file

from ..edit.regions import Region
from .model import Splats
from .sh import SH_C0


def export_splats(splats: Splats, path: str | os.PathLike, palette: np.ndarray | None = None,
                  regions: Sequence[Region] = (), force: bool = False) -> Path:
    """The splats recoloured (``splat_fields``) to ``path``, in the format its suffix names
    (``WRITERS``), written atomically; an existing file is replaced only with ``force``:
    what ``nerf-stage export`` and the studio write."""
    return write_splat_file(splat_fields(splats, palette, regions), path, force)


#: The suffixes a splat export is written as.
WRITERS = tuple(suffix for suffix, found in FORMATS.items() if found.writer)
#: Float32 can hold a logit of +-16.6 and a log scale of -87 exactly: the extremes kept.
_OPACITY_EPS = 2.0 ** -24
_SMALLEST_SCALE = float(np.finfo(np.float32).tiny)


def splat_fields(splats: Splats, palette: np.ndarray | None = None,
                 regions: Sequence[Region] = ()) -> SplatFields:
    """The splats recoloured with ``palette`` (the run's by default; inside ``regions``
    only, when given: ``Splats.colours``) as 3D Gaussian splatting stores them (float32
    ``SplatFields``): the degree-0 coefficients of the colours, the view-dependent residual
    through the basis as the higher ones ((S, 0, 3) without one), logit opacities, log
    scales, unit quaternions.

    Raises
    ------
    InputError
        If a value does not fit in float32.
    """
    rest = splats.rest_colours(palette, regions)
    opacity = np.clip(splats.opacities.astype(np.float64), _OPACITY_EPS, 1 - _OPACITY_EPS)
    quats = splats.rotations.astype(np.float64)
    fields = {"means": splats.centres,
              "sh0": (splats.colours(palette, regions).astype(np.float64) - 0.5) / SH_C0,
              "shN": np.zeros((len(splats), 0, 3)) if rest is None else rest,
              "opacities": np.log(opacity / (1 - opacity)),
              "scales": np.log(np.maximum(splats.scales.astype(np.float64), _SMALLEST_SCALE)),
              "quats": quats / np.linalg.norm(quats, axis=1, keepdims=True)}
    with np.errstate(over="ignore", invalid="ignore"):
        cast = {name: np.ascontiguousarray(value, np.float32) for name, value in fields.items()}
    for name, value in cast.items():
        if not np.isfinite(value).all():
            raise InputError(f"the splats' {name} do not fit in float32 (largest "
                             f"{np.abs(fields[name]).max():.3g}); nothing was written")
    return SplatFields(**cast)
