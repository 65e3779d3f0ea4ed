"""Training configuration: one dataclass, saved as ``config.json`` beside the checkpoint."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from palette_core.errors import InputError

BACKBONES = ("grid", "mlp")
STRATEGIES = ("two-stage", "traditional", "rgb")


@dataclass
class TrainConfig:
    """How to train one weight NeRF (defaults suit the ``grid`` backbone on a CPU)."""

    backbone: str = "grid"
    """``grid`` (dense voxel grids, fast on CPUs) or ``mlp`` (the paper's vanilla NeRF)."""
    strategy: str = "two-stage"
    """``two-stage`` (RGB pretrain, then weights), ``traditional`` (weights from scratch),
    or ``rgb`` (an RGB NeRF only, the baseline)."""
    pretrain_iters: int = 800
    """P: RGB iterations of ``two-stage`` (``traditional`` and ``rgb`` train P + F on one
    target)."""
    finetune_iters: int = 300
    """F: weight iterations of ``two-stage`` with the density part frozen."""
    batch_rays: int = 4096
    """Rays per iteration."""
    lr: float = 0.0
    """Adam learning rate of the networks; 0 picks the backbone's (grid 1e-3, mlp 5e-4)."""
    grid_lr: float = 0.1
    """Learning rate of the voxel grids (``grid`` only)."""
    grid_voxels: int = 96**3
    """Voxels of the density and feature grids (``grid``), spread over the scene box."""
    grid_features: int = 12
    """Feature channels per voxel of the colour grid (``grid``)."""
    grid_view_frequencies: int | None = None
    """Frequencies of the view direction's encoding in the ``grid`` head; None: diffuse."""
    head_width: int = 128
    """Width of the last hidden layer (the paper's 128/256/512 ablation for ``mlp``)."""
    step_voxels: float = 1.0
    """Ray-marching step of the ``grid`` backbone, in voxels."""
    mlp_samples: int = 96
    """Samples per ray of the ``mlp`` backbone."""
    occupancy_voxels: int = 64**3
    """Cells of the occupancy grid that lets empty space be skipped (the visual hull of the
    training views; the ``grid`` backbone refines it from its density)."""
    occupancy_every: int = 16
    """Iterations between occupancy updates (``grid``)."""
    warmup_iters: int = 64
    """Iterations before occupancy is refined from the learned density (``grid``)."""
    opacity_weight: float = 0.1
    """Weight of the L2 loss between the accumulated opacity and the images' alpha, while the
    density trains: it clears fog from space that few rays constrain."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Colour behind the scene, RGB in [0, 1]."""
    seed: int = 0
    """Seed of the weight initialisation, ray batches and sample jitter."""
    checkpoint_every: int = 500
    """Iterations between checkpoints."""

    def __post_init__(self):
        self.background = tuple(float(c) for c in self.background)
        if self.backbone not in BACKBONES:
            raise InputError(f"backbone must be one of {', '.join(BACKBONES)}, "
                             f"got {self.backbone!r}")
        if self.strategy not in STRATEGIES:
            raise InputError(f"strategy must be one of {', '.join(STRATEGIES)}, "
                             f"got {self.strategy!r}")
        for name in ("pretrain_iters", "finetune_iters", "occupancy_every", "warmup_iters"):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("batch_rays", "grid_voxels", "grid_features", "head_width", "mlp_samples",
                     "occupancy_voxels", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.pretrain_iters + self.finetune_iters == 0:
            raise InputError("pretrain_iters + finetune_iters must be > 0")
        if self.strategy == "two-stage" and self.finetune_iters == 0:
            raise InputError("the two-stage strategy needs finetune_iters > 0")
        if not (self.step_voxels > 0 and self.grid_lr > 0 and self.lr >= 0
                and self.opacity_weight >= 0):
            raise InputError("step_voxels and grid_lr must be > 0, lr and opacity_weight >= 0")
        if len(self.background) != 3 or not all(0 <= c <= 1 for c in self.background):
            raise InputError(f"background must be three numbers in [0, 1], got {self.background}")

    @property
    def total_iters(self) -> int:
        return self.pretrain_iters + self.finetune_iters

    @property
    def network_lr(self) -> float:
        return self.lr or {"grid": 1e-3, "mlp": 5e-4}[self.backbone]

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(asdict(self), indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> TrainConfig:
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read training config {path}: {exc}") from None
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InputError(f"{path}: unknown config fields {', '.join(unknown)}")
        return cls(**data)
