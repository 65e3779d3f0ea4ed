"""The abstract radiance field: a density part and a colour part.

A backbone takes positions in the normalised scene box (``scene_box.SceneBox``)
and exposes the split that two-stage training needs:

- ``density(x) -> (sigma, h)``: the density part. ``sigma`` (P,) is per unit of
  normalised length; ``h`` is whatever the colour part needs at x.
- ``head(h, d) -> (P, head_width)``: the colour part up to its last hidden layer;
  ``colour(h, d)`` adds the output layer and its activation: ``sigmoid`` for RGB,
  ``softmax`` for additive weights (they sum to one), ``softplus`` for transport
  weights (non-negative).

``set_output(kind, channels)`` puts in a new output layer, as the paper's
fine-tuning stage does; ``density_parameters`` and ``colour_parameters`` split the
parameters so that the density part can be frozen. A field is built from its own
settings (its section of ``TrainConfig``, ``backbones``), which also say how rays are
sampled for it (``sampling``). Adding a backbone: docs/architecture.md.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch
from torch import nn

from palette_core.basis import Basis
from palette_core.errors import InputError

#: Output kind of a field that predicts colours rather than weights.
RGB = "rgb"

#: Activation of the output layer per output kind (RGB, or the weights' basis).
ACTIVATIONS = {
    RGB: torch.sigmoid,
    Basis.ADDITIVE: lambda raw: torch.softmax(raw, dim=-1),
    Basis.TRANSPORT: nn.functional.softplus,
}

#: Inverse of each weight kind's activation, up to what the activation ignores (softmax
#: ignores a shift): (M,) positive outputs -> inputs that give them.
INVERSE_ACTIVATIONS = {
    Basis.ADDITIVE: torch.log,
    Basis.TRANSPORT: lambda out: out + torch.log(-torch.expm1(-out)),  # log(e^y - 1), stably
}


def tone_map(weights: torch.Tensor) -> torch.Tensor:
    """Transport weights w -> w / (1 + w) in [0, 1): emitters of radiance far above one
    (30 in the Cornell box) stay comparable with the rest (``inverse_tone_map`` undoes it)."""
    return weights / (1 + weights)


def inverse_tone_map(mapped: torch.Tensor) -> torch.Tensor:
    """Tone-mapped weights in [0, 1) -> transport weights."""
    return mapped / (1 - mapped)


@dataclass(frozen=True)
class RaySampling:
    """Samples ``step`` apart from where a ray enters the box (normalised units), or, when
    ``step`` is None, ``count`` samples evenly across the box; with ``sky``, each ray of an
    unbounded scene ends in an opaque sample at infinity (``rendering.march_rays``)."""

    step: float | None = None
    count: int | None = None
    sky: bool = False


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """(P, D) -> (P, D (1 + 2 F)): x, then sin and cos of 2^k x for k < F."""
    scaled = x[..., None, :] * (2.0 ** torch.arange(frequencies, device=x.device))[:, None]
    return torch.cat([x, torch.sin(scaled).flatten(-2), torch.cos(scaled).flatten(-2)], dim=-1)


class Field(nn.Module, ABC):
    """A backbone: subclasses build their layers, then call ``_init_output`` last.

    Subclasses take ``(extent, settings, head_width, kind, channels)``: ``extent`` (3,) the
    half sizes of the normalised box, ``settings`` their section of ``TrainConfig``.

    Attributes
    ----------
    settings : dataclass
        The backbone's settings (``backbones.BACKBONES``).
    kind : str
        ``RGB`` or a ``Basis``: what the output layer predicts.
    head_width : int
        Width of the last hidden layer (the output layer's input).
    refines_occupancy : bool
        Whether training refines the occupancy grid from this field's density.
    deferred : bool
        Whether the colour part shades each ray once, at its composited ``h``, rather than
        each sample (``rendering.Samples.colour_inputs``).
    """

    head_width: int
    refines_occupancy: bool = False
    deferred: bool = False

    @abstractmethod
    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(P, 3) positions -> (P,) densities and the colour part's input ``h``."""

    @abstractmethod
    def head(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """(P, head_width) last hidden layer of the colour part, the output layer's input."""

    @abstractmethod
    def density_parameters(self) -> list[nn.Parameter]:
        """The parameters that two-stage fine-tuning freezes."""

    @abstractmethod
    def colour_parameters(self) -> list[nn.Parameter]:
        """The parameters of the colour part, the output layer last."""

    @abstractmethod
    def sampling(self, render: bool = False) -> RaySampling:
        """How rays are sampled for this field in training or, with ``render``, in renders."""

    def baked(self, occupancy, factor: int) -> nn.Module:
        """A copy for fast rendering whose colour part is a table look-up, ``factor`` times
        finer than the field's grid, where ``occupancy`` (``occupancy.OccupancyGrid``) is
        occupied (``grid.BakedGrid``); InputError for backbones that cannot be baked."""
        raise InputError(f"a {type(self).__name__} cannot be baked (only the grid backbone with "
                         "per-sample diffuse colours can)")

    def grid_parameters(self) -> list[nn.Parameter]:
        """Voxel grids, trained at the backbone's grid learning rate ``lr``; none by default."""
        return []

    def _init_output(self, kind: str, channels: int) -> None:
        self.kind = kind
        self.output = nn.Linear(self.head_width, channels)

    def set_output(self, kind: str, channels: int) -> None:
        """A new output layer of ``channels`` outputs and activation ``kind``."""
        device = next(self.parameters()).device
        self._init_output(kind, channels)
        self.output.to(device)

    def start_output(self, outputs: torch.Tensor) -> None:
        """Start the output layer at the constant (M,) positive ``outputs``: zero weights and
        the bias that the activation turns into them, so that no channel starts saturated
        or dead (``field_steps.fit_output``)."""
        with torch.no_grad():
            self.output.weight.zero_()
            self.output.bias.copy_(INVERSE_ACTIVATIONS[self.kind](outputs))

    def colour(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """(P, C) outputs at the density part's ``h`` seen from unit directions ``d``."""
        return self.colour_output(self.head(h, d))

    def colour_output(self, features: torch.Tensor) -> torch.Tensor:
        """The output layer and its activation on (P, head_width) ``head`` features."""
        return ACTIVATIONS[self.kind](self.output(features))

    def output_state(self) -> dict:
        """What ``set_output`` needs to rebuild the output layer: kind and channels."""
        return {"kind": str(self.kind), "channels": self.output.out_features}
