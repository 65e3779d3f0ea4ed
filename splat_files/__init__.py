"""Splat files of other tools, opened and palette-edited (docs/splat_files.md): the 3D
Gaussian splatting PLY, SuperSplat's compressed PLY, Niantic's SPZ, antimatter15's
``.splat`` and PlayCanvas's SOG read as ``SplatFields`` (``formats``); a palette for them
and weights for every splat (``stack``), recoloured back into any of the written formats.
"""

from .fields import SH_C0, SplatFields
from .formats import FORMATS, is_splat_file, read_splat_file, write_splat_file

__all__ = ["FORMATS", "SH_C0", "SplatFields", "is_splat_file", "read_splat_file",
           "write_splat_file"]
