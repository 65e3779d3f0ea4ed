"""Rays through a field: the scene box and the space beyond it (``scene_box``,
``contraction``), empty-space skipping (``occupancy``), marching and compositing
(``march``). docs/training.md."""
