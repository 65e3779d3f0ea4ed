"""NeRF stage: simulated multi-view scenes with light-transport weights, multi-view
datasets and weight stacks joined to them. Imports ``palette_core``; never the reverse.
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
