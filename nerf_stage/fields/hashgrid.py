"""The ``hash`` backbone: a multi-resolution hash encoding read by two small MLPs, for detail
at the photos' resolution (the field of instant-ngp and nerfacto, in plain PyTorch, so that
it runs on the CPU and on CUDA alike).

References
----------
T. Mueller et al. Instant neural graphics primitives with a multiresolution hash encoding.
SIGGRAPH 2022 (Sec. 3: levels, the spatial hash, trilinear interpolation of each level).
M. Tancik et al. Nerfstudio. SIGGRAPH 2023 (nerfacto's field: 16 levels of 2 features,
2^19 entries a level, a density MLP whose other outputs feed the colour MLP).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..backbone_settings import HashConfig
from .base import RGB, Field, RaySampling
from .grid import GridField, _Trilinear

#: The spatial hash's primes (instant-ngp, eq. 4; the first is 1, for coherent memory), as
#: int32: 2654435761 wraps to -1640531535, with the same low bits.
PRIMES = (1, 2654435761 - (1 << 32), 805459861)
MAX_LOG_DENSITY = 15.0  # exp() of more is clamped: a density no step needs


class HashEncoding(nn.Module):
    """(P, 3) positions in the box [-extent, extent] -> (P, levels x features): each level a
    grid of its own resolution, from ``coarsest`` to ``finest`` cells along the box's
    longest side in a geometric series, whose vertices index a table of ``2^log2_entries``
    rows, directly where the level's vertices fit in it, else through the spatial hash;
    each level's features are interpolated trilinearly from its cell's eight vertices."""

    def __init__(self, extent: torch.Tensor, settings: HashConfig):
        super().__init__()
        levels, entries = settings.levels, 1 << settings.log2_entries
        growth = math.exp(math.log(settings.finest / settings.coarsest) / max(levels - 1, 1))
        resolution = [math.floor(settings.coarsest * growth ** level) for level in range(levels)]
        sizes = [min((n + 1) ** 3, entries) for n in resolution]
        offsets = torch.tensor([0, *sizes]).cumsum(0)
        self.register_buffer("reach", extent.max().float(), persistent=False)
        self.register_buffer("resolution", torch.tensor(resolution), persistent=False)
        # the coarse levels, first, whose vertices fit in their table, index it directly
        self.direct_levels = sum((n + 1) ** 3 <= entries for n in resolution)
        vertices = torch.tensor(resolution[:self.direct_levels])[:, None] + 1
        self.register_buffer("strides", (vertices ** torch.tensor([2, 1, 0])).int(),
                             persistent=False)
        self.register_buffer("primes", torch.tensor(PRIMES, dtype=torch.int32),
                             persistent=False)
        self.register_buffer("mask", torch.tensor(entries - 1, dtype=torch.int32),
                             persistent=False)
        self.register_buffer("offset", offsets[:-1].int(), persistent=False)
        self.register_buffer("ends", torch.arange(2, dtype=torch.int32), persistent=False)
        # (C, N) channels first, as ``_Trilinear`` takes it; small, as instant-ngp starts it
        self.table = nn.Parameter(torch.empty(settings.features, int(offsets[-1]))
                                  .uniform_(-1e-4, 1e-4))

    @property
    def width(self) -> int:
        return self.table.shape[0] * len(self.resolution)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        u = ((x + self.reach) / (2 * self.reach)).clamp(0, 1)
        scaled = u[:, None, :] * self.resolution[:, None]  # (P, L, 3)
        base = torch.minimum(scaled.floor(), self.resolution[:, None] - 1)
        frac = scaled - base
        # each axis's two ends, int32: a hashed row needs only the low bits of the products
        ends = base.int()[..., None] + self.ends  # (P, L, 3 axes, 2)
        d = self.direct_levels
        direct = ends[:, :d] * self.strides[..., None] + self.offset[:d, None, None]
        spread = ends[:, d:] * self.primes[:, None]
        index = torch.cat([
            direct[..., 0, :, None, None] + direct[..., 1, None, :, None]
            + direct[..., 2, None, None, :],
            ((spread[..., 0, :, None, None] ^ spread[..., 1, None, :, None]
              ^ spread[..., 2, None, None, :]) & self.mask) + self.offset[d:, None, None, None],
        ], 1)  # (P, L, 2, 2, 2): the rows of each level's eight corners
        w = torch.stack([1 - frac, frac], -1)
        weight = w[..., 0, :, None, None] * w[..., 1, None, :, None] * w[..., 2, None, None, :]
        features = _Trilinear.apply(self.table, index.view(-1, 8), weight.view(-1, 8))
        return features.view(len(x), -1)


class HashField(Field):
    """A ``HashEncoding`` read by a density MLP (one hidden layer of ``density_width``) whose
    first output is the log density (plus one) and whose other ``geometry_features`` outputs
    are ``h``; the colour part is the grid backbone's head: ``head_layers`` hidden layers of
    ``head_width`` on ``h`` and the encoded view direction. The density part (encoding and
    density MLP) is what two-stage fine-tuning freezes.

    Examples
    --------
    >>> from palette_core.basis import Basis
    >>> settings = HashConfig(levels=4, log2_entries=10, finest=32)
    >>> field = HashField(torch.ones(3), settings, kind=Basis.ADDITIVE, channels=4)
    >>> sigma, h = field.density(torch.zeros(5, 3))
    >>> tuple(sigma.shape), tuple(h.shape)
    ((5,), (5, 15))
    >>> [round(s, 5) for s in field.colour(h, torch.tensor([[0.0, 0.0, 1.0]] * 5)).sum(-1).tolist()]
    [1.0, 1.0, 1.0, 1.0, 1.0]
    """

    refines_occupancy = True

    def __init__(self, extent, settings: HashConfig | None = None, head_width: int = 128,
                 kind: str = RGB, channels: int = 3):
        super().__init__()
        self.settings = settings = settings or HashConfig()
        extent = torch.as_tensor(extent, dtype=torch.float32)
        self.encoding = HashEncoding(extent, settings)
        self.density_mlp = nn.Sequential(
            nn.Linear(self.encoding.width, settings.density_width), nn.ReLU(inplace=True),
            nn.Linear(settings.density_width, 1 + settings.geometry_features))
        self.head_width = head_width
        self.direction_frequencies = settings.view_frequencies
        self.deferred = settings.deferred
        self.span = 2 * float(extent.max())
        n_direction = 0 if self.direction_frequencies is None else 3 * (
            1 + 2 * self.direction_frequencies)
        self.hidden = nn.Linear(settings.geometry_features + n_direction, head_width)
        self.deeper = nn.ModuleList(nn.Linear(head_width, head_width)
                                    for _ in range(settings.head_layers - 1))
        self._init_output(kind, channels)

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Densities exp(first output - 1) (instant-ngp's activation; about 0.37 a unit at the
        start, clear space), and the other outputs as ``h``."""
        out = self.density_mlp(self.encoding(x))
        return torch.exp((out[:, 0] - 1).clamp(max=MAX_LOG_DENSITY)), out[:, 1:]

    head = GridField.head

    def density_parameters(self) -> list[nn.Parameter]:
        return [*self.encoding.parameters(), *self.density_mlp.parameters()]

    def colour_parameters(self) -> list[nn.Parameter]:
        return [*self.hidden.parameters(), *self.deeper.parameters(), *self.output.parameters()]

    def grid_parameters(self) -> list[nn.Parameter]:
        return [self.encoding.table]

    def sampling(self, render: bool = False) -> RaySampling:
        settings = self.settings
        return RaySampling(step=self.span / (settings.render_samples if render
                                             else settings.samples))
