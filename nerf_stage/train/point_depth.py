"""Where a capture's sparse points say its training rays end: the targets of a depth loss
(DS-NeRF, Deng et al., CVPR 2022) against the floaters and misplaced walls that photos
taken from few directions leave.

A capture's points file holds no tracks (which photos saw a point), so a point counts as
seen by a training view when it projects into the view in front of the camera and lies,
within ``TOLERANCE``, as near as the nearest point projecting into its cell of ``CELL`` x
``CELL`` pixels: points behind a nearer surface that has points of its own drop out.
"""

from __future__ import annotations

import numpy as np
import torch

from ..data.cameras import Intrinsics, project
from ..render.contraction import parameter, ray_interval
from ..render.march import box_intersection
from ..render.scene_box import SceneBox

CELL = 4  # pixels a side of the cells in which only the nearest points count as seen
TOLERANCE = 1.05  # a point counts as seen within this factor of its cell's nearest


def point_targets(points: np.ndarray, poses: np.ndarray, cameras: list[Intrinsics],
                  box: SceneBox) -> tuple[np.ndarray, np.ndarray]:
    """The training pixels on which a sparse point is seen, and where their rays should end.

    Parameters
    ----------
    points : (P, 3) world positions.
    poses : (N, 4, 4) camera-to-world of the training views (OpenGL axes), all of one size.
    cameras : N intrinsics.
    box : the run's scene box.

    Returns
    -------
    pixels : (Q,) int64 indices into the training pixels, view by view, row by row
        (``trainer._ray_bank``'s order).
    targets : (Q,) float32 the point's distance from the camera in the rays' marching
        parameter (``march.ray_interval``: the normalised distance in a bounded box, the
        contracted parameter beyond an unbounded scene's box, the distance in the NDC cube).
    """
    pixels, distances, origins, directions = [], [], [], []
    for view, (pose, camera) in enumerate(zip(poses, cameras)):
        offset = points - pose[:3, 3]
        x, y, depth = project(points, pose, camera)
        inside = (depth > 0) & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        column, row = x[inside].astype(np.int64), y[inside].astype(np.int64)
        distance = np.linalg.norm(offset[inside], axis=1)
        cell = (row // CELL) * (camera.width // CELL + 1) + column // CELL
        nearest = np.full(cell.max(initial=0) + 1, np.inf)
        np.minimum.at(nearest, cell, distance)
        seen = distance <= TOLERANCE * nearest[cell]
        pixels.append(view * camera.width * camera.height + row[seen] * camera.width
                      + column[seen])
        distances.append(distance[seen] / box.scale)
        origins.append(np.broadcast_to((pose[:3, 3] - box.centre) / box.scale, (seen.sum(), 3)))
        directions.append(offset[inside][seen] / distance[seen, None])
    pixels, distances = np.concatenate(pixels), np.concatenate(distances)
    if box.ndc is not None:  # how far along the ray in the NDC cube
        o, d = (torch.as_tensor(np.concatenate(a)) for a in (origins, directions))
        start, towards = box.ndc.rays(o, d)
        ends = box.ndc.from_box(o + torch.as_tensor(distances)[:, None] * d)
        distances = ((ends - start) * towards).sum(1).numpy()
    elif box.unbounded:  # beyond the box, the parameter of the contracted ray (disparity-like)
        _, exits = box_intersection(torch.as_tensor(np.concatenate(origins)),
                                    torch.as_tensor(np.concatenate(directions)),
                                    torch.ones(3, dtype=torch.float64))
        distances = parameter(torch.as_tensor(distances), ray_interval(exits)[2]).numpy()
    return pixels, distances.astype(np.float32)
