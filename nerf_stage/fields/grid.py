"""The ``grid`` backbone: dense voxel grids read by a small MLP head (fast on CPUs).

References
----------
C. Sun, M. Sun, H.-T. Chen. Direct voxel grid optimization. CVPR 2022 (a density
grid, a feature grid and a small MLP).
"""

from __future__ import annotations

import torch
from torch import nn

from palette_core.basis import Basis
from palette_core.errors import InputError

from ..backbone_settings import GridConfig
from .base import RGB, Field, RaySampling, inverse_tone_map, positional_encoding, tone_map

MAX_BAKE_FACTOR = 4  # a baked table grows with the factor's cube
GRID_DENSITY_SHIFT = -4.0  # softplus(-4) ~ 0.02 per voxel: below the occupancy threshold


def _grid_density(raw: torch.Tensor, voxels_per_unit: float) -> torch.Tensor:
    """Interpolated raw grid values -> densities per unit length (activated after
    interpolation, so that a surface can sit inside a voxel)."""
    return nn.functional.softplus(raw + GRID_DENSITY_SHIFT) * voxels_per_unit


def _corners(x: torch.Tensor, extent: torch.Tensor, resolution: torch.Tensor,
             offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Trilinear interpolation of (P, 3) positions in the box [-extent, extent] on a grid of
    ``resolution`` vertices: (P, 8) flat vertex indices and (P, 8) weights; ``offsets`` are
    the (8, 3) corners of a cell, in the order of the weights' outer product."""
    u = (x + extent) / (2 * extent) * (resolution - 1)
    u = torch.minimum(torch.clamp(u, min=0), (resolution - 1).to(u.dtype))
    base = torch.minimum(u.floor().long(), resolution - 2)
    frac = u - base
    strides = torch.stack([resolution[1] * resolution[2], resolution[2], resolution[2] ** 0])
    index = (base * strides).sum(-1, keepdim=True) + (offsets * strides).sum(-1)
    w = torch.stack([1 - frac, frac], -1)  # (P, 3 axes, 2 ends)
    weight = w[:, 0, :, None, None] * w[:, 1, None, :, None] * w[:, 2, None, None, :]
    return index, weight.reshape(-1, 8)


def _drop_feature_rows(field: GridField, *args) -> None:
    """Load hook of ``GridField``: loading copies into the grids in place, so the row-major
    copy of ``_feature_rows`` must be made again."""
    field._rows = None


def _interpolate_rows(table: torch.Tensor, index: torch.Tensor, weight: torch.Tensor):
    """(N, C) table, (P, 8) corner indices and weights -> (P, C) weighted sums of the rows."""
    corners = table.index_select(0, index.reshape(-1)).view(*index.shape, table.shape[1])
    return torch.einsum("pk,pkc->pc", weight, corners)


class _Trilinear(torch.autograd.Function):
    """Channels-first (C, N) table, (P, 8) corner indices and weights -> (P, C) weighted sums
    of the table's columns.

    The backward scatters into a (C, N) buffer with ``index_add_``, which is the table's own
    layout, so that the gradient needs no transposing copy
    (docs/decisions/0004-channels-first-grids.md measures it against an (N, C) table and
    ``embedding``). Positions get no gradient. Renders gather rows instead
    (``GridField._feature_rows``)."""

    @staticmethod
    def forward(ctx, table, index, weight):
        ctx.save_for_backward(index, weight)
        ctx.columns = table.shape[1]
        corners = table.index_select(1, index.reshape(-1)).view(table.shape[0], *index.shape)
        return torch.einsum("pk,cpk->pc", weight, corners)

    @staticmethod
    def backward(ctx, grad):
        index, weight = ctx.saved_tensors
        channels = grad.shape[1]
        scattered = (grad.t().contiguous()[..., None] * weight).view(channels, -1)  # (C, P 8)
        rows = index.reshape(-1).long()  # int32 rows (hash levels) scatter far slower
        table = grad.new_zeros(channels, ctx.columns).index_add_(1, rows, scattered)
        return table, None, None


class GridField(Field):
    """Dense voxel grids over the scene box: density (the density part), and colour features
    read by a small MLP of ``head_layers`` hidden layers of ``head_width`` (the colour part).

    Both grids are read at the same eight corners of each sample (trilinear
    interpolation as a gather, which is faster on CPUs than ``grid_sample``); the
    density part returns the interpolated features as ``h``.

    Parameters
    ----------
    extent : (3,) float
        Half sizes of the normalised scene box (the largest is 1).
    settings : backbones.GridConfig
        Voxels (about this many, cubic, spread over the box), feature channels, the
        head's view encoding and layers, deferred shading, and the ray-marching steps.

    Examples
    --------
    >>> from palette_core.basis import Basis
    >>> settings = GridConfig(voxels=1000, features=4)
    >>> field = GridField([1.0, 0.5, 1.0], settings, kind=Basis.TRANSPORT, channels=6)
    >>> field.resolution.tolist()
    [13, 6, 13]
    >>> sigma, h = field.density(torch.zeros(2, 3))
    >>> bool((field.colour(h, torch.tensor([[1.0, 0.0, 0.0]] * 2)) >= 0).all())
    True
    """

    refines_occupancy = True

    def __init__(self, extent, settings: GridConfig | None = None, head_width: int = 128,
                 kind: str = RGB, channels: int = 3):
        super().__init__()
        self.settings = settings = settings or GridConfig()
        voxels, features = settings.voxels, settings.features
        direction_frequencies, head_layers = settings.view_frequencies, settings.head_layers
        extent = torch.as_tensor(extent, dtype=torch.float32)
        per_unit = (voxels / float(torch.prod(2 * extent))) ** (1 / 3)
        self.register_buffer("extent", extent)
        self.register_buffer("CORNERS", torch.tensor(
            [[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)]), persistent=False)
        self.register_buffer("resolution", torch.clamp(torch.round(2 * extent * per_unit), 2)
                             .to(torch.int64))
        self.voxels_per_unit = per_unit
        self.head_width = head_width
        self.direction_frequencies = direction_frequencies
        self.deferred = settings.deferred
        n = int(torch.prod(self.resolution))
        self.density_grid = nn.Parameter(torch.zeros(1, n))  # (C, N) tables of ``_Trilinear``
        self.feature_grid = nn.Parameter(torch.zeros(features, n))
        self._register_load_state_dict_pre_hook(_drop_feature_rows, with_module=True)
        self._rows, self._rows_of = None, None  # ``_feature_rows``
        n_direction = 0 if direction_frequencies is None else 3 * (1 + 2 * direction_frequencies)
        self.hidden = nn.Linear(features + n_direction, head_width)
        self.deeper = nn.ModuleList(nn.Linear(head_width, head_width)
                                    for _ in range(head_layers - 1))
        self._init_output(kind, channels)

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Densities, and as ``h`` the (P, features) colour features read at the same corners."""
        raw, features = self.read(x)
        return _grid_density(raw, self.voxels_per_unit), features

    def read(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(P,) raw density and (P, features) colour features, trilinear at (P, 3) positions."""
        index, weight = _corners(x, self.extent, self.resolution, self.CORNERS)
        raw = _Trilinear.apply(self.density_grid, index, weight)[:, 0]  # (1, N) is also (N, 1)
        if self.training or torch.is_grad_enabled():
            return raw, _Trilinear.apply(self.feature_grid, index, weight)
        return raw, _interpolate_rows(self._feature_rows(), index, weight)

    def _feature_rows(self) -> torch.Tensor:
        """The feature grid as an (N, C) copy for reads in eval mode without gradients
        (renders: a gather of rows is faster, docs/decisions/0004-channels-first-grids.md); made at
        the first such read, dropped by ``train()`` and loading, made again after a move."""
        if self._rows is None or self._rows_of != self.feature_grid.data_ptr():
            self._rows = self.feature_grid.detach().t().contiguous()
            self._rows_of = self.feature_grid.data_ptr()
        return self._rows

    def train(self, mode: bool = True) -> GridField:
        if mode:
            self._rows = None
        return super().train(mode)

    def head(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        if self.direction_frequencies is not None:
            h = torch.cat([h, positional_encoding(d, self.direction_frequencies)], dim=-1)
        h = nn.functional.relu(self.hidden(h), inplace=True)
        for layer in self.deeper:
            h = nn.functional.relu(layer(h), inplace=True)
        return h

    def density_parameters(self) -> list[nn.Parameter]:
        return [self.density_grid]

    def colour_parameters(self) -> list[nn.Parameter]:
        return [self.feature_grid, *self.hidden.parameters(),
                *self.deeper.parameters(), *self.output.parameters()]

    def grid_parameters(self) -> list[nn.Parameter]:
        return [self.density_grid, self.feature_grid]

    def sampling(self, render: bool = False) -> RaySampling:
        grid = self.settings
        return RaySampling(step=(grid.render_step_voxels if render else grid.step_voxels)
                           / self.voxels_per_unit)

    @torch.no_grad()
    def baked(self, occupancy, factor: int) -> BakedGrid:
        if self.deferred or self.direction_frequencies is not None:
            raise InputError("only a grid run with per-sample diffuse colours can be baked "
                             "(trained with the grid's deferred shading off and no view "
                             "frequencies); a deferred head renders from the grids at about "
                             "the baked speed")
        if not 1 <= factor <= MAX_BAKE_FACTOR:
            raise InputError(f"the bake factor must be in [1, {MAX_BAKE_FACTOR}], got {factor}")
        return BakedGrid(self, occupancy, factor)



class BakedGrid(nn.Module):
    """A ``GridField`` with its colour part evaluated once, at the vertices of a grid
    ``factor`` times as fine, near the occupied cells.

    Rendering reads density and the C outputs from one (V, 1 + C) table at the eight
    corners of a sample and runs no network. The finer grid reproduces the field's
    trilinear density exactly (its vertices divide the field's cells) and samples the
    non-linear colour part ``factor`` times more finely (its error falls with
    ``factor``, its memory grows with the cube). Outputs are interpolated after their
    activation, so baked additive weights still sum to one; transport weights are
    interpolated tone-mapped (``base.tone_map``), so that a lamp's radiance does not
    bleed into its neighbours. Only vertices within reach of an occupied cell are kept
    (``slot`` maps the fine grid's vertices to table rows). Has the ``density`` /
    ``colour`` / ``sampling`` of a field, nothing to train.
    """

    deferred = False

    def __init__(self, field: GridField, occupancy, factor: int):
        super().__init__()
        self.kind = field.kind
        self.tone_mapped = field.kind == Basis.TRANSPORT
        fine = factor * (field.resolution - 1) + 1
        cell = 2 * field.extent / (fine - 1)
        margin = int(torch.ceil((cell * occupancy.resolution / (2 * occupancy.extent)).max()))
        near = occupancy.dilated(margin)
        for axis, (n, cells) in enumerate(zip(fine.tolist(), occupancy.resolution.tolist())):
            cell_of_vertex = torch.arange(n, device=fine.device) * cells // (n - 1)
            near = near.index_select(axis, cell_of_vertex.clamp(max=cells - 1))
        ijk = torch.nonzero(near)  # (V, 3) fine vertices within reach of an occupied cell
        rows = []
        for chunk in ijk.split(1 << 16):
            raw, features = field.read(-field.extent + chunk * cell)
            outputs = field.colour(features, None)
            if self.tone_mapped:
                outputs = tone_map(outputs)
            rows.append(torch.cat([raw[:, None], outputs], 1))
        empty = torch.zeros(1, 1 + field.output.out_features, device=fine.device)
        empty[0, 0] = -GRID_DENSITY_SHIFT - 30  # never read: empty space
        self.register_buffer("table", torch.cat([*rows, empty]))  # (V + 1, 1 + C)
        slot = torch.full(near.shape, len(ijk), dtype=torch.int32, device=fine.device)
        slot[tuple(ijk.t())] = torch.arange(len(ijk), dtype=torch.int32, device=fine.device)
        self.register_buffer("slot", slot.flatten())
        self.register_buffer("extent", field.extent)
        self.register_buffer("resolution", fine)
        self.register_buffer("CORNERS", field.CORNERS)
        self.voxels_per_unit = field.voxels_per_unit
        self.settings = field.settings

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Densities and, as ``h``, the (P, C) outputs read at the same corners."""
        index, weight = _corners(x, self.extent, self.resolution, self.CORNERS)
        both = _interpolate_rows(self.table, self.slot[index], weight)
        return _grid_density(both[:, 0], self.voxels_per_unit), both[:, 1:]

    def colour(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        return inverse_tone_map(h) if self.tone_mapped else h

    sampling = GridField.sampling
