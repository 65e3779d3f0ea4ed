"""A capture's sparse points: where structure from motion saw the scene, in the capture's own
frame, the start that splats grow from (docs/capture.md, docs/splats.md).

A nerfstudio capture names them in ``transforms.json``'s ``ply_file_path`` (nerfstudio's
``sparse_pc.ply``: a PLY of vertices with ``red green blue``); a COLMAP model holds them as
``points3D`` (``colmap.model_points``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from palette_core.errors import InputError

POINTS_FILE = "sparse_pc.ply"  # nerfstudio's name
MAX_BYTES = 1 << 30  # a point file larger than this is refused before it is parsed


@dataclass(frozen=True)
class Points:
    """Points of a capture.

    Attributes
    ----------
    positions : (P, 3) float64
        In the frame of the capture's poses.
    colours : (P, 3) float32
        RGB in [0, 1].
    """

    positions: np.ndarray
    colours: np.ndarray

    def __post_init__(self):
        """InputError unless the shapes agree and every position and colour is finite: no
        reader hands on, and ``write_points`` never writes, what ``read_points`` refuses."""
        if (self.positions.ndim != 2 or self.positions.shape[1:] != (3,)
                or self.colours.shape != self.positions.shape):
            raise InputError(f"points need (P, 3) positions and colours, got "
                             f"{self.positions.shape} and {self.colours.shape}")
        if not (np.isfinite(self.positions).all() and np.isfinite(self.colours).all()):
            raise InputError("point positions and colours must be finite")

    def __len__(self) -> int:
        return len(self.positions)


def write_points(points: Points, path: str | os.PathLike) -> None:
    """``points`` as a binary PLY of vertices with colours (nerfstudio's ``sparse_pc.ply``)."""
    import trimesh

    colours = np.round(np.clip(points.colours, 0, 1) * 255).astype(np.uint8)
    trimesh.PointCloud(points.positions, colors=colours).export(str(path), file_type="ply")


def read_points(path: str | os.PathLike) -> Points:
    """The points of the PLY at ``path`` (grey where it has no colours).

    Raises
    ------
    InputError
        A file that is missing, larger than ``MAX_BYTES``, not a PLY of vertices, or holds a
        position that is not finite.
    """
    import trimesh

    path = Path(path)
    try:
        if path.stat().st_size > MAX_BYTES:
            raise InputError(f"{path}: a point file larger than {MAX_BYTES >> 20} MB")
        cloud = trimesh.load(str(path), file_type="ply", process=False)
        positions = np.asarray(cloud.vertices, np.float64).reshape(-1, 3)
    except InputError:
        raise
    except Exception as exc:  # trimesh's parser raises whatever a broken file provokes
        raise InputError(f"{path}: not a PLY of points ({type(exc).__name__})") from None
    if not np.isfinite(positions).all():
        raise InputError(f"{path}: point positions must be finite")
    colours = np.asarray(getattr(cloud, "colors", np.zeros((0, 4))), np.float32)
    if colours.shape[:1] != (len(positions),) or colours.ndim != 2 or colours.shape[1] < 3:
        colours = np.full((len(positions), 3), 127.5, np.float32)
    return Points(positions, colours[:, :3] / 255.0)
