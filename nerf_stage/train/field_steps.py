"""The steps of the field backbones (grid, hash, mlp) for the one training loop
(``loop.Steps``): a batch of rays a step, the occupancy grid refined while the density
trains, and the two-stage switch to the palette stage.

Strategies (PaletteNeRF, sec. 3.3):

- ``two-stage``: P iterations on RGB, then the density part is frozen, the output
  layer replaced by one of M channels (first fitted alone, ``fit_output``), and
  the colour part fine-tuned on the weight images for F iterations (L2 loss).
- ``traditional``: the M-channel field trained from scratch on weights for P + F.
- ``rgb``: an RGB NeRF for P + F iterations (the baseline).
"""

from __future__ import annotations

from pathlib import Path

import torch

from palette_core.stack import WeightStack

from ..fields import RGB
from ..render.march import march_rays
from .appearance import exposure_free_weights
from .config import Strategy, TrainConfig
from .losses import depth_loss, distortion_loss, recorded_rgb_loss, sparsity_loss, weight_loss
from .metrics import psnr_from_mse
from .run import Run, save_checkpoint
from .schedule import set_rates

#: ``fit_output`` starts a channel at its mean weight, or at this where it is smaller.
MIN_START_WEIGHT = 1e-4
#: Pixels with a sparse point's depth added to each batch while the density trains
#: (``depth_weight``).
DEPTH_PIXELS = 512


class FieldSteps:
    """The steps of a field backbone (``loop.Steps``): RGB pretraining, then (two-stage) the
    palette stage with the density frozen, a new output layer fitted first (``fit_output``)
    and the targets made exposure-free at its start and at every checkpoint."""

    def __init__(self, run: Run, optimisers: list, rays: dict, stack: WeightStack,
                 generator: torch.Generator, depth: tuple | None):
        self.run, self.optimisers, self.rays, self.stack = run, optimisers, rays, stack
        self.generator, self.depth, self.finetuning = generator, depth, False
        device = run.device
        self.terms = torch.as_tensor(run.terms, dtype=torch.float32, device=device)
        self.background = torch.as_tensor(run.config.background, dtype=torch.float32,
                                          device=device)

    @property
    def stage(self) -> str:
        return str(self.run.field.kind)

    def before(self, it: int) -> None:
        run, config = self.run, self.run.config
        self.finetuning = config.strategy == Strategy.TWO_STAGE and it >= config.pretrain_iters
        if self.finetuning and run.field.kind == RGB:
            start_palette_stage(run)
            palette_targets(run, self.stack, self.rays)
            fit_output(run, self.rays, self.generator)
            self.optimisers = field_optimisers(run)
        elif self.finetuning and it % config.checkpoint_every == 0:
            palette_targets(run, self.stack, self.rays)

    def loss(self, it: int, progress: float) -> tuple[torch.Tensor, float]:
        """Iteration ``it``: refine the occupancy grid (while the density trains), set the
        learning rates, and the loss on a batch of pixels (and, while the density trains,
        ``DEPTH_PIXELS`` of the ``depth`` targets' pixels)."""
        run, config, generator = self.run, self.run.config, self.generator
        if run.field.refines_occupancy and not self.finetuning:
            settings = run.field.settings
            run.occupancy.update_every_n_steps(it, run.field, generator,
                                               settings.occupancy_every, settings.warmup_iters)
        set_rates(self.optimisers, progress, lambda g: g.setdefault("initial_lr", g["lr"]),
                  lambda g: config.lr_decay)
        batch, targets = pixel_batch(config, self.rays, generator), None
        if self.depth is not None and not self.finetuning:
            pick = torch.randint(len(self.depth[0]), (DEPTH_PIXELS,), generator=generator,
                                 device=batch.device)
            batch, targets = torch.cat([batch, self.depth[0][pick]]), self.depth[1][pick]
        run.field.train()
        return batch_loss(run, {key: value[batch] for key, value in self.rays.items()}, self.terms,
                     self.background, generator, targets)

    def update(self, loss: torch.Tensor, it: int) -> None:
        for optimiser in self.optimisers:
            optimiser.zero_grad(set_to_none=True)
        loss.backward()
        for optimiser in self.optimisers:
            optimiser.step()

    def extra(self) -> dict:
        return {}

    def save(self, path: Path) -> None:
        save_checkpoint(self.run, path, self.optimisers, self.generator)


def batch_loss(run: Run, rays: dict, terms, background, generator,
          targets: torch.Tensor | None = None) -> tuple[torch.Tensor, float]:
    """Loss of one batch of rays, and the PSNR of its colours (through the weights).

    L2 on RGB while the output is RGB, else ``losses.weight_loss``; plus, while the density
    trains, ``opacity_weight`` x L2 of the opacity against alpha and ``sparsity_weight``
    x ``losses.sparsity_loss``, in unbounded scenes ``distortion_weight`` x
    ``losses.distortion_loss``, and ``depth_weight`` x ``losses.depth_loss`` of the batch's
    last pixels against their depth ``targets``, where given.
    """
    values, acc, samples = run.render_pixels(rays["origins"], rays["directions"], generator)
    if run.field.kind == RGB:
        rgb = as_recorded(run, values + (1 - acc[:, None]) * background, rays)
        loss = torch.mean((rgb - rays["rgb"]) ** 2)
    else:
        loss = weight_loss(run.field.kind, values, rays["weights"])
        rgb = as_recorded(run, values @ terms + (1 - acc[:, None]) * background, rays)
        if run.config.rgb_weight:
            loss = loss + run.config.rgb_weight * recorded_rgb_loss(rgb, rays["rgb"])
    if acc.requires_grad:
        loss = loss + run.config.opacity_weight * torch.mean((acc - rays["alpha"]) ** 2)
        if run.config.sparsity_weight:
            loss = loss + run.config.sparsity_weight * sparsity_loss(samples.optical)
        if run.box.unbounded and run.config.distortion_weight:
            loss = loss + run.config.distortion_weight * distortion_loss(
                samples.ray, samples.t, samples.weight, run.sampling.step or 0.0, len(acc))
        if targets is not None:
            n = run.config.supersampling ** 2  # rays a pixel
            first = (len(acc) - len(targets)) * n
            tail = samples.ray >= first
            loss = loss + run.config.depth_weight * depth_loss(
                samples.ray[tail] - first, samples.t[tail], samples.weight[tail],
                targets.repeat_interleave(n))
    with torch.no_grad():
        mse = float(torch.mean((rgb.clamp(0, 1) - rays["rgb"]) ** 2))
    return loss, psnr_from_mse(max(mse, 1e-10))


def as_recorded(run: Run, rgb: torch.Tensor, rays: dict) -> torch.Tensor:
    """(B, 3) composited colours as the rays' training images recorded them: through their
    colour transforms when the run learns them (``appearance``), else as they are."""
    return rgb if run.appearance is None else run.appearance(rgb, rays["image"])


def pixel_batch(config: TrainConfig, rays: dict, generator: torch.Generator) -> torch.Tensor:
    """Random pixels of the ray bank, ``batch_rays`` rays in all (at least one pixel)."""
    pixels = max(1, config.batch_rays // config.supersampling ** 2)
    return torch.randint(len(rays["origins"]), (pixels,), generator=generator,
                         device=rays["origins"].device)


def start_palette_stage(run: Run) -> None:
    """Freeze the density part and put in a new M-channel output layer."""
    for p in run.field.density_parameters():
        p.requires_grad_(False)
    run.field.set_output(run.basis, run.record.channels)


def palette_targets(run: Run, stack: WeightStack, rays: dict) -> None:
    """Set the ray bank's weights to their exposure-free values under the current colour
    transforms, where the run learns them (``appearance.exposure_free_weights``): as
    fine-tuning starts and at every checkpoint, where a resumed run computes them too."""
    if run.appearance is None:
        return
    weights = exposure_free_weights(run.appearance, stack, rays["rgb"], rays["image"],
                                    rays["alpha"])
    if weights is not None:
        rays["weights"] = weights


def fit_output(run: Run, rays: dict, generator: torch.Generator, iterations: int = 100) -> None:
    """Fit the new output layer alone before fine-tuning starts.

    The frozen field is run once over a batch of training rays; the output layer's
    inputs at their visible samples (at the rays, for deferred fields) are cached, and the
    layer is fitted to the rays' weights (the training loss) by L-BFGS on that cache. This
    costs about one training step, and fine-tuning then starts near the RGB NeRF's
    batch PSNR instead of far below it (docs/decisions/0010-output-layer-fit.md).

    The layer starts at every channel's mean training weight (``Field.start_output``): from
    a random start, the first steps pushed a rare channel so far below zero on every ray
    that softplus left it no gradient, and the material it stands for was lost.
    """
    field = run.field
    field.start_output(rays["weights"].mean(0).clamp(min=MIN_START_WEIGHT))
    batch = pixel_batch(run.config, rays, generator)
    pixel_rays = rays["directions"].shape[1]
    directions = rays["directions"][batch].flatten(0, 1)
    with torch.no_grad():
        samples = march_rays(field, run.occupancy, rays["origins"][batch].flatten(0, 1),
                             directions, run.sampling).visible()
        features = field.head(*samples.colour_inputs(directions, field.deferred))
    targets = rays["weights"][batch]
    fit = torch.optim.LBFGS(field.output.parameters(), max_iter=iterations,
                            line_search_fn="strong_wolfe")

    def closure():
        fit.zero_grad()
        values = samples.composite_colours(field.colour_output(features), field.deferred)
        values = values.view(len(batch), pixel_rays, -1).mean(1)
        loss = weight_loss(field.kind, values, targets)
        loss.backward()
        return loss

    fit.step(closure)


def field_optimisers(run: Run) -> list[torch.optim.Optimizer]:
    """One Adam over the parameters being trained: voxel grids at the backbone's ``lr``,
    networks and the images' colour transforms at its ``network_lr`` (fused: one pass over
    each tensor per step)."""
    trained = [p for p in run.field.parameters() if p.requires_grad]
    grids = [p for p in run.field.grid_parameters() if p.requires_grad]
    networks = [p for p in trained if all(p is not g for g in grids)]
    backbone = run.config.backbone_config
    groups = [{"params": networks, "lr": backbone.network_lr}]
    if grids:
        groups.append({"params": grids, "lr": backbone.lr})
    if run.appearance is not None:
        groups.append({"params": list(run.appearance.parameters()), "lr": backbone.network_lr})
    return [torch.optim.Adam(groups, fused=True)]
