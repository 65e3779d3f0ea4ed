"""Rays, empty-space skipping and volume compositing of M channels.

Compositing does not care whether a sample carries 3 colour channels or M palette
weights: ``composite`` gives each sample its weight T_i alpha_i, and
``render_rays`` sums weight x value per ray. Weight renders come out premultiplied
by the accumulated opacity; a colour is ``weights @ basis + (1 - acc) background``.

All positions live in the normalised scene box of ``SceneBox``.

References
----------
B. Mildenhall et al. NeRF. ECCV 2020, eq. 3 (quadrature of the volume rendering integral).
T. Mueller et al. Instant neural graphics primitives. SIGGRAPH 2022 (occupancy grid).
J. C. Hart. Sphere tracing. The Visual Computer 12, 1996 (skipping empty space by its
distance to the nearest occupied cell).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import distance_transform_cdt, maximum_filter
from torch import nn

from .cameras import Intrinsics
from .fields.base import RaySampling

TERMINATION = 1e-4  # samples behind less transmittance skip the colour part
SEGMENT = 32  # samples a ray marched at a time, between checks for termination (rendering)
MAX_SKIPS = 16  # sphere-tracing steps across empty space before a ray is marched
CARVE_ALPHA = 0.01  # a pixel below this alpha (after dilation) shows empty space
OCCUPIED_ALPHA = 0.03  # a cell is occupied when one step through it is this opaque


@dataclass
class SceneBox:
    """Axis-aligned box around the scene; positions are normalised as (x - centre) / scale.

    Attributes
    ----------
    centre : (3,) float
    half : (3,) float
        World half sizes.
    """

    centre: np.ndarray
    half: np.ndarray

    @property
    def scale(self) -> float:
        return float(np.max(self.half))

    @property
    def extent(self) -> np.ndarray:
        """(3,) half sizes of the normalised box (the largest is 1)."""
        return self.half / self.scale

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "half": self.half.tolist()}


def scene_box(poses: np.ndarray, intrinsics: Intrinsics, alpha: np.ndarray,
              resolution: int = 64) -> SceneBox:
    """A box around what the cameras see.

    Starts from the cube around the point nearest to all optical axes, with half
    size 0.75 x the nearest camera's distance; when the images have transparent
    pixels, shrinks it to the visual hull carved from them.
    """
    axes = -poses[:, :3, 2]
    eyes = poses[:, :3, 3]
    projector = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # (N, 3, 3)
    centre = np.linalg.lstsq(projector.sum(0), np.einsum("nij,nj->i", projector, eyes),
                             rcond=None)[0]
    half = 0.75 * np.linalg.norm(eyes - centre, axis=1).min()
    box = SceneBox(centre, np.full(3, half))
    if alpha.min() >= CARVE_ALPHA:
        return box
    cells = np.argwhere(visual_hull(box, np.full(3, resolution), poses, intrinsics, alpha))
    if len(cells) == 0:
        return box
    cell = 2 * half / resolution
    lo = centre - half + (cells.min(0) - 1) * cell
    hi = centre - half + (cells.max(0) + 2) * cell
    lo, hi = np.maximum(lo, centre - half), np.minimum(hi, centre + half)
    return SceneBox((lo + hi) / 2, (hi - lo) / 2)


def visual_hull(box: SceneBox, resolution: np.ndarray, poses: np.ndarray,
                intrinsics: Intrinsics, alpha: np.ndarray) -> np.ndarray:
    """(X, Y, Z) bool: cells of ``box`` that no view shows as transparent.

    A cell is carved when its centre projects inside a view onto a pixel whose
    alpha, dilated by the cell's footprint in that view, is below ``CARVE_ALPHA``.
    """
    axes = [np.linspace(-1, 1, n, endpoint=False) + 1 / n for n in resolution]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    points = box.centre + grid * box.half
    keep = np.ones(len(points), bool)
    radius = 0.5 * float(np.linalg.norm(2 * box.half / resolution))  # of a cell's bounding ball
    for pose, mask in zip(poses, alpha):
        local = (points - pose[:3, 3]) @ pose[:3, :3]
        depth = -local[:, 2]
        ahead = depth > radius
        safe = np.where(ahead, depth, 1.0)
        u = intrinsics.cx + intrinsics.fx * local[:, 0] / safe
        v = intrinsics.cy - intrinsics.fy * local[:, 1] / safe
        inside = ahead & (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
        ui = np.clip(u.astype(np.int64), 0, intrinsics.width - 1)
        vi = np.clip(v.astype(np.int64), 0, intrinsics.height - 1)
        footprint = np.ceil(intrinsics.fx * radius / safe).astype(np.int64)  # pixels
        carved = np.zeros(len(points), bool)
        for pixels in np.unique(footprint[inside]):
            dilated = maximum_filter(mask, size=2 * int(pixels) + 1)
            at = inside & (footprint == pixels)
            carved[at] = dilated[vi[at], ui[at]] < CARVE_ALPHA
        keep &= ~carved
    return keep.reshape(tuple(resolution))


def box_intersection(origins: torch.Tensor, directions: torch.Tensor, extent: torch.Tensor):
    """Entry and exit distances (R,) of rays through the box [-extent, extent]; near = far
    where a ray misses it."""
    inverse = 1.0 / torch.where(directions.abs() < 1e-9, torch.full_like(directions, 1e-9),
                                directions)
    t0, t1 = (-extent - origins) * inverse, (extent - origins) * inverse
    near = torch.clamp(torch.minimum(t0, t1).amax(-1), min=0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, torch.maximum(far, near)


class OccupancyGrid(nn.Module):
    """Coarse boolean grid over the normalised box: samples in empty cells are never evaluated.

    Starts from the visual hull of the training views; once the field has
    learned some density, ``update`` keeps the carved cells whose density (an
    exponential moving maximum over random points in each cell) makes one
    step through it at least ``OCCUPIED_ALPHA`` opaque, or as opaque as the mean
    cell while the density is still low everywhere. The grids are buffers:
    ``hull``, ``occupied`` and ``density`` are saved in ``state_dict``; ``extent``,
    ``resolution`` and the ``cell_*`` constants follow from the config and are not.
    """

    def __init__(self, extent: torch.Tensor, cells: int):
        super().__init__()
        per_unit = (cells / float(torch.prod(2 * extent))) ** (1 / 3)
        resolution = torch.clamp(torch.round(2 * extent * per_unit), 1).long()
        shape = tuple(resolution.tolist())
        self.register_buffer("extent", extent, persistent=False)
        self.register_buffer("resolution", resolution, persistent=False)
        self.register_buffer("hull", torch.ones(shape, dtype=torch.bool))
        self.register_buffer("occupied", self.hull.clone())
        self.register_buffer("density", torch.zeros(shape))
        # _cell: point -> cell index in the lookup tables, padded by an empty cell a side
        scale, size = resolution / (2 * extent), resolution + 2
        strides = torch.stack([size[1] * size[2], size[2], size[2] ** 0])
        self.register_buffer("cell_scale", scale.float(), persistent=False)
        self.register_buffer("cell_shift", (extent * scale + 1).float(), persistent=False)
        self.register_buffer("cell_last", (resolution + 1).float(), persistent=False)
        self.register_buffer("cell_strides", strides.float(), persistent=False)

    def carve(self, box: SceneBox, poses: np.ndarray, intrinsics: Intrinsics,
              alpha: np.ndarray) -> None:
        """Start from the visual hull of views (``visual_hull``) at this grid's resolution."""
        self.hull = torch.as_tensor(visual_hull(box, self.resolution.cpu().numpy(), poses,
                                                intrinsics, alpha), device=self.extent.device)
        self.occupied = self.hull.clone()

    @property
    def cell(self) -> float:
        """Largest cell size in normalised units."""
        return float((2 * self.extent / self.resolution).max())

    def bounds(self) -> np.ndarray:
        """(2, 3) lowest and highest corner of the occupied cells, normalised units (the
        whole box when none is occupied)."""
        extent, cells = self.extent.cpu(), torch.nonzero(self.occupied).cpu()
        low, high = -extent, extent
        if len(cells):
            size = 2 * extent / self.resolution.cpu()
            low = cells.min(0).values * size - extent
            high = (cells.max(0).values + 1) * size - extent
        return torch.stack([low, high]).double().numpy()

    def dilated(self, margin: int) -> torch.Tensor:
        """(X, Y, Z) bool: the cells within ``margin`` cells of an occupied one."""
        return nn.functional.max_pool3d(self.occupied[None, None].float(), 2 * margin + 1, 1,
                                        margin)[0, 0].bool()

    def free_distance(self) -> torch.Tensor:
        """(X, Y, Z) float: chessboard distance of each cell to the nearest occupied one, in
        cells (0 when occupied; more than any ray crosses when none is)."""
        return self._tables()[2][1:-1, 1:-1, 1:-1]

    def _tables(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat tables over the padded grid, indexed by ``_cell``: whether each cell is
        occupied, and how far a ray can move from any point in it without entering an
        occupied cell (d - 1 cells at chessboard distance d, normalised units); and the
        padded ``free_distance``. Computed again only when ``occupied`` has changed."""
        occupied = self.occupied
        cached = getattr(self, "_cached", None)
        if cached is None or cached[0] is not occupied or cached[1] != occupied._version:
            padded = torch.zeros(tuple(s + 2 for s in occupied.shape), dtype=torch.bool,
                                 device=occupied.device)
            padded[1:-1, 1:-1, 1:-1] = occupied
            empty = ~padded.cpu().numpy()
            distance = torch.as_tensor(
                distance_transform_cdt(empty, metric="chessboard").astype(np.float32)
                if not empty.all() else np.full(empty.shape, sum(empty.shape), np.float32),
                device=occupied.device)
            cell = float((2 * self.extent / self.resolution).min())
            free = (distance - 1).clamp(min=0) * cell
            self._cached = occupied, occupied._version, (padded.flatten(), free.flatten(), distance)
        return self._cached[2]

    def skip_empty(self, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor,
                   far: torch.Tensor, step: float) -> torch.Tensor:
        """(R,) entry distances ``near`` moved on by whole ``step``s across empty space, to
        within a cell of the first occupied cell on each ray (``far`` for rays that meet
        none): at a point d cells from the nearest occupied cell, a ray can move d - 1 cells
        before it can enter one (``free_distance``; sphere tracing on the occupancy grid)."""
        free = self._tables()[1]
        t = near
        for _ in range(MAX_SKIPS):
            advance = free[self._cell(torch.addcmul(origins, t[:, None], directions))]
            t = t + advance
            if not bool((advance > 0).any()):
                break
        whole = torch.floor((torch.minimum(t, far) - near) / step) * step
        return torch.where(t < far, near + whole, far)

    def lookup(self, x: torch.Tensor) -> torch.Tensor:
        """(...) bool: (..., 3) points inside the box and in an occupied cell."""
        return self._tables()[0][self._cell(x)]

    def _cell(self, x: torch.Tensor) -> torch.Tensor:
        """(...) flat index into ``_tables`` of the cell of each of (..., 3) points; points
        outside the box fall into the padding."""
        padded = torch.floor(torch.addcmul(self.cell_shift, x, self.cell_scale))
        return (torch.minimum(padded.clamp_(min=0), self.cell_last) @ self.cell_strides).long()

    @torch.no_grad()
    def update(self, field, step: float, generator: torch.Generator, decay: float = 0.95) -> None:
        cells = torch.nonzero(self.hull)
        size = 2 * self.extent / self.resolution
        jitter = torch.rand(cells.shape, generator=generator, device=cells.device)
        points = -self.extent + (cells + jitter) * size
        sigma = torch.cat([field.density(chunk)[0] for chunk in points.split(1 << 16)])
        current = self.density[self.hull]
        self.density[self.hull] = torch.maximum(current * decay, sigma)
        alpha = 1 - torch.exp(-self.density * step)
        threshold = min(OCCUPIED_ALPHA, float(alpha[self.hull].mean()))
        self.occupied = self.hull & (alpha >= threshold)


def composite(sigma: torch.Tensor, deltas: torch.Tensor,
              depth: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample weights T_i alpha_i and transmittances T_i, both (R, S), from densities and
    step lengths (NeRF eq. 3); ``depth`` (R,) is the optical depth in front of the first
    sample (0 by default).

    Examples
    --------
    >>> composite(torch.tensor([[0.0, 1e9, 1e9]]), torch.ones(1, 3))[0]
    tensor([[0., 1., 0.]])
    """
    optical = sigma * deltas
    before = torch.cumsum(torch.cat([torch.zeros_like(optical[:, :1]), optical[:, :-1]], dim=1),
                          dim=1)
    if depth is not None:
        before = before + depth[:, None]
    transmittance = torch.exp(-before)
    return transmittance * (1 - torch.exp(-optical)), transmittance


@dataclass
class Samples:
    """Samples along a batch of rays that fall in occupied cells, packed.

    Attributes
    ----------
    ray : (P,) int64
        The ray of each sample.
    h : (P, ...)
        The density part's output for the colour part.
    weight : (P,)
        Compositing weight T_i alpha_i.
    transmittance : (P,)
    optical : (P,)
        Optical thickness sigma x step of each sample's step.
    opacity : (R,)
        Accumulated opacity of each ray.
    """

    ray: torch.Tensor
    h: torch.Tensor
    weight: torch.Tensor
    transmittance: torch.Tensor
    optical: torch.Tensor
    opacity: torch.Tensor

    def visible(self) -> Samples:
        """The samples in front of ``TERMINATION`` transmittance (the others skip the colour
        part)."""
        keep = self.transmittance.detach() > TERMINATION
        return Samples(self.ray[keep], self.h[keep], self.weight[keep],
                       self.transmittance[keep], self.optical[keep], self.opacity)

    def composite(self, values: torch.Tensor) -> torch.Tensor:
        """(P, C) per-sample values -> (R, C) composited along the rays."""
        out = torch.zeros(len(self.opacity), values.shape[-1], device=values.device,
                          dtype=values.dtype)
        return out.index_add(0, self.ray, self.weight[:, None] * values)

    def colour_inputs(self, directions: torch.Tensor,
                      deferred: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the colour part runs: each sample's ``h`` and its ray's direction, or, when
        ``deferred``, once a ray: its ``h`` composited and divided by its opacity, and its
        (R, 3) ``directions`` (deferred shading, Hedman et al. Baking neural radiance
        fields for real-time view synthesis. ICCV 2021)."""
        if not deferred:
            return self.h, directions[self.ray]
        opacity = self.opacity.detach().clamp(min=TERMINATION)[:, None]
        return self.composite(self.h) / opacity, directions

    def composite_colours(self, values: torch.Tensor, deferred: bool) -> torch.Tensor:
        """The colour part's outputs at ``colour_inputs`` -> (R, C) composited along the rays
        (premultiplied by opacity)."""
        return self.opacity[:, None] * values if deferred else self.composite(values)


def march_rays(field, occupancy: OccupancyGrid, origins: torch.Tensor, directions: torch.Tensor,
               sampling: RaySampling, generator: torch.Generator | None = None) -> Samples:
    """Sample rays and run the density part where the occupancy grid is occupied.

    Samples are spaced ``sampling.step`` apart from where a ray enters the box
    (grids), or ``sampling.count`` evenly across the box (MLPs); ``generator``
    jitters them (training). Stepped rays start marching in whole steps past the empty
    space in front of them (``OccupancyGrid.skip_empty``), so their samples stay where
    they were; samples in empty cells skip the field. Without gradients (rendering),
    rays are marched ``SEGMENT`` samples at a time, a ray whose transmittance has
    fallen below ``TERMINATION`` is not marched further (early ray termination), and
    stepped rays skip empty space again after each segment (past a floater to the
    surface behind it); with gradients, in one pass (each pass of a grid backbone
    costs a backward over its whole grids).

    Parameters
    ----------
    origins, directions : (R, 3)
        Normalised coordinates; unit directions.
    """
    near, far = box_intersection(origins, directions, occupancy.extent)
    if sampling.step is None:
        n_samples = sampling.count
        deltas = (far - near) / n_samples  # (R,)
    else:
        near = occupancy.skip_empty(origins, directions, near, far, sampling.step)
        n_samples = max(1, int(torch.ceil((far - near).max() / sampling.step)))
        deltas = torch.full_like(near, sampling.step)
    jitter = (torch.full_like(near[:, None], 0.5) if generator is None else
              torch.rand(len(near), 1, generator=generator, device=near.device))
    depth = torch.zeros_like(near)  # optical depth marched so far
    first = torch.zeros_like(near)  # each ray's next sample, counted in steps from near
    alive = torch.arange(len(near), device=near.device)
    parts = []
    segment = n_samples if torch.is_grad_enabled() else min(SEGMENT, n_samples)
    offsets = torch.arange(segment, device=near.device, dtype=near.dtype)
    while True:
        enter, step, leave = near[alive, None], deltas[alive, None], far[alive, None]
        t = enter + (first[alive, None] + offsets + jitter[alive]) * step  # (A, S)
        points = origins[alive, None] + t[..., None] * directions[alive, None]  # (A, S, 3)
        valid = (t < leave) & occupancy.lookup(points)
        row, sample = torch.nonzero(valid, as_tuple=True)
        sigma_packed, h = field.density(points[row, sample])
        sigma = torch.zeros_like(t).index_put((row, sample), sigma_packed)
        weights, transmittance = composite(sigma, step.expand_as(t), depth[alive])
        parts.append((alive[row], h, weights[row, sample], transmittance[row, sample],
                      sigma_packed * step[row, 0]))
        depth = depth.index_add(0, alive, (sigma * step).sum(1))
        first[alive] += segment
        at = near[alive] + first[alive] * deltas[alive]
        alive = alive[(depth[alive].detach() < -math.log(TERMINATION)) & (at < far[alive])]
        if sampling.step is not None and len(alive) and segment < n_samples:
            at = near[alive] + first[alive] * sampling.step  # across empty space again
            moved = occupancy.skip_empty(origins[alive], directions[alive], at, far[alive],
                                         sampling.step)
            first[alive] += torch.round((moved - at) / sampling.step)
            alive = alive[moved < far[alive]]
        if len(alive) == 0:
            break
    ray, h, weight, transmittance, optical = (torch.cat(part) for part in zip(*parts))
    return Samples(ray, h, weight, transmittance, optical, 1 - torch.exp(-depth))


def render_rays(field, occupancy: OccupancyGrid, origins: torch.Tensor,
                directions: torch.Tensor, sampling: RaySampling,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, Samples]:
    """Composite the field's outputs along rays (``march_rays``); samples behind
    ``TERMINATION`` transmittance skip the colour part (``Samples.visible``), which runs
    on each sample or, for a ``deferred`` field, once a ray (``Samples.colour_inputs``).

    Returns
    -------
    values : (R, C)
        Composited outputs, premultiplied by opacity.
    samples : Samples
        All the rays' samples in occupied cells; ``samples.opacity`` (R,) is the
        accumulated opacity.
    """
    samples = march_rays(field, occupancy, origins, directions, sampling, generator)
    visible = samples.visible()
    values = field.colour(*visible.colour_inputs(directions, field.deferred))
    return visible.composite_colours(values, field.deferred), samples
