"""palette_core: shared palettes and additive weights for sets of images.

Stitch all pixels of all images into one colour set (``colour_set``), fit one
palette (``palettes``: the convex-hull simplification of ``hull``, refined to the
pixels by ``refine``), compute per-pixel weights (``weights``: mean value
coordinates, ``mvc``, or RGBXY, ``rgbxy``), store them as a weight stack (``stack``:
NPZ, or Zarr for collections beyond memory, ``collection``) and recolour by editing
the palette (``basis``, ``recolor``). docs/architecture.md shows how the modules fit
together.
"""

from .basis import Basis, basis_terms, n_terms, transport_basis, transport_terms, weights_to_rgb
from .colour_set import ColourSet
from .decompose import Decomposition, decompose
from .errors import InputError
from .hull import extract_palette, simplification_levels
from .io import LoadedImage, find_images, load_image
from .mvc import rgb_to_mvc_weights
from .palette_file import palette_to_hex, read_palette_json, write_palette_json
from .palettes import PALETTE_METHODS, palette_polytope
from .polytope import Polytope, polytope_from_points, polytope_rmse, project_to_polytope
from .recolor import recolor_stack
from .stack import WeightStack, read_stack, write_stack
from .version import __version__
from .weights import WEIGHT_METHODS, image_weights

__all__ = [
    "__version__",
    "PALETTE_METHODS",
    "WEIGHT_METHODS",
    "Basis",
    "ColourSet",
    "Decomposition",
    "InputError",
    "LoadedImage",
    "Polytope",
    "WeightStack",
    "basis_terms",
    "decompose",
    "extract_palette",
    "find_images",
    "image_weights",
    "load_image",
    "n_terms",
    "palette_polytope",
    "palette_to_hex",
    "polytope_from_points",
    "polytope_rmse",
    "project_to_polytope",
    "read_palette_json",
    "read_stack",
    "recolor_stack",
    "rgb_to_mvc_weights",
    "simplification_levels",
    "transport_basis",
    "transport_terms",
    "weights_to_rgb",
    "write_palette_json",
    "write_stack",
]
