"""Tiny splat scenes the splat tests share: a 12 x 10 camera, its pose and a few random
splats in front of it (torch is imported: only for tests that skip without it)."""

import numpy as np
import torch

from nerf_stage.data.cameras import Intrinsics, look_at
from nerf_stage.splats.model import covariances

PIXELS = 10**6  # training pixels in all: no bound on the splats
CAMERA = Intrinsics(width=12, height=10, fx=14.0, fy=14.0, cx=6.0, cy=5.0)
POSE = torch.as_tensor(look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3)), dtype=torch.float64)


def few_splats(n=5, seed=0, dtype=torch.float64):
    """``n`` splats around the origin, in front of ``POSE``, with random shapes."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 0.8
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = 0.08 + 0.15 * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.3 + 0.6 * torch.rand(n, generator=g, dtype=dtype)
    values = torch.rand(n, 4, generator=g, dtype=dtype)
    return means, covariances(quats, scales), values, opacities
