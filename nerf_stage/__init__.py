"""NeRF stage: simulated multi-view scenes with light-transport weights, multi-view
datasets and weight stacks joined to them, and weight NeRFs (PaletteNeRF).

Its rooms: ``data`` (datasets, cameras, lenses, captures), ``fields`` (the neural
backbones), ``render`` (the scene box, occupancy, marching), ``train`` (settings, run
folders, the loop, scores), ``edit`` (weight renders recoloured, regions), ``splats``
(3D Gaussians: a backbone, bakes, the rasteriser, the PLY), ``simulation`` (the path
tracer) and ``cli``. The weight NeRF modules need torch (the ``nerf`` extra);
``backbones``, ``train.config``, ``data.cameras`` and ``train.metrics`` need none.
Imports ``palette_core`` and ``harmonize``; never the reverse. docs/architecture.md
shows how they fit together.
"""

import importlib

#: Public names, by the module that holds them; imported on first use, so that importing
#: one module (a metric, the config) does not compile the path tracer.
_LAZY = {
    "Intrinsics": "data.cameras",
    "Dataset": "data.dataset", "join_weights": "data.dataset", "load_dataset": "data.dataset",
    "Scene": "simulation", "Simulation": "simulation", "load_scene": "simulation",
    "simulate": "simulation", "write_dataset": "simulation",
}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'nerf_stage' has no attribute {name!r}")
    return getattr(importlib.import_module(f"nerf_stage.{_LAZY[name]}"), name)


__all__ = [
    "Dataset",
    "Intrinsics",
    "Scene",
    "Simulation",
    "join_weights",
    "load_dataset",
    "load_scene",
    "simulate",
    "write_dataset",
]
