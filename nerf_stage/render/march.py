"""Ray marching and volume compositing of M channels.

Compositing does not care whether a sample carries 3 colour channels or M palette
weights: ``composite`` gives each sample its weight T_i alpha_i, and
``render_rays`` sums weight x value per ray. Weight renders come out premultiplied
by the accumulated opacity; a colour is ``weights @ basis + (1 - acc) background``.

All positions live in the normalised scene box (``scene_box.SceneBox``); empty space
is skipped with the occupancy grid (``occupancy.OccupancyGrid``).

References
----------
B. Mildenhall et al. NeRF. ECCV 2020, eq. 3 (quadrature of the volume rendering integral).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..fields.base import RaySampling
from . import contraction
from .occupancy import OccupancyGrid

TERMINATION = 1e-4  # samples behind less transmittance skip the colour part
SEGMENT = 32  # samples a ray marched at a time, between checks for termination (rendering)
#: Most (ray, sample) slots a training batch marches at a time: a batch whose longest ray
#: would need more is marched in segments, so that one long ray cannot make every ray of
#: its batch hold dense tensors of its length (memory bounded by design).
TRAIN_SLOTS = 1 << 21


def box_intersection(origins: torch.Tensor, directions: torch.Tensor, extent: torch.Tensor):
    """Entry and exit distances (R,) of rays through the box [-extent, extent]; near = far
    where a ray misses it."""
    inverse = 1.0 / torch.where(directions.abs() < 1e-9, torch.full_like(directions, 1e-9),
                                directions)
    t0, t1 = (-extent - origins) * inverse, (extent - origins) * inverse
    near = torch.clamp(torch.minimum(t0, t1).amax(-1), min=0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, torch.maximum(far, near)


def ray_interval(occupancy: OccupancyGrid, origins: torch.Tensor, directions: torch.Tensor):
    """(R,) where each ray's samples start and end in its marching parameter, and its bend
    (``contraction``; None in a bounded box, where the parameter is the distance)."""
    if not occupancy.contracted:
        return (*box_intersection(origins, directions, occupancy.extent), None)
    _, exits = box_intersection(origins, directions, torch.ones_like(occupancy.extent))
    return contraction.ray_interval(exits)


def composite(sigma: torch.Tensor, deltas: torch.Tensor,
              depth: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample weights T_i alpha_i and transmittances T_i, both (R, S), from densities and
    step lengths (NeRF eq. 3); ``depth`` (R,) is the optical depth in front of the first
    sample (0 by default).

    Examples
    --------
    >>> composite(torch.tensor([[0.0, 1e9, 1e9]]), torch.ones(1, 3))[0]
    tensor([[0., 1., 0.]])
    """
    optical = sigma * deltas
    before = torch.cumsum(torch.cat([torch.zeros_like(optical[:, :1]), optical[:, :-1]], dim=1),
                          dim=1)
    if depth is not None:
        before = before + depth[:, None]
    transmittance = torch.exp(-before)
    return transmittance * (1 - torch.exp(-optical)), transmittance


@dataclass
class Samples:
    """Samples along a batch of rays that fall in occupied cells, packed.

    Attributes
    ----------
    ray : (P,) int64
        The ray of each sample.
    h : (P, ...)
        The density part's output for the colour part.
    weight : (P,)
        Compositing weight T_i alpha_i.
    transmittance : (P,)
    optical : (P,)
        Optical thickness sigma x step of each sample's step.
    opacity : (R,)
        Accumulated opacity of each ray.
    t : (P,)
        Where each sample lies on its ray, in the ray's marching parameter (``ray_interval``).
    """

    ray: torch.Tensor
    h: torch.Tensor
    weight: torch.Tensor
    transmittance: torch.Tensor
    optical: torch.Tensor
    opacity: torch.Tensor
    t: torch.Tensor

    def visible(self) -> Samples:
        """The samples in front of ``TERMINATION`` transmittance (the others skip the colour
        part)."""
        keep = self.transmittance.detach() > TERMINATION
        return Samples(self.ray[keep], self.h[keep], self.weight[keep],
                       self.transmittance[keep], self.optical[keep], self.opacity, self.t[keep])

    def composite(self, values: torch.Tensor) -> torch.Tensor:
        """(P, C) per-sample values -> (R, C) composited along the rays."""
        out = torch.zeros(len(self.opacity), values.shape[-1], device=values.device,
                          dtype=values.dtype)
        return out.index_add(0, self.ray, self.weight[:, None] * values)

    def colour_inputs(self, directions: torch.Tensor,
                      deferred: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the colour part runs: each sample's ``h`` and its ray's direction, or, when
        ``deferred``, once a ray: its ``h`` composited and divided by its opacity, and its
        (R, 3) ``directions`` (deferred shading, Hedman et al. Baking neural radiance
        fields for real-time view synthesis. ICCV 2021)."""
        if not deferred:
            return self.h, directions[self.ray]
        opacity = self.opacity.detach().clamp(min=TERMINATION)[:, None]
        return self.composite(self.h) / opacity, directions

    def composite_colours(self, values: torch.Tensor, deferred: bool) -> torch.Tensor:
        """The colour part's outputs at ``colour_inputs`` -> (R, C) composited along the rays
        (premultiplied by opacity)."""
        return self.opacity[:, None] * values if deferred else self.composite(values)


def sample_positions(samples: Samples, occupancy: OccupancyGrid, origins: torch.Tensor,
                     directions: torch.Tensor) -> torch.Tensor:
    """(P, 3) where ``samples`` of rays ``origins``, ``directions`` (R, 3) lie in the normalised
    box coordinates, uncontracted (an unbounded scene's samples beyond the box are far away)
    and out of NDC."""
    if occupancy.ndc is not None:
        origins, directions = occupancy.ndc.rays(origins, directions)
        return occupancy.ndc.to_box(origins[samples.ray]
                                    + samples.t[:, None] * directions[samples.ray])
    _, _, bend = ray_interval(occupancy, origins, directions)
    t = samples.t
    if bend is not None:
        b = bend[samples.ray]
        t = torch.where(t <= b, t, b * b / (2 * b - t).clamp(min=1e-12))
    return origins[samples.ray] + t[:, None] * directions[samples.ray]


def scale_near_gradients(values: torch.Tensor, t: torch.Tensor, near: float) -> torch.Tensor:
    """``values`` (P, ...) unchanged, their gradients scaled by min(1, (t / near)^2) at the
    samples' distances ``t`` (P,) from the camera: a point close to a camera covers many of
    its pixels, so without this its gradients outweigh those of the views that see it
    from afar, and it learns to be a floater (Philip and Deschaintre. Floaters no more:
    radiance field gradient scaling for improved near-camera training. EGSR 2023)."""
    scale = (t / near).clamp(max=1).square().view(-1, *(1,) * (values.dim() - 1))
    return values * scale + (values * (1 - scale)).detach()


def march_rays(field, occupancy: OccupancyGrid, origins: torch.Tensor, directions: torch.Tensor,
               sampling: RaySampling, generator: torch.Generator | None = None,
               near_gradient: float | None = None) -> Samples:
    """Sample rays and run the density part where the occupancy grid is occupied.

    Samples are spaced ``sampling.step`` apart from where a ray enters the box
    (grids), or ``sampling.count`` evenly across the box (MLPs), in the ray's marching
    parameter (``ray_interval``: the distance, or, in an unbounded scene, a parameter
    whose steps are about as long in the contracted space); ``generator``
    jitters them (training). Stepped rays start marching in whole steps past the empty
    space in front of them (``OccupancyGrid.skip_empty``), so their samples stay where
    they were; samples in empty cells skip the field. ``near_gradient`` scales the
    gradients of samples nearer than it to the camera (``scale_near_gradients``; the
    parameter is the distance up to one box half size, so any ``near_gradient`` <= 1
    works in unbounded scenes too). In NDC space (``occupancy.ndc``) the rays are mapped into
    the NDC cube first and marched there as in a box. Without gradients (rendering),
    rays are marched ``SEGMENT`` samples at a time, a ray whose transmittance has
    fallen below ``TERMINATION`` is not marched further (early ray termination), and
    stepped rays skip empty space again after each segment (past a floater to the
    surface behind it); with gradients, in one pass (each pass of a grid backbone
    costs a backward over its whole grids) unless the batch's longest ray would make it
    hold more than ``TRAIN_SLOTS`` samples, then in segments as in rendering. With
    ``sampling.sky`` (an unbounded scene whose training pixels are all opaque), each ray
    that light still reaches ends in an opaque sample at infinity (``_sky_samples``).

    Parameters
    ----------
    origins, directions : (R, 3)
        Normalised coordinates; unit directions.
    """
    if occupancy.ndc is not None:
        origins, directions = occupancy.ndc.rays(origins, directions)
    near, far, bend, n_samples, deltas = _spacing(occupancy, origins, directions, sampling)
    jitter = (torch.full_like(near[:, None], 0.5) if generator is None else
              torch.rand(len(near), 1, generator=generator, device=near.device))
    depth = torch.zeros_like(near)  # optical depth marched so far
    first = torch.zeros_like(near)  # each ray's next sample, counted in steps from near
    alive = torch.arange(len(near), device=near.device)
    parts = []
    segment = (min(n_samples, max(SEGMENT, TRAIN_SLOTS // max(len(near), 1)))
               if torch.is_grad_enabled() else min(SEGMENT, n_samples))
    offsets = torch.arange(segment, device=near.device, dtype=near.dtype)
    while True:
        enter, step, leave = near[alive, None], deltas[alive, None], far[alive, None]
        t = enter + (first[alive, None] + offsets + jitter[alive]) * step  # (A, S)
        points = contraction.ray_points(origins[alive, None], directions[alive, None], t,
                                        None if bend is None else bend[alive, None])  # (A, S, 3)
        valid = (t < leave) & occupancy.lookup(points)
        row, sample = torch.nonzero(valid, as_tuple=True)
        sigma_packed, h = field.density(points[row, sample])
        if near_gradient is not None:
            sigma_packed, h = (scale_near_gradients(x, t[row, sample], near_gradient)
                               for x in (sigma_packed, h))
        sigma = torch.zeros_like(t).index_put((row, sample), sigma_packed)
        weights, transmittance = composite(sigma, step.expand_as(t), depth[alive])
        parts.append((alive[row], h, weights[row, sample], transmittance[row, sample],
                      sigma_packed * step[row, 0], t[row, sample]))
        depth = depth.index_add(0, alive, (sigma * step).sum(1))
        first[alive] += segment
        at = near[alive] + first[alive] * deltas[alive]
        alive = alive[(depth[alive].detach() < -math.log(TERMINATION)) & (at < far[alive])]
        if sampling.step is not None and len(alive) and segment < n_samples:
            at = near[alive] + first[alive] * sampling.step  # across empty space again
            moved = occupancy.skip_empty(origins[alive], directions[alive], at, far[alive],
                                         sampling.step, None if bend is None else bend[alive])
            first[alive] += torch.round((moved - at) / sampling.step)
            alive = alive[moved < far[alive]]
        if len(alive) == 0:
            break
    if sampling.sky:
        parts.append(_sky_samples(field, origins, directions, far, bend, depth))
        depth = depth.masked_fill(depth.detach() < -math.log(TERMINATION), math.inf)
    ray, h, weight, transmittance, optical, t = (torch.cat(part) for part in zip(*parts))
    if sampling.sky:  # each ray's sky sample after its others
        order = torch.argsort(ray, stable=True)
        ray, h, weight, transmittance, optical, t = (
            x[order] for x in (ray, h, weight, transmittance, optical, t))
    return Samples(ray, h, weight, transmittance, optical, 1 - torch.exp(-depth), t)


def _spacing(occupancy: OccupancyGrid, origins: torch.Tensor, directions: torch.Tensor,
             sampling: RaySampling) -> tuple:
    """Where ``march_rays`` samples each ray: its (R,) marching interval ``near`` to ``far``
    (past the empty space in front, for stepped rays) and ``bend`` (``ray_interval``), the
    most samples a ray takes and the (R,) step between them."""
    near, far, bend = ray_interval(occupancy, origins, directions)
    if sampling.step is None:
        return near, far, bend, sampling.count, (far - near) / sampling.count
    near = occupancy.skip_empty(origins, directions, near, far, sampling.step, bend)
    n_samples = max(1, int(torch.ceil((far - near).max() / sampling.step)))
    return near, far, bend, n_samples, torch.full_like(near, sampling.step)


def _sky_samples(field, origins, directions, far, bend, depth) -> tuple:
    """The sky of an unbounded scene: every ray that light still reaches ends on the boundary
    of the contracted space (or where it leaves the NDC cube), which takes all the light
    left (``march_rays``'s parts).

    The point where a ray ends depends only on its direction, so the field's colour there is
    a map of the sky at infinity (as the last sample of NeRF takes an infinite step, eq. 3).
    Without it, rays that see the sky could only end in fog, which training views do not see
    against the sky but views from elsewhere do."""
    ends = torch.nonzero(depth.detach() < -math.log(TERMINATION), as_tuple=True)[0]
    points = contraction.ray_points(origins[ends], directions[ends], far[ends],
                                    None if bend is None else bend[ends])
    _, h = field.density(points)
    light = torch.exp(-depth[ends])
    return ends, h, light, light, torch.zeros_like(light), far[ends]


def render_rays(field, occupancy: OccupancyGrid, origins: torch.Tensor,
                directions: torch.Tensor, sampling: RaySampling,
                generator: torch.Generator | None = None,
                near_gradient: float | None = None) -> tuple[torch.Tensor, Samples]:
    """Composite the field's outputs along rays (``march_rays``); samples behind
    ``TERMINATION`` transmittance skip the colour part (``Samples.visible``), which runs
    on each sample or, for a ``deferred`` field, once a ray (``Samples.colour_inputs``).

    Returns
    -------
    values : (R, C)
        Composited outputs, premultiplied by opacity.
    samples : Samples
        All the rays' samples in occupied cells; ``samples.opacity`` (R,) is the
        accumulated opacity.
    """
    samples = march_rays(field, occupancy, origins, directions, sampling, generator,
                         near_gradient)
    visible = samples.visible()
    values = field.colour(*visible.colour_inputs(directions, field.deferred))
    return visible.composite_colours(values, field.deferred), samples
