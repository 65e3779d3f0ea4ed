"""NeRF's synthetic (Blender) layout: ``transforms_{train,val,test}.json`` with
``camera_angle_x`` and ``frames[]`` (``file_path`` without or with suffix,
``transform_matrix`` camera-to-world, OpenGL axes), as ``nerf-stage simulate`` writes it;
a frame with ``"off_ring": true`` is a test view away from the training cameras.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.io import image_size

from ..cameras import checked_camera, focal_length
from ..distortion import Distortion
from .common import SPLITS, Frames, Layout, frames_of, load_json, number


def read(root: Path, frames_outside: bool) -> Frames:
    """NeRF's synthetic layout: ``transforms_{train,val,test}.json``, one camera."""
    names, splits, poses, angle, off_ring = [], [], [], None, []
    for split in SPLITS:
        path = root / f"transforms_{split}.json"
        if not path.is_file():
            continue
        data = load_json(path)
        split_angle = number(data, "camera_angle_x", path)
        if angle is not None and abs(split_angle - angle) > 1e-9:
            raise InputError(f"{path}: camera_angle_x {split_angle} differs from the train split's")
        angle = split_angle
        split_names, split_poses, split_off = frames_of(data, path, ".png", frames_outside)
        names += split_names
        poses += split_poses
        off_ring += split_off
        splits += [split] * len(split_names)
    if not names:
        raise InputError(f"{root}: the transforms files list no frames")
    width, height = image_size(root / names[0])
    focal = focal_length(width, angle)
    camera = checked_camera(str(root / "transforms_train.json"), width, height, focal, focal,
                            width / 2, height / 2)
    return Frames(names, splits, np.array(poses), [camera], [Distortion()], np.array(off_ring))


LAYOUT = Layout("transforms_train.json", lambda root: (root / "transforms_train.json").is_file(),
                read)
