"""Scene simulation: scene files, a numba path tracer that sorts light paths by the
editable materials they hit, and Blender-format datasets with transport weights.
"""

from .scene import BUILTIN_SCENES, Scene
from .scene_file import load_scene, parse_scene
from .simulate import (
    LAYOUTS,
    Simulation,
    SimulationRecord,
    render_terms,
    simulate,
    simulate_to,
    view_poses,
    with_overrides,
    with_palette,
    write_dataset,
)

__all__ = [
    "BUILTIN_SCENES",
    "LAYOUTS",
    "Scene",
    "Simulation",
    "SimulationRecord",
    "load_scene",
    "parse_scene",
    "render_terms",
    "simulate",
    "simulate_to",
    "view_poses",
    "with_overrides",
    "with_palette",
    "write_dataset",
]
