"""Radiance-field backbones with a density part and a colour part.

Both backbones take positions in the normalised scene box (``SceneBox``) and
expose the same split:

- ``density(x) -> (sigma, h)``: the density part. ``sigma`` (P,) is per unit of
  normalised length; ``h`` is whatever the colour part needs at x.
- ``colour(h, d) -> (P, C)``: the colour part, ending in the output layer and its
  activation: ``sigmoid`` for RGB, ``softmax`` for additive weights (they sum to
  one), ``softplus`` for transport weights (non-negative).

``set_output(kind, channels)`` puts in a new output layer, as the paper's
fine-tuning stage does; ``density_parameters`` and ``colour_parameters`` split the
parameters so the density part can be frozen.

References
----------
B. Mildenhall et al. NeRF: Representing scenes as neural radiance fields for view
synthesis. ECCV 2020 (the ``mlp`` backbone).
C. Sun, M. Sun, H.-T. Chen. Direct voxel grid optimization. CVPR 2022 (the ``grid``
backbone: a density grid, a feature grid and a small MLP).
Q. Wu et al. PaletteNeRF: Palette-based color editing for NeRFs, 2022 (two-stage
training, last-layer width ablation).
"""

from __future__ import annotations

import torch
from torch import nn

OUTPUTS = {
    "rgb": lambda raw: torch.sigmoid(raw),
    "additive": lambda raw: torch.softmax(raw, dim=-1),
    "transport": lambda raw: nn.functional.softplus(raw),
}
GRID_DENSITY_SHIFT = -4.0  # softplus(-4) ~ 0.02 per voxel: below the occupancy threshold


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """(P, D) -> (P, D (1 + 2 F)): x, then sin and cos of 2^k x for k < F."""
    scaled = x[..., None, :] * (2.0 ** torch.arange(frequencies, device=x.device))[:, None]
    return torch.cat([x, torch.sin(scaled).flatten(-2), torch.cos(scaled).flatten(-2)], dim=-1)


class Field(nn.Module):
    """Shared output handling of the backbones."""

    head_width: int

    def _init_output(self, kind: str, channels: int) -> None:
        self.kind = kind
        self.output = nn.Linear(self.head_width, channels)

    def set_output(self, kind: str, channels: int) -> None:
        """A new output layer of ``channels`` outputs and activation ``kind``."""
        device = next(self.parameters()).device
        self._init_output(kind, channels)
        self.output.to(device)

    def colour(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """(P, C) outputs at the density part's ``h`` seen from unit directions ``d``."""
        return self.colour_output(self.head(h, d))

    def colour_output(self, features: torch.Tensor) -> torch.Tensor:
        """The output layer and its activation on (P, head_width) ``head`` features."""
        return OUTPUTS[self.kind](self.output(features))

    def head(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """(P, head_width) last hidden layer of the colour part, the output layer's input."""
        raise NotImplementedError

    def extra_state_dict(self) -> dict:
        return {"kind": self.kind, "channels": self.output.out_features}


class MLPField(Field):
    """Vanilla NeRF: 8 x 256 trunk with a skip, density and feature layers (the density part),
    then a view-dependent layer of ``head_width`` and the output layer (the colour part).

    Examples
    --------
    >>> field = MLPField(kind="additive", channels=5)
    >>> sigma, h = field.density(torch.zeros(2, 3))
    >>> [round(s, 5) for s in field.colour(h, torch.tensor([[0.0, 0.0, 1.0]] * 2)).sum(-1).tolist()]
    [1.0, 1.0]
    """

    def __init__(self, head_width: int = 128, kind: str = "rgb", channels: int = 3,
                 depth: int = 8, width: int = 256, skip: int = 4,
                 position_frequencies: int = 10, direction_frequencies: int = 4):
        super().__init__()
        self.head_width = head_width
        self.position_frequencies = position_frequencies
        self.direction_frequencies = direction_frequencies
        self.skip = skip
        n_in = 3 * (1 + 2 * position_frequencies)
        self.trunk = nn.ModuleList(
            nn.Linear(n_in if i == 0 else width + (n_in if i == skip else 0), width)
            for i in range(depth))
        self.sigma = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + 3 * (1 + 2 * direction_frequencies), head_width)
        self._init_output(kind, channels)

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        encoded = positional_encoding(x, self.position_frequencies)
        h = encoded
        for i, layer in enumerate(self.trunk):
            if i == self.skip:
                h = torch.cat([h, encoded], dim=-1)
            h = torch.relu(layer(h))
        return nn.functional.softplus(self.sigma(h)[:, 0]), self.feature(h)

    def head(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        encoded = positional_encoding(d, self.direction_frequencies)
        return torch.relu(self.view(torch.cat([h, encoded], dim=-1)))

    def density_parameters(self) -> list[nn.Parameter]:
        return [*self.trunk.parameters(), *self.sigma.parameters(), *self.feature.parameters()]

    def colour_parameters(self) -> list[nn.Parameter]:
        return [*self.view.parameters(), *self.output.parameters()]

    def grid_parameters(self) -> list[nn.Parameter]:
        return []


class GridField(Field):
    """Dense voxel grids over the scene box: density (the density part), and colour features
    read by a small MLP of ``head_width`` (the colour part).

    The grids are sparse embeddings so that an optimiser step touches only the
    voxels that samples reached: empty, skipped space costs nothing.

    Parameters
    ----------
    extent : (3,) float
        Half sizes of the normalised scene box (the largest is 1).
    voxels : int
        About this many voxels, cubic, spread over the box.
    direction_frequencies : int or None
        Positional encoding of the view direction fed to the head; None for a
        view-independent (diffuse) colour, which generalises better from few pixels.

    Examples
    --------
    >>> field = GridField([1.0, 0.5, 1.0], voxels=1000, features=4, kind="transport", channels=6)
    >>> field.resolution.tolist()
    [13, 6, 13]
    >>> sigma, h = field.density(torch.zeros(2, 3))
    >>> bool((field.colour(h, torch.tensor([[1.0, 0.0, 0.0]] * 2)) >= 0).all())
    True
    """

    def __init__(self, extent, voxels: int = 96**3, features: int = 12, head_width: int = 128,
                 kind: str = "rgb", channels: int = 3, direction_frequencies: int | None = None):
        super().__init__()
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
        n = int(torch.prod(self.resolution))
        self.density_grid = nn.Embedding(n, 1, sparse=True)
        self.feature_grid = nn.Embedding(n, features, sparse=True)
        nn.init.zeros_(self.density_grid.weight)
        nn.init.zeros_(self.feature_grid.weight)
        n_direction = 0 if direction_frequencies is None else 3 * (1 + 2 * direction_frequencies)
        self.hidden = nn.Linear(features + n_direction, head_width)
        self._init_output(kind, channels)

    def _corners(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinear interpolation: (P, 8) flat voxel indices and (P, 8) weights."""
        res = self.resolution
        u = (x + self.extent) / (2 * self.extent) * (res - 1)
        u = torch.minimum(torch.clamp(u, min=0), (res - 1).to(u.dtype))
        base = torch.minimum(u.floor().long(), res - 2)
        frac = (u - base)[:, None]  # (P, 1, 3)
        ijk = base[:, None] + self.CORNERS  # (P, 8, 3)
        index = (ijk[..., 0] * res[1] + ijk[..., 1]) * res[2] + ijk[..., 2]
        weight = torch.where(self.CORNERS.bool(), frac, 1 - frac).prod(-1)
        return index, weight

    @staticmethod
    def _interpolate(grid: nn.Embedding, index: torch.Tensor, weight: torch.Tensor):
        return (grid(index) * weight[..., None]).sum(1)  # (P, C)

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        index, weight = self._corners(x)
        raw = self._interpolate(self.density_grid, index, weight)[:, 0]
        return nn.functional.softplus(raw + GRID_DENSITY_SHIFT) * self.voxels_per_unit, x

    def head(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        features = self._interpolate(self.feature_grid, *self._corners(h))
        if self.direction_frequencies is not None:
            features = torch.cat([features, positional_encoding(d, self.direction_frequencies)],
                                 dim=-1)
        return torch.relu(self.hidden(features))

    def density_parameters(self) -> list[nn.Parameter]:
        return [self.density_grid.weight]

    def colour_parameters(self) -> list[nn.Parameter]:
        return [self.feature_grid.weight, *self.hidden.parameters(), *self.output.parameters()]

    def grid_parameters(self) -> list[nn.Parameter]:
        """The sparse parameters (optimised by ``SparseAdam``)."""
        return [self.density_grid.weight, self.feature_grid.weight]


def make_field(config, extent, kind: str, channels: int) -> Field:
    """The backbone ``config.backbone`` with an output of ``channels`` and activation ``kind``."""
    if config.backbone == "mlp":
        return MLPField(config.head_width, kind, channels)
    return GridField(extent, config.grid_voxels, config.grid_features, config.head_width,
                     kind, channels, config.grid_view_frequencies)


__all__ = ["OUTPUTS", "Field", "GridField", "MLPField", "make_field", "positional_encoding"]
