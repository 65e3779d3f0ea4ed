"""NeRF stage: simulated multi-view scenes with light-transport weights, multi-view
datasets and weight stacks joined to them, and weight NeRFs (PaletteNeRF).

The weight NeRF modules need torch (the ``nerf`` extra) and are imported by name:
``fields`` (backbones), ``scene_box``, ``occupancy``, ``rendering`` (marching and
compositing), ``losses``, ``run`` (the run folder: config, checkpoint, load_run),
``trainer`` (train), ``editing`` (weight renders and recolouring) and ``evaluation``
(re-simulated edits); ``config``, ``backbones``, ``cameras`` and ``metrics`` (PSNR,
SSIM) need no torch. Imports ``palette_core`` and
``harmonize``; never the reverse. docs/architecture.md shows how they fit together.
"""

import importlib

#: Public names, by the module that holds them; imported on first use, so that importing
#: one module (a metric, the config) does not compile the path tracer.
_LAZY = {
    "Intrinsics": "cameras",
    "Dataset": "data", "join_weights": "data", "load_dataset": "data",
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
