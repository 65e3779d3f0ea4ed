"""The ``mlp`` backbone: the vanilla NeRF of the paper.

References
----------
B. Mildenhall et al. NeRF: Representing scenes as neural radiance fields for view
synthesis. ECCV 2020.
Q. Wu et al. PaletteNeRF: Palette-based color editing for NeRFs, 2022 (last-layer
width ablation).
"""

from __future__ import annotations

import torch
from torch import nn

from ..backbone_settings import MLPConfig
from .base import RGB, Field, RaySampling, positional_encoding


class MLPField(Field):
    """Vanilla NeRF: 8 x 256 trunk with a skip, density and feature layers (the density part),
    then a view-dependent layer of ``head_width`` and the output layer (the colour part).
    Positions are encoded as they are: the box's ``extent`` is not needed.

    Examples
    --------
    >>> from palette_core.basis import Basis
    >>> field = MLPField(kind=Basis.ADDITIVE, channels=5)
    >>> sigma, h = field.density(torch.zeros(2, 3))
    >>> [round(s, 5) for s in field.colour(h, torch.tensor([[0.0, 0.0, 1.0]] * 2)).sum(-1).tolist()]
    [1.0, 1.0]
    """

    def __init__(self, extent=None, settings: MLPConfig | None = None, head_width: int = 128,
                 kind: str = RGB, channels: int = 3, depth: int = 8, width: int = 256,
                 skip: int = 4, position_frequencies: int = 10, direction_frequencies: int = 4):
        super().__init__()
        self.settings = settings = settings or MLPConfig()
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

    def sampling(self, render: bool = False) -> RaySampling:
        return RaySampling(count=self.settings.samples)
