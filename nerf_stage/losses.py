"""Training losses of weight NeRFs: colours as a camera records them, weights (tone-mapped
for transport), and the Cauchy sparsity prior on optical thickness."""

from __future__ import annotations

import torch

from palette_core.basis import Basis

from .fields.base import tone_map

SPARSITY_SCALE = 0.01  # optical thickness of a step where the sparsity prior bends


def recorded_rgb_loss(rgb: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
    """L2 of (R, 3) colours through the weights against the images, as a camera records them:
    clipped at 1, so that a lamp of radiance 30 is not pulled down to the image's 1 (which
    would move its weight onto the materials' channels)."""
    return torch.mean((rgb.clamp(max=1) - images) ** 2)


def sparsity_loss(optical: torch.Tensor) -> torch.Tensor:
    """Cauchy sparsity prior: mean of log(1 + (tau / SPARSITY_SCALE)^2) over the (P,) optical
    thicknesses tau of the samples (the sparsity prior of Plenoxels, Fridovich-Keil et al.
    CVPR 2022, on thickness rather than density): steep for thin fog, flat for opaque
    surfaces; 0 for no samples."""
    return torch.log1p((optical / SPARSITY_SCALE) ** 2).sum() / max(1, len(optical))


def weight_loss(kind: str, values: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """L2 of (R, M) premultiplied weights; transport weights are tone-mapped first
    (``fields.base.tone_map``), so that emitters do not drown the rest."""
    if kind == Basis.TRANSPORT:
        values, targets = tone_map(values), tone_map(targets)
    return torch.mean((values - targets) ** 2)
