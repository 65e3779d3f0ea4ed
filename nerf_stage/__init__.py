"""NeRF stage: simulated multi-view scenes with light-transport weights, multi-view
datasets and weight stacks joined to them, and weight NeRFs (PaletteNeRF).

The weight NeRF modules need torch (the ``nerf`` extra) and are imported by name:
``fields`` (backbones), ``rendering`` (occupancy, sampling, compositing), ``run``
(the run folder: config, checkpoint, load_run), ``trainer`` (train), ``editing``
(weight renders and recolouring) and ``evaluation`` (PSNR, SSIM, re-simulated
edits); ``config`` and ``cameras`` need no torch. Imports ``palette_core`` and
``harmonize``; never the reverse. docs/architecture.md shows how they fit together.
"""

from .cameras import Intrinsics
from .data import Dataset, join_weights, load_dataset
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
