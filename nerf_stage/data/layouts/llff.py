"""LLFF's forward-facing layout (Mildenhall et al. 2019), the one every forward-facing NeRF
paper reads: ``poses_bounds.npy`` and the photos in ``images/`` (or, without it, in one
``images_N`` folder of LLFF's downsampled copies).

``poses_bounds.npy`` holds one row of 17 numbers a photo, in the photos' name order: a
3 x 5 matrix, row-major, whose first three columns are the camera-to-world rotation with
LLFF's axes (x down, y right, z backwards), the fourth the camera's centre and the fifth the
full-size photo's height, width and focal length; then the near and far depths of the scene
in that photo. As NeRF's ``load_llff_data`` does, the axes are turned to OpenGL's (x right,
y up, z backwards), the world is scaled so that the nearest depth is 1 / ``BOUND_FACTOR``,
and centred on the cameras' mean pose (``recentre``). Every eighth photo, from the first,
is a test view (LLFF's ``llffhold``).

References
----------
B. Mildenhall et al. Local light field fusion: practical view synthesis with prescriptive
sampling guidelines. SIGGRAPH 2019.
B. Mildenhall et al. NeRF: representing scenes as neural radiance fields for view synthesis.
ECCV 2020 (``load_llff.py``: ``bd_factor``, ``recenter_poses``, ``llffhold``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.folders import files_in
from palette_core.io import IMAGE_SUFFIXES, image_size

from ..cameras import checked_camera
from ..distortion import Distortion
from .common import HOLDOUT, Frames, Layout

POSES_FILE = "poses_bounds.npy"
#: The nearest depth is scaled to 1 / this (NeRF's ``bd_factor``).
BOUND_FACTOR = 0.75
#: Largest ``poses_bounds.npy`` read, in bytes (a photo's row is 136).
MAX_BYTES = 64 << 20


def read(root: Path, frames_outside: bool) -> Frames:
    """The frames of the LLFF capture in ``root`` (module docstring).

    Raises
    ------
    InputError
        If ``poses_bounds.npy`` is not an (N, 17) array of finite numbers with positive
        sizes and bounds, its rows and the photos differ in number, or the photos are not of
        the size its focal length is scaled to.
    """
    table = _read_table(root / POSES_FILE)
    folder, names = _photos(root)
    if len(names) != len(table):
        raise InputError(f"{root / POSES_FILE} has {len(table)} rows for the {len(names)} "
                         f"photos in {folder.name}/")
    matrices = table[:, :15].reshape(-1, 3, 5)
    height, width, focal = matrices[0, :, 4]
    bounds = table[:, 15:].copy()
    w, h = image_size(root / names[0])
    scale = w / width
    if abs(h / height - scale) > 0.01 * scale:
        raise InputError(f"{root}: the photos are {w}x{h}, not a scaled {width:g}x{height:g} "
                         f"as {POSES_FILE} says")
    camera = checked_camera(str(root / POSES_FILE), w, h, focal * scale, focal * scale,
                            w / 2, h / 2)
    poses = np.zeros((len(table), 4, 4))
    poses[:, :3, :3] = np.stack([matrices[:, :, 1], -matrices[:, :, 0], matrices[:, :, 2]], -1)
    poses[:, :3, 3], poses[:, 3, 3] = matrices[:, :, 3], 1.0
    factor = 1.0 / (bounds.min() * BOUND_FACTOR)
    poses[:, :3, 3] *= factor
    splits = ["test" if i % HOLDOUT == 0 and len(names) > 1 else "train"
              for i in range(len(names))]
    return Frames(names, splits, recentre(poses), [camera], [Distortion()],
                  bounds=bounds * factor)


def recentre(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ``poses`` expressed in the frame of their mean pose (NeRF's
    ``recenter_poses``: the mean centre, the mean viewing direction as -z, the mean up as
    +y, made orthonormal)."""
    centre = poses[:, :3, 3].mean(0)
    back = _unit(poses[:, :3, 2].sum(0))
    right = _unit(np.cross(poses[:, :3, 1].sum(0), back))
    mean = np.eye(4)
    mean[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
    mean[:3, 3] = centre
    return np.linalg.inv(mean) @ poses


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _read_table(path: Path) -> np.ndarray:
    """(N, 17) float64 rows of ``poses_bounds.npy``, checked."""
    if path.stat().st_size > MAX_BYTES:
        raise InputError(f"{path} is larger than {MAX_BYTES >> 20} MB")
    try:
        table = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"cannot read {path}: {exc}") from None
    if table.ndim != 2 or table.shape[1] != 17 or not len(table) or table.dtype.kind not in "fi":
        raise InputError(f"{path} must hold an (N, 17) array of numbers, got {table.shape} "
                         f"{table.dtype}")
    table = table.astype(np.float64)
    if not np.isfinite(table).all():
        raise InputError(f"{path} holds NaN or infinity")
    hwf, bounds = table[:, :15].reshape(-1, 3, 5)[:, :, 4], table[:, 15:]
    if (hwf <= 0).any() or (bounds <= 0).any() or (bounds[:, 0] >= bounds[:, 1]).any():
        raise InputError(f"{path}: image sizes, focal lengths and near < far bounds must be "
                         "positive")
    return table


def _photos(root: Path) -> tuple[Path, list[str]]:
    """The photo folder (``images/``, else the one ``images_N``) and its photos' paths
    relative to ``root``, in name order."""
    folder = root / "images"
    if not folder.is_dir():
        scaled = sorted(p for p in root.iterdir() if p.is_dir() and re.fullmatch(r"images_\d+",
                                                                                 p.name))
        if len(scaled) != 1:
            raise InputError(f"{root} holds {POSES_FILE} but no images/ folder (and not one "
                             "images_N folder) of its photos")
        folder = scaled[0]
    names = [p.relative_to(root).as_posix() for p in files_in(folder, suffixes=IMAGE_SUFFIXES,
                                                                recursive=False)]
    return folder, names


LAYOUT = Layout(POSES_FILE, lambda root: (root / POSES_FILE).is_file(), read)
