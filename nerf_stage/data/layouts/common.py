"""What every dataset layout's reader shares: the frames it finds (``Frames``), the layout's
record (``Layout``), and the checks of what a file from elsewhere says (JSON, numbers,
poses, frame paths that stay inside the dataset).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from palette_core.errors import InputError

from ..cameras import Intrinsics
from ..distortion import Distortion
from ..points import Points

SPLITS = ("train", "val", "test")
HOLDOUT = 8  # every eighth frame of a capture is a test view


@dataclass(frozen=True)
class Frames:
    """What a layout's reader finds in a dataset folder (``Dataset``'s fields of the same
    names): frame paths, splits, (N, 4, 4) poses, the cameras (one for all frames, or one a
    frame) and their distortions, (N,) off-ring marks (or None) and sparse points (or
    None)."""

    names: list[str]
    splits: list[str]
    poses: np.ndarray
    cameras: list[Intrinsics]
    distortions: list[Distortion]
    off_ring: np.ndarray | None = None
    points: Points | None = None
    bounds: np.ndarray | None = None
    """(N, 2) near and far depths of the scene in each frame, where the layout has them."""


@dataclass(frozen=True)
class Layout:
    """A dataset layout: the file that marks it (``marker``), whether a folder holds it
    (``holds(root)``), and its reader (``read(root, frames_outside) -> Frames``)."""

    marker: str
    holds: Callable[[Path], bool]
    read: Callable[[Path, bool], Frames]


def listing(names: list[str], most: int = 5) -> str:
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError(f"{path}: expected an object with a 'frames' list")
    return data


def number(data: dict, key: str, path: Path, kind=float):
    value = data.get(key)
    if (not isinstance(value, (int, float)) or isinstance(value, bool)
            or not math.isfinite(value) or value <= 0):
        raise InputError(f"{path}: field {key!r} must be a positive number, got {value!r}")
    return kind(value)


def frames_of(data: dict, path: Path, default_suffix: str,
            frames_outside: bool) -> tuple[list[str], list, list[bool]]:
    """Image names (relative to root, with suffix), poses and off-ring flags of a ``frames``
    list."""
    names, poses, off_ring = [], [], []
    for i, frame in enumerate(data["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(f"{where}: missing 'file_path'")
        name = frame["file_path"]
        if not PurePosixPath(name).suffix:  # Blender's file_path leaves out ".png"
            name += default_suffix
        pose = np.asarray(frame.get("transform_matrix"), dtype=object)
        if pose.shape not in ((4, 4), (3, 4)):
            raise InputError(f"{where}: 'transform_matrix' must be 4x4, got shape {pose.shape}")
        try:
            pose = pose.astype(np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}: 'transform_matrix' must hold numbers") from None
        if not np.isfinite(pose).all():
            raise InputError(f"{where}: 'transform_matrix' holds NaN or infinity")
        if not isinstance(frame.get("off_ring", False), bool):
            raise InputError(f"{where}: 'off_ring' must be true or false")
        names.append(frame_path(name, where, path.parent, frames_outside))
        poses.append(np.vstack([pose[:3], [0.0, 0.0, 0.0, 1.0]]))
        off_ring.append(frame.get("off_ring", False))
    return names, poses, off_ring


def frame_path(name: str, where: str, root: Path, frames_outside: bool) -> str:
    """A frame's image ``name`` normalised, InputError if it lies outside ``root``, by its
    name or through a link (unless ``frames_outside``): a file from elsewhere cannot make us
    read what it does not hold."""
    path = PurePosixPath(os.path.normpath(name))
    if not frames_outside and (path.is_absolute() or path.parts[:1] == ("..",)
                               or not (root / path).resolve().is_relative_to(root.resolve())):
        raise InputError(f"{where}: file_path {name!r} lies outside {root}",
                         fixes=[("frames_outside", "to read it")])
    return path.as_posix()


def holdout(n: int) -> list[str]:
    """Splits of n frames of a capture: every eighth a test view (one frame: training)."""
    return ["test" if i % HOLDOUT == HOLDOUT - 1 and n > 1 else "train"
            for i in range(n)]
