"""Checks of the values in configs and files from elsewhere: types and limits, so that a
``NERF_STAGE_CONFIG`` file or a checkpoint can neither crash us nor ask for terabytes."""

from __future__ import annotations

import math
from enum import StrEnum

from palette_core.errors import InputError

#: Most voxels of a grid (2^25: 320^3), and most iterations of a stage.
MAX_VOXELS = 1 << 25
MAX_ITERS = 10_000_000


def member(enum: type[StrEnum], value, name: str):
    try:
        return enum(value)
    except ValueError:
        raise InputError(f"{name} must be one of {', '.join(enum)}, got {value!r}") from None


def is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def integers(config, low: int, high: int, *names: str) -> None:
    """InputError unless each field is an integer in [low, high] (limits keep a config from
    elsewhere from asking for terabytes)."""
    for name in names:
        value = getattr(config, name)
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            raise InputError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


def at_least_zero(config, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        if not (is_number(value) and 0 <= value < math.inf):
            raise InputError(f"{name} must be a finite number >= 0, got {value!r}")


def positive(config, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        if not (is_number(value) and 0 < value < math.inf):
            raise InputError(f"{name} must be a finite number > 0, got {value!r}")
