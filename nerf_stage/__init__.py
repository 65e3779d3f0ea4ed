"""NeRF stage: simulated multi-view scenes with light-transport weights (and, with the
``nerf`` extra, NeRFs trained on weight stacks). Imports ``palette_core``; never the reverse.
"""

from .simulation import Scene, Simulation, load_scene, simulate, write_dataset

__all__ = ["Scene", "Simulation", "load_scene", "simulate", "write_dataset"]
