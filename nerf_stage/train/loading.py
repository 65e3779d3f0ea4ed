"""A trained run read back from its folder, whatever its backbone: the one place that looks
a checkpoint's backbone up in ``backbones.BACKBONES`` (no backbone's module imports it).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from palette_core.basis import n_terms
from palette_core.errors import InputError, first_line

from ..backbones import BACKBONES
from ..fields import RGB, make_field
from ..render.occupancy import OccupancyGrid
from .checkpoint import CHECKPOINT, read_checkpoint
from .config import TrainConfig
from .run import Run, RunBase, default_device, restore, run_fields


def load_run(rundir: str | os.PathLike, device: torch.device | None = None) -> RunBase:
    """The trained run in ``rundir``: a ``Run``, or what a backbone that is not a field
    loads (``backbones.BackboneSpec``).

    Raises
    ------
    InputError
        If there is no readable checkpoint.
    """
    device = device or default_device()
    path = Path(rundir) / CHECKPOINT
    state = read_checkpoint(path)
    try:
        config = TrainConfig.from_dict(state["config"], str(path))
        spec = BACKBONES.get(config.backbone)
        if spec is None:
            raise InputError(f"{path}: its config names no backbone ({config.backbone})")
        if not spec.is_field:
            return spec.module().load_run(state, str(path), device)
        if "occupancy" not in state:  # a field run's own key
            raise InputError(f"checkpoint {path} lacks occupancy")
        base = run_fields(state, str(path))
        channels = n_terms(len(base["palette"]), base["basis"], base["order"])
        output = state["output"]
        if output["kind"] != RGB and output["channels"] != channels:
            raise InputError(f"{path}: the field outputs {output['channels']} channels, the "
                             f"basis has {channels}")
        field = make_field(config, base["box"], output["kind"], output["channels"])
        occupancy = OccupancyGrid.over(base["box"], config.occupancy_voxels)
        run = Run(**base, field=field, occupancy=occupancy)
        restore(run, state)
        run.field.to(device)
        run.occupancy.to(device)
        return run
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        raise InputError(f"checkpoint {path} is malformed: {first_line(exc)}") from None
