"""Recolouring a weight stack: every image again, with another palette."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .basis import weights_to_rgb
from .outputs import atomic_outputs, check_writable, inside, save_image
from .stack import WeightStack


def recolor_stack(stack: WeightStack, palette: np.ndarray, folder: str | os.PathLike,
                  force: bool = False) -> list[Path]:
    """Write every image of ``stack`` recoloured with ``palette`` (K, 3) under its own name.

    Returns
    -------
    list of Path
        The images written, all published together (``outputs.atomic_outputs``).

    Raises
    ------
    InputError
        If an image exists (without ``force``) or the folder cannot be written.
    """
    targets = [inside(folder, name) for name in stack.names]
    check_writable(targets, force)
    with atomic_outputs(force) as stage:
        for target, weights in zip(targets, stack.weights):
            save_image(stage(target), weights_to_rgb(weights, palette, stack.basis, stack.order))
    return targets
