"""Dataset layouts, one module each (nerfstudio's dataparsers): each has a ``LAYOUT`` (the
file that marks it, whether a folder holds it, its reader returning ``Frames``), and
``LAYOUTS`` names them in the order a folder is looked at. A new layout is one module and
one entry here.
"""

from .blender import LAYOUT as BLENDER
from .colmap import LAYOUT as COLMAP
from .common import Frames, Layout
from .nerfstudio import LAYOUT as NERFSTUDIO

LAYOUTS = {"blender": BLENDER, "nerfstudio": NERFSTUDIO, "colmap": COLMAP}

__all__ = ["LAYOUTS", "Frames", "Layout"]
