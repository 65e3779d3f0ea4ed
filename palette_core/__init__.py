"""palette_core: shared palettes and additive weights for sets of images.

Stitch all pixels of all images, extract one palette by convex-hull
simplification (``hull``), compute per-pixel additive weights with mean value
coordinates (``mvc``), store them as an NPZ weight stack (``stack``) and recolour
by editing the palette (``recolor``).
"""

from .decompose import decompose
from .errors import InputError
from .hull import extract_palette, simplification_levels
from .io import ColourSet, LoadedImage, find_images, load_image
from .mvc import rgb_to_mvc_weights
from .polytope import Polytope, polytope_from_points, polytope_rmse, project_to_polytope
from .recolor import (
    basis_terms,
    read_palette_json,
    transport_basis,
    weights_to_rgb,
    write_palette_json,
)
from .stack import WeightStack, read_stack, write_stack

__version__ = "0.1.0"

__all__ = [
    "ColourSet",
    "InputError",
    "LoadedImage",
    "Polytope",
    "WeightStack",
    "basis_terms",
    "decompose",
    "extract_palette",
    "find_images",
    "load_image",
    "polytope_from_points",
    "polytope_rmse",
    "project_to_polytope",
    "read_palette_json",
    "read_stack",
    "rgb_to_mvc_weights",
    "simplification_levels",
    "transport_basis",
    "weights_to_rgb",
    "write_palette_json",
    "write_stack",
]
