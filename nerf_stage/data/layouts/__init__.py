"""Dataset layouts, one module each (nerfstudio's dataparsers): each has a ``LAYOUT`` (the
file that marks it, whether a folder holds it, its reader returning ``Frames``), and
``LAYOUTS`` names them in the order a folder is looked at. A new layout is one module and
one entry here.
"""

from .blender import LAYOUT as BLENDER
from .colmap import LAYOUT as COLMAP
from .common import Frames, Layout
from .llff import LAYOUT as LLFF
from .nerfstudio import LAYOUT as NERFSTUDIO

#: An LLFF capture's ``poses_bounds.npy`` is read before the COLMAP model it may also hold:
#: its poses are the ones the forward-facing papers evaluate with.
LAYOUTS = {"blender": BLENDER, "nerfstudio": NERFSTUDIO, "llff": LLFF, "colmap": COLMAP}

__all__ = ["LAYOUTS", "Frames", "Layout"]
