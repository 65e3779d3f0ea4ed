"""Tiny training settings shared by the weight-NeRF tests, and training without the CLI."""

from dataclasses import replace

import torch

from nerf_stage.backbone_settings import GridConfig, HashConfig, MLPConfig
from nerf_stage.data.dataset import load_dataset
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.trainer import train
from palette_core.stack import read_stack

TINY = {"occupancy_voxels": 6**3, "batch_rays": 64, "head_width": 16, "checkpoint_every": 2,
        "grid": GridConfig(voxels=12**3, warmup_iters=1, occupancy_every=1),
        "mlp": MLPConfig(samples=8),
        "hash": HashConfig(levels=4, log2_entries=10, finest=32, density_width=16, samples=24,
                           render_samples=48, warmup_iters=1, occupancy_every=1)}

#: The paper's per-sample diffuse colours, which bake.
PER_SAMPLE = replace(TINY["grid"], deferred=False, view_frequencies=None)
PER_SAMPLE_FLAGS = ["--no-grid-deferred", "--grid-view-frequencies", "none"]
#: ``nerf-stage train`` flags of a tiny run.
TINY_FLAGS = ["--pretrain-iters", "2", "--finetune-iters", "2", "--batch-rays", "64",
              "--grid-voxels", str(12**3), "--head-width", "16"]


def tiny_config(**changes) -> TrainConfig:
    return TrainConfig(**(TINY | {"pretrain_iters": 2, "finetune_iters": 2} | changes))


def trained(root, config, rundir, **kwargs):
    """Train on the CPU unless ``device`` says otherwise: bit-for-bit comparisons between
    runs need its deterministic kernels (CUDA's atomic adds reorder sums)."""
    dataset = load_dataset(root, config.background)
    return train(config, dataset, read_stack(root / "weights.npz"), rundir, progress=False,
                 **({"device": torch.device("cpu")} | kwargs))
