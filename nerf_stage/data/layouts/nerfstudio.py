"""nerfstudio's layout: one ``transforms.json`` with ``fl_x``, ``fl_y``, ``cx``, ``cy``,
``w``, ``h``, a lens (``camera_model`` OPENCV or OPENCV_FISHEYE with ``k1``-``k4``, ``p1``,
``p2``) and ``frames[]``, where a frame may carry its own camera and lens (of one image
size); splits from ``train_filenames``, ``val_filenames`` and ``test_filenames`` where the
file lists them, else every eighth frame held out, and the sparse points of
``ply_file_path``.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

import numpy as np

from palette_core.errors import InputError

from ..cameras import checked_camera
from ..distortion import Distortion
from ..points import read_points
from .common import (
    SPLITS,
    Frames,
    Layout,
    frame_path,
    frames_of,
    holdout,
    listing,
    load_json,
    number,
)

#: What a nerfstudio frame may set for itself (else the file's top level says it).
CAMERA_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_model", "k1", "k2", "k3", "k4",
               "p1", "p2")
#: nerfstudio's camera models -> our distortion models (``distortion.MODELS``).
MODELS = {"OPENCV": "opencv", "PINHOLE": "opencv", "SIMPLE_PINHOLE": "opencv",
          "OPENCV_FISHEYE": "fisheye"}


def read(root: Path, frames_outside: bool) -> Frames:
    """nerfstudio's layout: ``transforms.json``, a camera (and lens) per frame or for all."""
    path = root / "transforms.json"
    data = load_json(path)
    names, poses, off_ring = frames_of(data, path, "", frames_outside)
    if not names:
        raise InputError(f"{path} lists no frames")
    cameras, lenses = [], []
    for i, frame in enumerate(data["frames"]):
        own = {key: frame[key] for key in CAMERA_KEYS if key in frame}
        fields, where = {**data, **own}, f"{path}: frames[{i}]" if own else path
        cameras.append(checked_camera(
            str(where), number(fields, "w", where, int), number(fields, "h", where, int),
            number(fields, "fl_x", where), number(fields, "fl_y", where),
            number(fields, "cx", where), number(fields, "cy", where)))
        lenses.append(_lens(fields, where))
    sizes = {(camera.width, camera.height) for camera in cameras}
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
        raise InputError(f"{path}: frames of different image sizes ({listed}) are not supported")
    points = None
    if "ply_file_path" in data:
        if not isinstance(data["ply_file_path"], str):
            raise InputError(f"{path}: ply_file_path must be a file name")
        points = read_points(root / frame_path(data["ply_file_path"], f"{path}: ply_file_path",
                                                root, frames_outside))
    return Frames(names, _splits(data, names, path), np.array(poses), cameras,
                  lenses, np.array(off_ring), points)


def _lens(fields: dict, where) -> Distortion:
    """The distortion of a nerfstudio camera (``camera_model``, ``k1``-``k4``, ``p1``,
    ``p2``; OPENCV when no model is named, as nerfstudio reads it)."""
    name = fields.get("camera_model", "OPENCV")
    if not isinstance(name, str) or name not in MODELS:
        raise InputError(f"{where}: camera_model {name!r} is not supported (read: "
                         f"{', '.join(MODELS)}); undistort the photos first")
    coefficients = {key: fields.get(key, 0.0) for key in ("k1", "k2", "k3", "k4", "p1", "p2")}
    try:
        return Distortion(MODELS[name],
                          tuple(coefficients[f"k{i}"] for i in range(1, 5)),
                          (coefficients["p1"], coefficients["p2"]))
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _splits(data: dict, names: list[str], path: Path) -> list[str]:
    """The split of each frame: from nerfstudio's ``train_filenames``, ``val_filenames`` and
    ``test_filenames`` lists where the file has any, else every eighth frame held out
    (``_holdout``). A frame is in one list, or in ``val`` and ``test`` both (nerfstudio
    holds out its val views while training and its test views in ``ns-eval``; a capture
    made for both names the same held-out frames twice): then a test view."""
    lists = {split: data[f"{split}_filenames"] for split in SPLITS
             if f"{split}_filenames" in data}
    if not lists:
        return holdout(len(names))
    listed = {}
    for split, files in lists.items():
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            raise InputError(f"{path}: '{split}_filenames' must be a list of file paths")
        for name in files:
            name = PurePosixPath(os.path.normpath(name)).as_posix()
            before = listed.setdefault(name, split)
            if {before, split} == {"val", "test"}:
                listed[name] = "test"
            elif before != split:
                raise InputError(f"{path}: {name} is listed in two splits")
    unlisted = [name for name in names if name not in listed]
    if unlisted:
        raise InputError(f"{path}: frames in no split list: {listing(unlisted)}")
    return [listed[name] for name in names]


LAYOUT = Layout("transforms.json", lambda root: (root / "transforms.json").is_file(), read)
