"""Radiance-field backbones behind the abstract ``Field`` (``base``), by name.

Adding a backbone is one module here with a ``Field`` subclass, one entry in
``BACKBONES``, and its settings in ``nerf_stage.config`` (docs/architecture.md).
"""

from __future__ import annotations

import torch

from ..config import Backbone
from .base import ACTIVATIONS, RGB, Field, RaySampling, positional_encoding
from .grid import GridField
from .mlp import MLPField

BACKBONES: dict[str, type[Field]] = {Backbone.GRID: GridField, Backbone.MLP: MLPField}


def make_field(config, extent: torch.Tensor, kind: str, channels: int) -> Field:
    """The backbone ``config.backbone`` with an output of ``channels`` and activation ``kind``."""
    return BACKBONES[config.backbone].from_config(config, extent, kind, channels)


__all__ = ["ACTIVATIONS", "BACKBONES", "RGB", "Field", "GridField", "MLPField", "RaySampling",
           "make_field", "positional_encoding"]
