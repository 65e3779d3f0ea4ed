"""Rays through a field: the scene box and the space beyond it (``scene_box``,
``contraction``), empty-space skipping (``occupancy``), marching and compositing
(``march``), and the samples behind each pixel that a render keeps (``samples``).
docs/training.md."""
