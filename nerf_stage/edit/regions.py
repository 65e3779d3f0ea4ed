"""Regions of a scene: boxes and ellipsoids in world coordinates, inside which a palette edit
applies (docs/selections.md).

Recolouring is linear in the weights, so a render's weights w split exactly into a part
inside the regions and a part outside, each recoloured with its own palette:

    rgb = (w - w_in) @ B(P_out) + w_in @ B(P_in) + (1 - opacity) background.

A pixel's light comes from the samples along its rays, each with its compositing weight
T_i alpha_i. ``w_in`` is w times the share of the first half of that light (the samples in
front of the pixel's median termination) whose samples lie in a region
(``PixelSamples.shares``): a pixel is what its rays reach first, and light that leaks
through a surface the field left not quite opaque does not move it out of the region.
It is exact for a pixel whose samples all lie on one side; a deferred field
(``GridConfig.deferred``) has one colour per ray, so splitting a pixel's weights is the
only split there is. The samples are kept with a render (``render.samples``), so moving a
region splits again without the network; docs/selections.md measures the choice of the
first half against the alternatives.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.json_file import read_json
from palette_core.selection import Selection

SHAPES = ("box", "ellipsoid", "colour")


@dataclass(frozen=True)
class Region:
    """A box or an ellipsoid, axis-aligned in world coordinates.

    Attributes
    ----------
    shape : "box" or "ellipsoid"
    centre : (3,) tuple of float
    half : (3,) tuple of float
        Half sizes (box) or radii (ellipsoid), all positive.
    """

    shape: str
    centre: tuple[float, float, float]
    half: tuple[float, float, float]

    def __post_init__(self):
        if self.shape not in SHAPES[:2]:
            raise InputError(f"unknown region shape {self.shape!r}; choose one of "
                             f"{', '.join(SHAPES)}")
        numbers = (*self.centre, *self.half)
        if len(numbers) != 6 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                        and math.isfinite(x) for x in numbers):
            raise InputError(f"a {self.shape} region needs 3 finite centre coordinates and "
                             f"3 finite sizes, got {list(self.centre)} and {list(self.half)}")
        if min(self.half) <= 0:
            raise InputError(f"a {self.shape} region needs sizes above zero, got "
                             f"{list(self.half)}")

    @classmethod
    def box(cls, low, high) -> Region:
        """The box between corners ``low`` and ``high`` (3,)."""
        low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        return cls("box", tuple(((low + high) / 2).tolist()),
                   tuple((np.abs(high - low) / 2).tolist()))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: which of the (P, 3) world ``points`` lie inside (its surface included)."""
        offset = np.abs(points - np.asarray(self.centre, points.dtype))
        offset /= np.asarray(self.half, points.dtype)
        if self.shape == "box":
            return (offset <= 1).all(-1)
        return np.einsum("pc,pc->p", offset, offset) <= 1

    def to_dict(self) -> dict:
        return {"shape": self.shape, "centre": list(self.centre), "half": list(self.half)}


@dataclass(frozen=True)
class ColourRegion:
    """A weight-space selection, as in photos (``palette_core.selection``): the pixels whose
    weight for palette colour ``colour`` (its first-order term for transport weights), divided
    by the pixel's opacity, is at least ``threshold``."""

    colour: int
    threshold: float = 0.5
    shape = "colour"

    def __post_init__(self):
        if not isinstance(self.colour, int) or isinstance(self.colour, bool):
            raise InputError(f"a colour region names a palette colour by its index, got "
                             f"{self.colour!r}")
        self.selection()  # checks the threshold

    def selection(self) -> Selection:
        return Selection(colour=self.colour, threshold=self.threshold)

    def values(self, weights: np.ndarray, opacity: np.ndarray, basis) -> np.ndarray:
        """(N, H, W) 0 or 1 for views of (N, H, W, M) ``weights`` premultiplied by their
        (N, H, W) ``opacity``."""
        straight = weights / np.maximum(opacity, 1e-6)[..., None]
        selection = self.selection()
        return np.stack([selection.values("view", w, None, basis) for w in straight])

    def to_dict(self) -> dict:
        return {"shape": self.shape, "colour": self.colour, "threshold": self.threshold}


#: Most regions one edit applies inside: their samples' tests and the saved render grow with
#: the count, and no edit needs more.
MAX_REGIONS = 64


def check_count(regions: list, where: str) -> list:
    """``regions``, InputError if more than ``MAX_REGIONS`` (or not a list)."""
    if not isinstance(regions, list) or len(regions) > MAX_REGIONS:
        count = len(regions) if isinstance(regions, list) else "no list of"
        raise InputError(f"{where}: {count} regions, at most {MAX_REGIONS} apply at once")
    return regions


def region_from_dict(data, where: str) -> Region | ColourRegion:
    """The region of a ``to_dict``, from a file named by ``where``; InputError if malformed."""
    if isinstance(data, dict) and data.get("shape") == ColourRegion.shape:
        if not set(data) <= {"shape", "colour", "threshold"} or "colour" not in data:
            raise InputError(f"{where}: a colour region is {{\"shape\", \"colour\", "
                             f"\"threshold\"}}, got {data!r}")
        return ColourRegion(data["colour"], data.get("threshold", 0.5))
    if not isinstance(data, dict) or set(data) != {"shape", "centre", "half"}:
        raise InputError(f"{where}: a region is {{\"shape\", \"centre\", \"half\"}}, got "
                         f"{data!r}")
    centre, half = data["centre"], data["half"]
    if not (isinstance(centre, list) and isinstance(half, list)):
        raise InputError(f"{where}: a region's centre and half are lists of 3 numbers")
    return Region(data["shape"], tuple(centre), tuple(half))


def parse_region(text: str) -> list[Region | ColourRegion]:
    """Regions from the command line: ``box:x0,y0,z0,x1,y1,z1`` (two corners),
    ``ellipsoid:cx,cy,cz,rx,ry,rz`` (centre and radii), ``colour:K`` or ``colour:K,T``
    (palette colour K's weight at least T, 0.5 by default), or a JSON file
    (``read_regions``).

    Raises
    ------
    InputError
        For an unknown shape, numbers that are not 6 finite ones, or a zero size.
    """
    shape, colon, numbers = text.partition(":")
    if not colon:
        return read_regions(text)
    if shape not in SHAPES:
        raise InputError(f"unknown region shape {shape!r} in {text!r}; choose one of "
                         f"{', '.join(SHAPES)} (box:x0,y0,z0,x1,y1,z1, "
                         "ellipsoid:cx,cy,cz,rx,ry,rz or colour:K[,T]), or give a region file")
    try:
        values = [float(x) for x in numbers.split(",")]
    except ValueError:
        values = []
    if shape == ColourRegion.shape:
        if len(values) not in (1, 2) or not values[0].is_integer():
            raise InputError(f"region {text!r} needs a palette colour index and optionally "
                             "a threshold: colour:K or colour:K,T")
        return [ColourRegion(int(values[0]), *values[1:])]
    if len(values) != 6 or not all(math.isfinite(x) for x in values):
        raise InputError(f"region {text!r} needs 6 finite numbers separated by commas")
    if shape == "box":
        return [Region.box(values[:3], values[3:])]
    return [Region("ellipsoid", tuple(values[:3]), tuple(values[3:]))]


def read_regions(path: str | os.PathLike) -> list[Region | ColourRegion]:
    """The regions of a JSON file: ``{"regions": [{"shape", "centre", "half"} |
    {"shape": "colour", "colour", "threshold"}, ...]}`` (a palette file the studio saved
    holds them beside its colours; docs/formats.md)."""
    path = Path(path)
    data = read_json(path, "region file", " (a region is box:x0,y0,z0,x1,y1,z1, "
                     "ellipsoid:cx,cy,cz,rx,ry,rz or a file)")
    regions = data.get("regions") if isinstance(data, dict) else None
    if not isinstance(regions, list) or not regions:
        raise InputError(f"region file {path} must hold {{\"regions\": [regions...]}}")
    check_count(regions, f"region file {path}")
    return [region_from_dict(r, f"region file {path}") for r in regions]


__all__ = ["ColourRegion", "Region", "SHAPES", "parse_region",
           "read_regions", "region_from_dict"]
