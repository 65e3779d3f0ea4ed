"""Where a splat run's Gaussians start: the capture's sparse points in their colours (3D
Gaussian splatting's start), and splats where the training views look where there are no
points (``seen_splats``, ``uncovered``), each as wide as its neighbours allow.
docs/splats.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..data.cameras import Intrinsics, project
from ..data.points import Points
from ..render.contraction import distance, parameter
from ..render.march import box_intersection
from ..render.scene_box import SceneBox
from .sh import SH_C0, sh_terms

INITIAL_OPACITY = 0.1
#: At most one starting splat for this many pixels of a training image: more, at a low
#: opacity, all cover every pixel (hundreds of pairs a pixel on a tiny image).
PIXELS_PER_INITIAL = 4
MIN_POINTS = 4  # a capture with fewer sparse points starts at random
HULL_CELLS = 64  # along each side of the box: the visual hull that bounded scenes start in
HULL_TRIES = 32  # places along a starting splat's ray tried for one in the hull
#: A capture's sparse points leave parts of its views empty (sky, ground, a background
#: too plain or too far to match): splats start there too, where a view's cell, one of
#: this many along its longer side, holds no point (``uncovered``).
COVER_CELLS = 16
#: ... no nearer to the camera than this quantile of the depths of the points it sees.
COVER_NEAR = 0.1
#: Far splats start out to this many bends of a ray's marching parameter (``contraction``):
#: ten bends from the camera.
FAR_SHELL = 1.9
#: A starting splat has a standard deviation in its nearest training view of at most this
#: share of ``--splats-reach``: its ellipse to 1/255 (2.5 deviations at ``INITIAL_OPACITY``)
#: spans half the reach, so that none starts cut off square, nor covers every pixel of a
#: small view (docs/decisions/0011-splat-start.md).
START_REACH = 0.2

def initial_splats(box: SceneBox, n: int, degree: int, generator: torch.Generator,
                   views: SeenViews | None = None, points: Points | None = None,
                   eyes: np.ndarray | None = None, widest: float = math.inf) -> dict:
    """Splats to start from, ``INITIAL_OPACITY`` opaque, as wide as the mean distance to
    their three nearest neighbours, with colours of ``degree``: at most ``n`` of the
    capture's ``points`` in their colours (3D Gaussian splatting's start), else at most
    ``n`` where the training ``views`` look (``seen_splats``). With both, splats start
    where the ``views`` see no point, too (``uncovered``), as many for those pixels as
    the points are for the rest, at most ``n``. Starting splats may lie far apart (sparse
    points, far splats of an unbounded scene), so none is wider than ``widest`` times its
    distance to the nearest of the (N, 3) normalised camera centres ``eyes``."""
    if points is None:
        means, rgb = seen_splats(box, n, generator, views)
    else:
        pick = torch.randperm(len(points), generator=generator)[:n].numpy()
        means = torch.as_tensor((points.positions[pick] - box.centre) / box.scale,
                                dtype=torch.float32)
        rgb = torch.as_tensor(points.colours[pick], dtype=torch.float32)
        if views is not None:
            empty = uncovered(points, views)
            share = empty.alpha.sum() / max(1, (views.alpha >= 0.5).sum())
            extra = min(n, round(len(pick) * share / max(1 - share, 1 / len(pick))))
            if extra:
                far, far_rgb = seen_splats(box, extra, generator, empty)
                means, rgb = torch.cat([means, far]), torch.cat([rgb, far_rgb])
    colours = (rgb - 0.5) / SH_C0
    distance = cKDTree(means.numpy()).query(means.numpy(), k=4)[0][:, 1:].mean(1)
    if eyes is not None:
        distance = np.minimum(distance, widest * cKDTree(eyes).query(means.numpy())[0])
    scale = np.log(np.maximum(distance, 1e-7))
    n = len(means)
    return {"means": means, "scales": torch.as_tensor(scale, dtype=torch.float32)[:, None]
            .repeat(1, 3), "quats": torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
            "opacities": torch.full((n,), math.log(INITIAL_OPACITY / (1 - INITIAL_OPACITY))),
            "colours": colours, "colours_rest": torch.zeros(n, sh_terms(degree) - 1, 3)}


@dataclass
class SeenViews:
    """The training views a splat run starts from: N world ``poses``, their ``cameras``,
    (N, H, W, 3) ``images`` and (N, H, W) ``alpha``, the box's visual ``hull`` (X, Y, Z)
    where a bounded scene's images are partly transparent (None elsewhere), and the (N,)
    world distance from each camera within which no splat starts (``near``; None: 0)."""

    poses: np.ndarray
    cameras: list[Intrinsics]
    images: np.ndarray
    alpha: np.ndarray
    hull: np.ndarray | None = None
    near: np.ndarray | None = None


def uncovered(points: Points, views: SeenViews) -> SeenViews:
    """The opaque pixels (alpha at least a half) of ``views`` whose cell (``COVER_CELLS``
    along the view's longer side) no point in front of the camera falls in, as ``alpha``
    (N, H, W) bool, with ``near``: the ``COVER_NEAR`` quantile of the depths of the points
    each view sees (0 where it sees none)."""
    empty, near = views.alpha >= 0.5, np.zeros(len(views.poses))
    for i, (pose, camera) in enumerate(zip(views.poses, views.cameras)):
        x, y, depth = project(points.positions, pose, camera)
        seen = (depth > 0) & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        size = max(camera.width, camera.height) / COVER_CELLS
        covered = np.zeros((COVER_CELLS + 1, COVER_CELLS + 1), bool)
        covered[(y[seen] / size).astype(int), (x[seen] / size).astype(int)] = True
        empty[i] &= ~covered[np.ix_(((np.arange(camera.height) + 0.5) / size).astype(int),
                                    ((np.arange(camera.width) + 0.5) / size).astype(int))]
        near[i] = np.quantile(depth[seen], COVER_NEAR) if seen.any() else 0.0
    return replace(views, alpha=empty, near=near)


def seen_splats(box: SceneBox, n: int, generator: torch.Generator,
                views: SeenViews) -> tuple[torch.Tensor, torch.Tensor]:
    """(at most n, 3) positions and colours of splats where the training ``views`` look:
    each on the ray through a random point of an opaque pixel (alpha at least a half) of a
    random view, in that pixel's colour, at a uniform random place of the ray's marching
    parameter (``contraction``: linear in distance through the box, in disparity beyond it
    out to ``FAR_SHELL``, so that about half of them are far in an unbounded scene; within
    the ``hull`` where there is one, the first of ``HULL_TRIES`` places in it), beyond the
    view's ``near``. Rays that meet no box (or hull) start no splat, unless none does."""
    opaque = np.flatnonzero(views.alpha.reshape(-1) >= 0.5)
    if not len(opaque):
        opaque = np.arange(views.alpha.size)
    pick = opaque[torch.randint(len(opaque), (n,), generator=generator).numpy()]
    view, y, x = np.unravel_index(pick, views.alpha.shape)
    colours = torch.as_tensor(views.images[view, y, x], dtype=torch.float32)
    x = x + torch.rand(n, generator=generator).numpy()
    y = y + torch.rand(n, generator=generator).numpy()
    intrinsics = np.array([[c.fx, c.fy, c.cx, c.cy] for c in views.cameras])[view]
    local = np.stack([(x - intrinsics[:, 2]) / intrinsics[:, 0],
                      -(y - intrinsics[:, 3]) / intrinsics[:, 1], -np.ones(n)], 1)
    directions = np.einsum("nij,nj->ni", views.poses[view, :3, :3], local)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = (views.poses[view, :3, 3] - box.centre) / box.scale
    origins, directions = (torch.as_tensor(a, dtype=torch.float32) for a in (origins, directions))
    start = torch.as_tensor(0.0 if views.near is None else views.near[view] / box.scale,
                            dtype=torch.float32)
    if box.unbounded:
        _, exits = box_intersection(origins, directions, torch.ones(3))
        bend = exits.clamp(min=1.0)
        first = torch.minimum(parameter(start, bend), FAR_SHELL * bend)  # where u starts
        u = first + torch.rand(n, generator=generator) * (FAR_SHELL * bend - first)
        return origins + distance(u, bend)[:, None] * directions, colours
    extent = torch.as_tensor(box.extent, dtype=torch.float32)
    near, far = box_intersection(origins, directions, extent)
    near = torch.maximum(near, start)
    tries = 1 if views.hull is None else HULL_TRIES
    t = near[:, None] + torch.rand(n, tries, generator=generator) * (far - near)[:, None]
    hit = (far > near)[:, None].expand(n, tries)
    if views.hull is not None:
        cells = torch.as_tensor(views.hull.shape)
        unit = (origins[:, None] + t[..., None] * directions[:, None]) / extent * 0.5 + 0.5
        index = (unit * cells).long().clamp(torch.zeros(3, dtype=torch.long), cells - 1)
        hit = hit & torch.as_tensor(views.hull)[index.unbind(-1)]
    first = hit.float().argmax(1)  # the first place that is in (or 0 where none is)
    keep = hit.any(1) if hit.any() else torch.ones(n, dtype=torch.bool)  # none: keep all
    t = t.gather(1, first[:, None])[:, 0]
    return (origins + t[:, None] * directions)[keep], colours[keep]
