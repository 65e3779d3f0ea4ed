"""studio: live palette editing in the browser (``palette-studio``), on viser.

``editor`` holds the palette being edited (undo, reset, harmonisation);
``photos`` and ``scene`` are the two targets, a weight stack and a trained weight
NeRF, each recolouring by ``weights @ basis(palette)``; ``app`` is the web page.
"""

from .editor import PaletteEditor

__all__ = ["PaletteEditor"]
