"""Radiance-field backbones by name: each one's settings (``backbone_settings``) and where
its model lives, imported only when a run is built or loaded (by ``trainer.train``,
``loading.load_run`` and ``fields.make_field``, which no backbone's module imports).

Adding a backbone is one module in ``fields/`` with a ``Field`` subclass (or a module with
its own steps, like ``splats.backbone``), its settings in ``backbone_settings`` and one entry
here (docs/architecture.md).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from .backbone_settings import GridConfig, HashConfig, MLPConfig, SplatConfig


@dataclass(frozen=True)
class BackboneSpec:
    """A backbone: its settings' dataclass and its model in ``nerf_stage``: a ``Field`` as
    ``"module:Class"``, trained by ``trainer`` and loaded by ``loading``; or, for a model
    that is not a field, ``"module"``, which has its own ``train(config, dataset, stack,
    rundir, weights, state, box, weights_path, progress, device)`` (handed the training
    weights, the checkpoint's state when resuming and the scene box by ``trainer.train``)
    and ``load_run(state, path, device)`` (``splats.backbone``)."""

    settings: type
    target: str

    @property
    def is_field(self) -> bool:
        return ":" in self.target

    def field_class(self) -> type:
        """The ``Field`` subclass (imports torch)."""
        module, name = self.target.split(":")
        return getattr(importlib.import_module(f"nerf_stage.{module}"), name)

    def module(self):
        """The module of a backbone that is not a field (imports torch)."""
        return importlib.import_module(f"nerf_stage.{self.target}")


BACKBONES = {
    "grid": BackboneSpec(GridConfig, "fields.grid:GridField"),
    "mlp": BackboneSpec(MLPConfig, "fields.mlp:MLPField"),
    "hash": BackboneSpec(HashConfig, "fields.hashgrid:HashField"),
    "splats": BackboneSpec(SplatConfig, "splats.backbone"),
}
