"""The occupancy grid: a coarse boolean grid over the normalised box whose empty cells are
never sampled, and the sphere tracing that skips them; it owns its update schedule.

References
----------
T. Mueller et al. Instant neural graphics primitives. SIGGRAPH 2022 (occupancy grid).
R. Li et al. NerfAcc. 2023 (``update_every_n_steps``).
J. C. Hart. Sphere tracing. The Visual Computer 12, 1996 (skipping empty space by its
distance to the nearest occupied cell).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import distance_transform_cdt
from torch import nn

from ..data.cameras import Intrinsics
from .contraction import ray_points
from .ndc import NDCFrame
from .scene_box import SceneBox, visual_hull

MAX_SKIPS = 16  # sphere-tracing steps across empty space before a ray is marched
OCCUPIED_ALPHA = 0.03  # a cell is occupied when one step through it is this opaque


class OccupancyGrid(nn.Module):
    """Coarse boolean grid over the normalised box: samples in empty cells are never evaluated.

    Starts from the visual hull of the training views; once the field has
    learned some density, ``update`` keeps the carved cells whose density (an
    exponential moving maximum over random points in each cell) makes one
    step through it at least ``OCCUPIED_ALPHA`` opaque, or as opaque as the mean
    cell while the density is still low everywhere. The grids are buffers:
    ``hull``, ``occupied`` and ``density`` are saved in ``state_dict``; ``extent``,
    ``resolution`` and the ``cell_*`` constants follow from the config and are not.
    A ``contracted`` grid covers an unbounded scene's contracted space (``contraction``);
    with an ``ndc`` frame, the NDC cube of a forward-facing scene (``ndc``), where rays are
    marched as in a box once they are mapped into it.
    """

    def __init__(self, extent: torch.Tensor, cells: int, contracted: bool = False,
                 ndc: NDCFrame | None = None):
        super().__init__()
        self.contracted = contracted
        self.ndc = ndc
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

    @classmethod
    def over(cls, box: SceneBox, cells: int) -> OccupancyGrid:
        """A grid of about ``cells`` cells over the space of ``box`` (its ``field_extent``)."""
        return cls(torch.as_tensor(box.field_extent, dtype=torch.float32), cells, box.unbounded,
                   box.ndc)

    def carve(self, box: SceneBox, poses: np.ndarray, intrinsics: list[Intrinsics],
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
        whole box when none is occupied; within the box when ``contracted``)."""
        extent, cells = self.extent.cpu(), torch.nonzero(self.occupied).cpu()
        low, high = -extent, extent
        if len(cells):
            size = 2 * extent / self.resolution.cpu()
            low = cells.min(0).values * size - extent
            high = (cells.max(0).values + 1) * size - extent
        bounds = torch.stack([low, high]).double().numpy()
        return np.clip(bounds, -1, 1) if self.contracted else bounds

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
            if self.contracted:  # no skipping in the shell, where steps are not distances
                free = free * self._inner_cells()
            self._cached = occupied, occupied._version, (padded.flatten(), free.flatten(), distance)
        return self._cached[2]

    def _inner_cells(self) -> torch.Tensor:
        """(X + 2, Y + 2, Z + 2) padded grid: 1 for the cells of a contracted grid inside the
        box [-1, 1]^3, else 0."""
        inside = []
        for n, e in zip(self.resolution.tolist(), self.extent.tolist()):
            centres = (torch.arange(n + 2, device=self.extent.device) - 0.5) * 2 * e / n - e
            inside.append(centres.abs() + e / n <= 1 + 1e-6)
        return (inside[0][:, None, None] & inside[1][None, :, None]
                & inside[2][None, None, :]).float()

    def skip_empty(self, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor,
                   far: torch.Tensor, step: float, bend: torch.Tensor | None = None
                   ) -> torch.Tensor:
        """(R,) entry distances ``near`` moved on by whole ``step``s across empty space, to
        within a cell of the first occupied cell on each ray (``far`` for rays that meet
        none): at a point d cells from the nearest occupied cell, a ray can move d - 1 cells
        before it can enter one (``free_distance``; sphere tracing on the occupancy grid).
        In a contracted grid, ``near`` and ``far`` are in the rays' marching parameter and
        ``bend`` (R,) is where it stops being the distance (``contraction``): rays skip only
        inside the box."""
        free = self._tables()[1]
        t = near
        for _ in range(MAX_SKIPS):
            # in a box: addcmul, as before contraction existed (box runs stay bit-identical)
            points = (torch.addcmul(origins, t[:, None], directions) if bend is None
                      else ray_points(origins, directions, t, bend))
            advance = free[self._cell(points)]
            t = t + advance if bend is None else torch.minimum(t + advance, t.maximum(bend))
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

    def update_every_n_steps(self, step: int, field, generator: torch.Generator,
                             every: int, warmup: int) -> None:
        """``update`` from ``field``'s density at training iteration ``step`` when it is past
        ``warmup`` and a multiple of ``every`` (the schedule of the field's settings)."""
        if step >= warmup and step % every == 0:
            self.update(field, field.sampling().step, generator)
