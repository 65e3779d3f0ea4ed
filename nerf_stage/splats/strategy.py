"""Adaptive density control of trained splats (3D Gaussian splatting, Sec. 5.2): splats
whose screen-space position is pulled hard are cloned (small) or split in two (large), as
are splats that the rasteriser cut off at its reach (too wide on screen: gsplat's
screen-size refinement), nearly transparent and oversized ones are removed, and every
opacity is reset now and then so that splats in front of others have to earn their opacity
again.

The training loop calls ``after_backward`` once a step; the strategy edits the model's
parameters and the optimiser's moments together (new rows start with no moments).

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (the thresholds are theirs).
V. Ye et al. gsplat: an open-source library for Gaussian splatting. JMLR 2025
(``DefaultStrategy``: the same control as a separate object with a step hook).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from palette_core.errors import InputError

from ..backbone_settings import SplatConfig
from .model import rotation_matrices

SPLIT_SHRINK = 1.6  # a split splat's two halves are this many times smaller (3DGS's 0.8 x 2)
#: Densification grows the splats to at most one for this many training pixels: past it,
#: most splats are drawn strongly by no training view, and each step and the palette stage
#: cost more than the splats give (docs/decisions/0012-splat-densification.md).
PIXELS_PER_SPLAT = 10


@dataclass
class Densification:
    """The control's settings, the cameras' ``extent`` (normalised units), the most splats
    it grows to (``limit``), the schedule (``start``, ``every``, ``reset``: ``for_stage``;
    densifying until ``settings.refine_stop`` of the stage) and the screen-space gradients
    gathered since the last densification."""

    settings: SplatConfig
    extent: float
    limit: int
    start: int
    every: int
    reset: int
    grad2d: torch.Tensor | None = field(default=None, repr=False)
    count: torch.Tensor | None = field(default=None, repr=False)
    clipped: torch.Tensor | None = field(default=None, repr=False)

    @classmethod
    def for_stage(cls, settings: SplatConfig, extent: float, iterations: int,
                  pixels: int) -> Densification:
        """The control of an RGB stage of ``iterations`` on ``pixels`` training pixels in
        all: on the settings' schedule, scaled down to a stage shorter than
        ``schedule_iters``, to at most ``max_splats`` splats and one for ``PIXELS_PER_SPLAT``
        pixels."""
        scale = (min(1.0, iterations / settings.schedule_iters) if settings.schedule_iters
                 else 1.0)
        return cls(settings, extent, min(settings.max_splats, pixels // PIXELS_PER_SPLAT),
                   round(settings.refine_start * scale),
                   max(1, round(settings.refine_every * scale)),
                   max(1, round(settings.reset_every * scale)))

    def after_backward(self, model, optimiser: torch.optim.Optimizer, info: dict, step: int,
                       progress: float, width: int, height: int,
                       generator: torch.Generator | None = None) -> None:
        """Gather the gradients of step ``step``, ``progress`` through its stage
        (``schedule.stage_progress``: its iterations' share or, when a clock ends the stage,
        its time's if more), from ``rasterise.draw``'s ``info`` of a view of ``width`` x
        ``height``; then densify, prune and reset as the schedule says, until
        ``refine_stop`` of the stage. Split splats' halves are placed by the (CPU)
        ``generator``, the run's, so that a resumed run splits as the uninterrupted one."""
        if progress >= self.settings.refine_stop:
            return
        self._gather(model, info, width, height)
        if step > self.start and step % self.every == 0:
            self._grow(model, optimiser, generator)
            self._prune(model, optimiser, oversized=step > self.reset)
            self.grad2d = self.count = self.clipped = None
        if step % self.reset == 0 and step > 0:
            self._reset_opacities(model, optimiser)

    def state(self) -> dict[str, torch.Tensor]:
        """The running totals since the last densification (gsplat's strategy state), for
        the checkpoint; empty when none is gathered."""
        if self.grad2d is None:
            return {}
        return {"grad2d": self.grad2d, "count": self.count, "clipped": self.clipped}

    def load_state(self, state: dict, means: torch.Tensor) -> None:
        """Continue from a checkpoint's ``state`` (``state``) of the model of ``means``.

        Raises
        ------
        InputError
            If the totals are not one (splats,) tensor each, as ``state`` writes them.
        """
        if not state:
            return
        kinds = {"grad2d": torch.float32, "count": torch.float32, "clipped": torch.bool}
        if set(state) != set(kinds) or any(
                not isinstance(state[k], torch.Tensor) or state[k].shape != (len(means),)
                or state[k].dtype != dtype for k, dtype in kinds.items()):
            raise InputError("the checkpoint's densification totals do not fit its splats")
        self.grad2d, self.count, self.clipped = (state[k].to(means.device) for k in kinds)

    def _gather(self, model, info: dict, width: int, height: int) -> None:
        n = len(model.means)
        if self.grad2d is None:
            self.grad2d = model.means.new_zeros(n)
            self.count = model.means.new_zeros(n)
            self.clipped = torch.zeros(n, dtype=torch.bool, device=model.means.device)
        if "clipped" in info:
            self.clipped[info["clipped"]] = True
        means2d = info.get("means2d")
        if means2d is None or means2d.grad is None:
            return
        # in normalised image units ([-1, 1] across the view), as 3D Gaussian splatting's
        grad = means2d.grad * means2d.new_tensor([width / 2, height / 2])
        self.grad2d.index_add_(0, info["front"], grad.norm(dim=1))
        self.count.index_add_(0, info["drawn"], torch.ones_like(info["drawn"], dtype=grad.dtype))

    @torch.no_grad()
    def _grow(self, model, optimiser, generator: torch.Generator | None = None) -> None:
        settings = self.settings
        mean = self.grad2d / self.count.clamp(min=1)
        high = mean > settings.grow_grad2d
        room = self.limit - len(model.means)
        if room <= 0 or not (high | self.clipped).any():
            return
        small = torch.exp(model.scales).max(1).values <= settings.grow_scale * self.extent
        clone, split = high & small & ~self.clipped, (high & ~small) | self.clipped
        high = high | self.clipped
        wanted = int(clone.sum() + split.sum())  # each adds one splat
        if wanted > room:  # the strongest gradients first
            keep = torch.zeros_like(high)
            keep[torch.argsort(torch.where(high, mean, -1.0), descending=True)[:room]] = True
            clone, split = clone & keep, split & keep
        clone_ids, split_ids = torch.nonzero(clone)[:, 0], torch.nonzero(split)[:, 0]
        scales = torch.exp(model.scales[split_ids])
        offsets = torch.randn(2, len(split_ids), 3, generator=generator).to(scales.device) * scales
        rotation = rotation_matrices(model.quats[split_ids])
        moved = model.means[split_ids] + torch.einsum("sij,nsj->nsi", rotation, offsets)

        def rows(name: str, old: torch.Tensor) -> torch.Tensor:
            halves = old[split_ids].repeat(2, *[1] * (old.dim() - 1))
            if name == "means":
                halves = moved.reshape(-1, 3)
            elif name == "scales":
                halves = halves - torch.log(torch.tensor(SPLIT_SHRINK))
            kept = torch.ones(len(old), dtype=torch.bool, device=old.device)
            kept[split_ids] = False
            return torch.cat([old[kept], old[clone_ids], halves])

        def moments(old: torch.Tensor) -> torch.Tensor:
            kept = torch.ones(len(old), dtype=torch.bool, device=old.device)
            kept[split_ids] = False
            zeros = old.new_zeros((len(clone_ids) + 2 * len(split_ids), *old.shape[1:]))
            return torch.cat([old[kept], zeros])

        edit_rows(model, optimiser, rows, moments)

    @torch.no_grad()
    def _prune(self, model, optimiser, oversized: bool) -> None:
        settings = self.settings
        drop = torch.sigmoid(model.opacities) < settings.prune_opacity
        if oversized:
            drop |= torch.exp(model.scales).max(1).values > settings.prune_scale * self.extent
        if drop.all():  # an empty model cannot train on: keep the most opaque
            drop[torch.argmax(model.opacities)] = False
        if drop.any():
            edit_rows(model, optimiser, lambda name, old: old[~drop], lambda old: old[~drop])

    @torch.no_grad()
    def _reset_opacities(self, model, optimiser) -> None:
        ceiling = torch.logit(torch.tensor(2 * self.settings.prune_opacity)).item()

        def rows(name: str, old: torch.Tensor) -> torch.Tensor:
            return old.clamp(max=ceiling) if name == "opacities" else old

        edit_rows(model, optimiser, rows, None, only="opacities")


def edit_rows(model: nn.Module, optimiser: torch.optim.Optimizer, rows, moments,
              only: str | None = None) -> None:
    """Replace each splat parameter of ``model`` (one a parameter group of ``optimiser``,
    named by the group's ``name``) by ``rows(name, old)``, and its Adam moments by
    ``moments(old)`` (zeroed when ``moments`` is None); ``only``: that parameter alone.
    Groups of parameters that are not the model's (the run's appearance) are left alone."""
    for group in optimiser.param_groups:
        name, (old,) = group["name"], group["params"]
        if (only is not None and name != only) or getattr(model, name, None) is not old:
            continue
        new = nn.Parameter(rows(name, old.detach()), requires_grad=old.requires_grad)
        state = optimiser.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = (moments(state[key]) if moments is not None
                              else torch.zeros_like(state[key]))
            optimiser.state[new] = state
        group["params"] = [new]
        setattr(model, name, new)
