"""Radiance-field backbones behind the abstract ``Field`` (``base``).

Which backbones exist, their settings and where their fields live is the torch-free
table ``nerf_stage.backbones.BACKBONES``; adding a backbone is one module here with a
``Field`` subclass and one entry there (docs/architecture.md).
"""

from __future__ import annotations

import torch

from ..backbones import BACKBONES
from .base import ACTIVATIONS, RGB, Field, RaySampling, positional_encoding
from .grid import GridField
from .mlp import MLPField


def make_field(config, box, kind: str, channels: int) -> Field:
    """The backbone ``config.backbone`` of a ``TrainConfig``, built from its settings section
    over the space of the ``scene_box.SceneBox`` ``box``, with an output of ``channels`` and
    activation ``kind``."""
    field_class = BACKBONES[config.backbone].field_class()
    return field_class(torch.as_tensor(box.field_extent, dtype=torch.float32),
                       config.backbone_config, config.head_width, kind, channels)


__all__ = ["ACTIVATIONS", "RGB", "Field", "GridField", "MLPField", "RaySampling",
           "make_field", "positional_encoding"]
