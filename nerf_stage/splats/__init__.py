"""3D Gaussians with palette weights (docs/splats.md): the model and its file (``model``),
a differentiable rasteriser (``rasterise``), bakes of a weight NeRF (``baking``) and the
export to splat files (``export``, through ``splat_files``)."""

from .baking import (
    BAKE_VERSION,
    MAX_SPLATS,
    REFINE_STEPS,
    SPLAT_CACHE,
    bake,
    bake_run,
    bake_to,
    cached_bake,
    refine,
    splats_of,
)
from .export import WRITERS, export_splats, splat_fields
from .model import SPLAT_FORMAT, Splats, covariances, matrix_quaternions, read_splats, write_splats
from .rasterise import draw, render_splats, splat_tensors
from .sh import SH_C0

__all__ = [
    "BAKE_VERSION",
    "MAX_SPLATS",
    "REFINE_STEPS",
    "SH_C0",
    "SPLAT_CACHE",
    "SPLAT_FORMAT",
    "WRITERS",
    "Splats",
    "bake",
    "bake_run",
    "bake_to",
    "cached_bake",
    "covariances",
    "draw",
    "export_splats",
    "matrix_quaternions",
    "read_splats",
    "refine",
    "render_splats",
    "splat_tensors",
    "splats_of",
    "splat_fields",
    "write_splats",
]
