"""Radiance-field backbones by name, without torch: each one's settings (a config dataclass,
the section of ``TrainConfig`` of the same name) and where its ``Field`` lives, imported
only when a run is built.

Adding a backbone is one module in ``fields/`` with a ``Field`` subclass and one entry in
``BACKBONES`` with its settings here (and the section in ``TrainConfig``;
docs/architecture.md).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from enum import StrEnum

from palette_core.errors import InputError

from .checks import MAX_ITERS, MAX_VOXELS, integers, positive


@dataclass
class GridConfig:
    """Settings of the ``grid`` backbone (dense voxel grids and a small MLP head)."""

    voxels: int = 96**3
    """Voxels of the density and feature grids, spread over the scene box."""
    features: int = 12
    """Feature channels per voxel of the colour grid."""
    view_frequencies: int | None = 4
    """Frequencies of the view direction's encoding in the head; None (``none`` on the command
    line): diffuse."""
    deferred: bool = True
    """Shade each ray once, from its features composited along it, rather than each sample
    (deferred shading; docs/nerf.md, "Deferred shading"): faster, and a view-dependent head
    then tells a thin wall's two sides apart. False: the paper's per-sample colours, which
    ``render --baked`` needs."""
    head_layers: int = 2
    """Hidden layers of the head, each ``head_width`` wide (docs/nerf.md, "The colour
    head")."""
    lr: float = 0.1
    """Adam learning rate of the voxel grids."""
    network_lr: float = 1e-3
    """Adam learning rate of the head."""
    step_voxels: float = 1.0
    """Ray-marching step of training, in voxels."""
    render_step_voxels: float = 0.5
    """Ray-marching step of renders, in voxels: finer than training's, so that surfaces that
    training made thinner than a step render without bands."""
    occupancy_every: int = 16
    """Iterations between updates of the occupancy grid from the learned density."""
    warmup_iters: int = 64
    """Iterations before occupancy is refined from the learned density."""

    def __post_init__(self):
        if not isinstance(self.deferred, bool):
            raise InputError(f"deferred must be true or false, got {self.deferred!r}")
        integers(self, 1, MAX_VOXELS, "voxels")
        integers(self, 1, 256, "features")
        integers(self, 1, 16, "head_layers")
        integers(self, 1, MAX_ITERS, "occupancy_every")
        integers(self, 0, MAX_ITERS, "warmup_iters")
        if self.view_frequencies is not None:
            integers(self, 0, 16, "view_frequencies")
        positive(self, "lr", "network_lr", "step_voxels", "render_step_voxels")


@dataclass
class MLPConfig:
    """Settings of the ``mlp`` backbone (the paper's vanilla NeRF)."""

    samples: int = 96
    """Samples per ray, evenly across the scene box."""
    network_lr: float = 5e-4
    """Adam learning rate."""

    def __post_init__(self):
        integers(self, 1, 4096, "samples")
        positive(self, "network_lr")


@dataclass(frozen=True)
class BackboneSpec:
    """A backbone: its settings' dataclass and its field as ``"module:Class"`` in
    ``nerf_stage``."""

    settings: type
    target: str

    def field_class(self) -> type:
        """The ``Field`` subclass (imports torch)."""
        module, name = self.target.split(":")
        return getattr(importlib.import_module(f"nerf_stage.{module}"), name)


BACKBONES = {
    "grid": BackboneSpec(GridConfig, "fields.grid:GridField"),
    "mlp": BackboneSpec(MLPConfig, "fields.mlp:MLPField"),
}

#: The backbones' names, as ``TrainConfig.backbone`` takes them.
Backbone = StrEnum("Backbone", {name.upper(): name for name in BACKBONES})
Backbone.__doc__ = "Backbone names (``BACKBONES``); each has a settings section of its name."
