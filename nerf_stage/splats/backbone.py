"""The ``splats`` backbone: a weight NeRF's run whose model is 3D Gaussians trained from the
images themselves, so that what the studio draws and what the PLY holds is the model that
was trained, not a bake of a field (docs/splats.md).

Two stages, as the paper trains a field: first RGB (positions, shapes, opacities and a
view-dependent colour in spherical harmonics, with adaptive density control, one training
image an iteration, L1 and 1 - SSIM), then the palette weights of every splat with its
geometry frozen. A splat's weights are an editable part, on the simplex for the additive
basis (a softmax; ``fields.base.ACTIVATIONS``), plus a view-dependent residual in spherical
harmonics of degree 1 to ``sh_degree`` that sums to zero over the channels, so that the
weights of every view still sum to one; recolouring stays linear (``weights @ basis``).
The residual's share of the weights is reported (``SplatRun.residual_share``).

Coordinates are the scene box's normalised ones (``scene_box.SceneBox``); the run's
``splats()`` gives them in the world.

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (initial scales, learning rates, the loss, the degree schedule).
Z. Kuang et al. PaletteNeRF: palette-based appearance editing of neural radiance fields.
CVPR 2023 (the two stages, the view-dependent residual beside the palette weights).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from palette_core.basis import Basis, n_terms
from palette_core.errors import InputError
from palette_core.weights import stack_colour_weights

from ..backbone_settings import SplatConfig
from ..data.dataset import Dataset
from ..fields.base import RGB, inverse_tone_map, tone_map
from ..render.scene_box import SceneBox, visual_hull
from ..train.appearance import Appearance, exposure_free_weights
from ..train.checkpoint import CHECKPOINT, load_optimisers
from ..train.config import Strategy, TrainConfig
from ..train.loop import train_loop
from ..train.losses import recorded_rgb_loss, ssim_loss, weight_loss
from ..train.metrics import psnr_from_mse
from ..train.run import CONFIG, RunRecord, default_device
from ..train.schedule import set_rates
from .footprints import (
    PAIRS_AT_ONCE,
    Footprint,
    TrainingView,
    Window,
    patch,
    training_views,
    view_pairs,
)
from .rasterise import draw
from .run import SplatModel, SplatRun, load_run, save_checkpoint
from .sh import SH_C0
from .start import (
    HULL_CELLS,
    MIN_POINTS,
    PIXELS_PER_INITIAL,
    START_REACH,
    SeenViews,
    initial_splats,
)
from .strategy import Densification

__all__ = ["load_run", "train"]

#: The factor the centres' rate decays to over the RGB stage (3D Gaussian splatting's).
MEANS_DECAY = 0.01


def train(config: TrainConfig, dataset: Dataset, stack, rundir: Path, weights: np.ndarray,
          state: dict | None, box: SceneBox, weights_path: str = "", progress: bool = True,
          device: torch.device | None = None) -> SplatRun:
    """Train (or, given a checkpoint's ``state``, resume) a splat run in ``box`` on the
    training frames' ``weights`` and write its run folder (``trainer.train`` hands them
    over): RGB for ``pretrain_iters``, then the palette weights for ``finetune_iters``
    (``two-stage``); ``rgb`` stops after the first (``traditional`` is not offered:
    ``TrainConfig`` refuses it)."""
    device = device or default_device()
    train_ids = dataset.indices("train")
    run = (load_run(state, str(rundir / CHECKPOINT), device) if state is not None else
           _started_run(config, dataset, stack, box, train_ids, device))
    run.record.weights = weights_path
    if config.appearance and run.appearance is None:
        run.appearance = Appearance(len(train_ids)).to(device)
    views = training_views(run, dataset, train_ids, weights, device)
    del weights  # the views hold them, until the palette stage's replace them
    rundir.mkdir(parents=True, exist_ok=True)
    config.save(rundir / CONFIG)
    steps = SplatSteps(run, views, stack, sum(v.alpha.numel() for v in views))
    if state is not None:
        steps.resume(state, rundir)
    last = config.pretrain_iters if config.strategy == Strategy.RGB else config.total_iters
    train_loop(config, steps, rundir, last, "splats", progress)
    return run


def _started_run(config: TrainConfig, dataset: Dataset, stack, box: SceneBox, train_ids,
                 device) -> SplatRun:
    """A new run in ``box``, its splats started from the capture's points and where its
    views look (``start.initial_splats``)."""
    settings = config.splats
    generator = torch.Generator().manual_seed(config.seed)
    channels = n_terms(len(stack.palette), stack.basis, stack.order)
    record = RunRecord(str(Path(dataset.root).resolve()), channels=channels,
                       stack_meta=stack.meta, frames_outside=dataset.frames_outside,
                       downscale=dataset.downscale)
    points = dataset.points if dataset.points is not None and len(
        dataset.points) >= MIN_POINTS else None
    pixels = min(dataset.camera(i).width * dataset.camera(i).height for i in train_ids)
    initial = (settings.initial if points is not None
               else max(4, min(settings.initial, pixels // PIXELS_PER_INITIAL)))
    poses, cameras = dataset.poses[train_ids], dataset.cameras(train_ids)
    alpha = dataset.alpha[train_ids]
    hull = (visual_hull(box, np.full(3, HULL_CELLS), poses, cameras, alpha)
            if not box.unbounded and (alpha < 1).any() else None)
    seen = SeenViews(poses, cameras, dataset.images[train_ids], alpha,
                     hull if hull is not None and hull.any() else None)
    eyes = (poses[:, :3, 3] - box.centre) / box.scale
    focal = max(max(c.fx, c.fy) for c in cameras)
    model = SplatModel(initial_splats(box, initial, settings.sh_degree, generator, seen,
                                      points, eyes, START_REACH * settings.reach / focal),
                       RGB, settings.sh_degree)
    return SplatRun(config, box, dataset.intrinsics, np.asarray(stack.palette, np.float64),
                    stack.basis, stack.order, record, model.to(device))


class SplatSteps:
    """The steps of the splats backbone (``loop.Steps``): one training view (a random patch
    of it in the RGB stage) a step; densification after each RGB step; at the palette
    stage's start the geometry frozen, the weights started where the RGB stage ended
    (``_start_palette``), the colour transforms frozen, the targets made exposure-free and
    the views' footprints made (``_palette_targets``)."""

    def __init__(self, run: SplatRun, views: list, stack, pixels: int):
        config, device = run.config, run.device
        self.run, self.views, self.stack = run, views, stack
        self.extent = 1.1 * float(max(torch.linalg.norm(v.pose[:3, 3]) for v in views))
        self.optimiser = _optimiser(run, self.extent)
        self.strategy = Densification.for_stage(config.splats, self.extent,
                                                config.pretrain_iters, pixels)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.window = Window([])  # the RGB stage holds no footprint
        self.terms = torch.as_tensor(run.terms, dtype=torch.float32, device=device)
        self.background = torch.as_tensor(config.background, dtype=torch.float32, device=device)
        self.view, self.info, self.progress = None, {}, 0.0

    def resume(self, state: dict, rundir: Path) -> None:
        """Continue from a checkpoint's ``state``: the optimiser, the random state, the
        densification's totals and the palette stage's window."""
        load_optimisers([self.optimiser], state["optimisers"], rundir)
        self.generator.set_state(state["generator"])
        training = state.get("training")
        training = training if isinstance(training, dict) else {}
        self.strategy.load_state(training.get("densification") or {}, self.run.model.means)
        if self.run.kind != RGB:
            window = training.get("window")
            start, visits = ((window.get("start", 0), window.get("visits", 0))
                             if isinstance(window, dict) else (0, 0))
            if not all(isinstance(v, int) and v >= 0 for v in (start, visits)):
                raise InputError("the checkpoint's palette-stage window is not two counts")
            self._palette_targets(start % len(self.views), visits)

    @property
    def stage(self) -> str:
        return str(self.run.kind)

    def before(self, it: int) -> None:
        run, config = self.run, self.run.config
        if it >= config.pretrain_iters and run.kind == RGB:
            _start_palette(run, self.views, self.stack)
            self._palette_targets()
            self.optimiser = _optimiser(run, self.extent)

    def _palette_targets(self, start: int = 0, visits: int = 0) -> None:
        """The palette stage's colour transforms frozen (on one view a step, Adam moved
        every image's transform, and the training views drifted from the held-out ones:
        docs/splats.md), the views' weights made exposure-free under them, and the window
        of footprints from view ``start`` on, ``visits`` steps into it."""
        if self.run.appearance is not None:
            self.run.appearance.requires_grad_(False)
        _exposure_free(self.run, self.stack, self.views)
        self.window = Window.made(self.run, self.views, start, visits)

    def loss(self, it: int, progress: float) -> tuple[torch.Tensor, float]:
        run, generator = self.run, self.generator
        index, footprint = self.window.pick(run, self.views, generator)
        self.progress = progress
        _set_rates(self.optimiser, run.config, self.extent, it, progress)
        view = self.views[index] if footprint else patch(self.views[index],
                                                         run.config.splats.patch, generator)
        self.view, self.info = view, {}
        return _loss(run, view, self.terms, self.background, it, self.info, footprint)

    def update(self, loss: torch.Tensor, it: int) -> None:
        self.optimiser.zero_grad(set_to_none=True)
        loss.backward()
        if self.run.kind == RGB:
            self.strategy.after_backward(self.run.model, self.optimiser, self.info, it + 1,
                                         self.progress, self.view.window[2],
                                         self.view.window[3], self.generator)
        self.optimiser.step()

    def extra(self) -> dict:
        return {"splats": len(self.run.model.means)}

    def save(self, path: Path) -> None:
        save_checkpoint(self.run, path, self.optimiser, self.generator,
                        {"densification": self.strategy.state(), "window": self.window.state()})


def _loss(run: SplatRun, view: TrainingView, terms, background, it: int, info: dict,
          footprint: Footprint | None = None) -> tuple[torch.Tensor, float]:
    """Loss of one training view and the PSNR of its colours (through the weights in the
    palette stage, from the view's ``footprint`` when it has one); ``info`` receives what
    densification needs (``rasterise.draw``)."""
    model, config = run.model, run.config
    if footprint is None:
        degree = min(model.degree, it // config.splats.sh_every) if model.kind == RGB else None
        covariance, opacity = model.gaussians()
        values, acc = draw(model.means, covariance, model.values(view.pose[:3, 3], degree),
                           opacity, view.pose, view.camera, config.splats.reach, info,
                           view.window)
    else:
        values, acc = footprint.draw(model.values(view.pose[:3, 3])), footprint.opacity
    w, h = view.window[2:]
    values, acc = values.view(h, w, -1), acc.view(h, w)
    if model.kind == RGB:
        rgb = _as_recorded(run, values + (1 - acc[..., None]) * background, view)
        ssim = config.splats.ssim_weight
        loss = ((1 - ssim) * torch.mean(torch.abs(rgb - view.rgb))
                + ssim * ssim_loss(rgb, view.rgb)
                + config.opacity_weight * torch.mean((acc - view.alpha) ** 2))
    else:
        rgb = _as_recorded(run, values @ terms + (1 - acc[..., None]) * background, view)
        loss = weight_loss(model.kind, values, view.weights)
        if config.rgb_weight:
            loss = loss + config.rgb_weight * recorded_rgb_loss(rgb, view.rgb)
    with torch.no_grad():
        mse = float(torch.mean((rgb.clamp(0, 1) - view.rgb) ** 2))
    return loss, psnr_from_mse(max(mse, 1e-10))


def _as_recorded(run: SplatRun, rgb: torch.Tensor, view: TrainingView) -> torch.Tensor:
    """(H, W, 3) colours as the view's image recorded them (``appearance``)."""
    if run.appearance is None:
        return rgb
    image = torch.full((rgb.shape[0] * rgb.shape[1],), view.image, device=rgb.device)
    return run.appearance(rgb.reshape(-1, 3), image).view(rgb.shape)


def _exposure_free(run: SplatRun, stack, views: list) -> None:
    """Give the palette stage's training ``views`` (in place) their weights exposure-free
    under the colour transforms where the run learns them
    (``appearance.exposure_free_weights``): as the stage starts, and as a resumed run
    continues it; a view at a time, so that one view's pixels are computed and one view's
    weights are held twice at once."""
    if run.appearance is None:
        return
    for n, view in enumerate(views):
        image = torch.full((view.alpha.numel(),), view.image, device=view.alpha.device)
        weights = exposure_free_weights(run.appearance, stack, view.rgb.reshape(-1, 3), image,
                                        view.alpha.flatten())
        if weights is None:
            return
        views[n] = replace(view, weights=weights.view(view.weights.shape))


@torch.no_grad()
def _start_palette(run: SplatRun, views: list, stack) -> None:
    """Freeze the geometry and start the palette weights where the RGB stage ended: from
    each splat's own colour for an additive ``stack`` (``_colour_start``), from the light
    each splat sends to the training ``views``' weights otherwise (``_light_start``)."""
    weights, residual = _colour_start(run.model, stack) if (
        stack.basis == Basis.ADDITIVE) else (_light_start(run, views), None)
    run.model.set_output(run.basis, weights, residual)


def _colour_start(model, stack) -> tuple[torch.Tensor, torch.Tensor]:
    """(S, K) weights and (S, B - 1, K) residual that give each splat the colour the RGB
    stage gave it: the stack's weights of its view-independent colour
    (``weights.stack_colour_weights``), and its view-dependent spherical harmonics through
    the least-norm map of colours to weight changes that sum to zero (the pseudo-inverse of
    [P^T; 1^T]), as the residual is."""
    colours = (SH_C0 * model.colours + 0.5).clamp(0, 1).double().cpu().numpy()
    weights = stack_colour_weights(stack, colours)
    palette = np.asarray(stack.palette, np.float64)
    inverse = np.linalg.pinv(np.vstack([palette.T, np.ones(len(palette))]))[:, :3]  # (K, 3)
    residual = model.colours_rest @ torch.as_tensor(inverse.T, dtype=model.colours_rest.dtype,
                                                    device=model.means.device)
    return torch.as_tensor(weights, dtype=torch.float32, device=model.means.device), residual


def _light_start(run: SplatRun, views: list) -> torch.Tensor:
    """(S, M) weights: each splat's mean of the training weights it sends light to, weighted
    by that light (each pixel's weights over its opacity, from each view's pairs drawn
    afresh, before any footprint is held); transport weights are averaged tone-mapped, as
    the weight loss compares them, so that a splat on an emitter's edge does not start at
    its radiance; a splat no view sees starts at the mean weights."""
    model = run.model
    channels = views[0].weights.shape[-1]
    transport = run.basis == Basis.TRANSPORT
    light = model.means.new_zeros(len(model.means), channels + 1)  # weights, then light
    for view in views:
        pixel, splat, contribution, opacity = view_pairs(run, view)
        straight = view.weights.view(-1, channels) / opacity[:, None].clamp(min=1e-6)
        straight = tone_map(straight) if transport else straight
        sent = torch.cat([straight, torch.ones_like(straight[:, :1])], 1)  # (H W, M + 1)
        for first in range(0, len(pixel), PAIRS_AT_ONCE):  # (pairs, M + 1) a part at a time
            part = slice(first, first + PAIRS_AT_ONCE)
            light.index_add_(0, splat[part].long(), contribution[part, None]
                             * sent.index_select(0, pixel[part]))
        del pixel, splat, contribution  # not held while the next view's are drawn
    mean = torch.cat([v.weights.view(-1, channels) for v in views]).mean(0)
    weights = light[:, :-1] / light[:, -1:].clamp(min=1e-6)
    weights = inverse_tone_map(weights.clamp(max=1 - 1e-6)) if transport else weights
    weights = torch.where(light[:, -1:] > 1e-6, weights, mean)
    if run.basis == Basis.ADDITIVE:
        weights = weights / weights.sum(1, keepdim=True).clamp(min=1e-6)
    return weights.clamp(min=0)


def _optimiser(run: SplatRun, extent: float) -> torch.optim.Adam:
    """One Adam, a group a trained parameter, named by it (``strategy.edit_rows``); the
    colour transforms only in the RGB stage (``SplatSteps._palette_targets``)."""
    rates = _rates(run.config.splats, extent)
    groups = [{"name": name, "params": [p], "lr": rates[name]}
              for name, p in run.model.named_parameters() if p.requires_grad]
    if run.appearance is not None and run.kind == RGB:
        groups.append({"name": "appearance", "params": list(run.appearance.parameters()),
                       "lr": rates["appearance"]})
    return torch.optim.Adam(groups, eps=1e-15, fused=True)


def _rates(settings: SplatConfig, extent: float) -> dict[str, float]:
    """Each trained parameter's learning rate at the start of its stage."""
    return {"means": settings.means_lr * extent, "scales": settings.scales_lr,
            "quats": settings.quats_lr, "opacities": settings.opacities_lr,
            "colours": settings.colours_lr, "colours_rest": settings.colours_lr / 20,
            "weights": settings.weights_lr, "residual": settings.weights_lr / 20,
            "appearance": 1e-3}


def _set_rates(optimiser, config: TrainConfig, extent: float, it: int,
               progress: float) -> None:
    """At iteration ``it``, ``progress`` through its stage (``stage_progress``): over the RGB
    stage, the centres' rate decays exponentially to a hundredth (3D Gaussian splatting's;
    the geometry is frozen after it); over the palette stage, every rate to ``lr_decay`` of
    its start."""
    palette = it >= config.pretrain_iters
    rates = _rates(config.splats, extent)
    set_rates([optimiser], progress, lambda group: rates[group["name"]],
              lambda group: config.lr_decay if palette else
              MEANS_DECAY if group["name"] == "means" else None)
