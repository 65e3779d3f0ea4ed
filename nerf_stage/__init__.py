"""NeRF stage: simulated multi-view scenes with light-transport weights, multi-view
datasets and weight stacks joined to them, and weight NeRFs (PaletteNeRF).

The weight NeRF modules need torch (the ``nerf`` extra) and are imported by name:
``config`` (TrainConfig), ``fields`` (backbones), ``rendering`` (rays, occupancy,
compositing), ``trainer`` (train, load_run) and ``editing`` (weight renders,
recolouring, evaluation). Imports ``palette_core``; never the reverse.
"""

from .data import Dataset, Intrinsics, join_weights, load_dataset
from .simulation import Scene, Simulation, load_scene, simulate, write_dataset

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
