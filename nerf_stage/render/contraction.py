"""Unbounded scenes: everything beyond the scene box contracted into a shell around it.

A point x of the normalised box coordinates (the box is the cube [-1, 1]^3) maps to

    contract(x) = x                          if ||x||_inf <= 1
                  (2 - 1 / ||x||_inf) x / ||x||_inf   otherwise,

so that all of space fits in [-2, 2]^3, where fields and the occupancy grid live
(mip-NeRF 360, eq. 10, with the infinity norm as nerfstudio's ``SceneContraction``).
Rays are marched in a parameter u: u = t (linear) up to the ray's ``bend``, where it
leaves the box (at least one box half size from its origin), then linearly in disparity,
t = bend^2 / (2 bend - u), out to ``FAR`` bends (the sky). A step in u then moves a sample
about a step in the contracted space, in the box and in the shell alike.

References
----------
J. T. Barron et al. Mip-NeRF 360: unbounded anti-aliased neural radiance fields. CVPR
2022 (contraction, sampling linear in disparity).
M. Tancik et al. Nerfstudio. SIGGRAPH 2023 (``UniformLinDispPiecewiseSampler``).
"""

from __future__ import annotations

import torch

#: The contracted space is [-EXTENT, EXTENT]^3.
EXTENT = 2.0
#: Rays end this many bends from their origin.
FAR = 1000.0


def contract(x: torch.Tensor) -> torch.Tensor:
    """(..., 3) normalised positions -> (..., 3) contracted positions in [-2, 2]^3.

    Examples
    --------
    >>> contract(torch.tensor([[0.5, -1.0, 0.0], [4.0, 0.0, -2.0], [1e9, 0.0, 0.0]]))
    tensor([[ 0.5000, -1.0000,  0.0000],
            [ 1.7500,  0.0000, -0.8750],
            [ 2.0000,  0.0000,  0.0000]])
    """
    norm = x.abs().amax(-1, keepdim=True).clamp(min=1.0)
    return (2 - 1 / norm) * x / norm


def ray_interval(exits: torch.Tensor):
    """(R,) start and end of each ray in u, and its ``bend``, from the (R,) distances at
    which the rays leave the box."""
    bend = exits.clamp(min=1.0)
    return torch.zeros_like(bend), bend * (2 - 1 / FAR), bend


def parameter(t: torch.Tensor, bend: torch.Tensor) -> torch.Tensor:
    """The u of distance ``t`` along rays of ``bend`` (the inverse of ``distance``)."""
    return torch.where(t <= bend, t, 2 * bend - bend * bend / t.clamp(min=1e-12))


def distance(u: torch.Tensor, bend: torch.Tensor) -> torch.Tensor:
    """The distance t along rays of ``bend`` at parameter ``u`` (the inverse of
    ``parameter``)."""
    return torch.where(u <= bend, u, bend * bend / (2 * bend - u).clamp(min=1e-12))


def ray_points(origins: torch.Tensor, directions: torch.Tensor, u: torch.Tensor,
               bend: torch.Tensor | None) -> torch.Tensor:
    """Positions (..., 3) of the samples at ``u`` (...) on rays with origins and directions
    (..., 3): contracted, with each ray's ``bend`` (...) broadcast against ``u``, or, when
    ``bend`` is None (a bounded box), o + u d."""
    if bend is None:
        return origins + u[..., None] * directions
    return contract(origins + distance(u, bend)[..., None] * directions)
