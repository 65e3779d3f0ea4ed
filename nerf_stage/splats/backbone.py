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

import math
import os
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn
from tqdm import tqdm

from palette_core.basis import Basis, n_terms
from palette_core.errors import InputError, first_line

from ..backbones import MAX_SPLATS, SplatConfig
from ..data.cameras import Intrinsics, project
from ..data.dataset import Dataset
from ..data.points import Points
from ..fields.base import ACTIVATIONS, INVERSE_ACTIVATIONS, RGB, inverse_tone_map, tone_map
from ..render.contraction import distance, parameter
from ..render.march import box_intersection
from ..render.samples import KEEP_WEIGHT, PixelSamples
from ..render.scene_box import SceneBox, visual_hull
from ..train.appearance import Appearance, exposure_free_weights
from ..train.checkpoint import CHECKPOINT, write_checkpoint
from ..train.config import Strategy, TrainConfig
from ..train.losses import recorded_rgb_loss, ssim_loss, weight_loss
from ..train.metrics import psnr_from_mse
from ..train.run import CONFIG, RunBase, RunRecord, default_device, run_fields
from ..train.trainer import (
    choose_scene_box,
    load_optimisers,
    next_iteration,
    stage_progress,
    training_targets,
)
from .model import Splats, covariances, with_residual
from .rasterise import draw
from .sh import SH_C0, sh_basis, sh_terms
from .strategy import Densification

GEOMETRY = ("means", "scales", "quats", "opacities")
INITIAL_OPACITY = 0.1
#: At most one starting splat for this many pixels of a training image: more, at a low
#: opacity, all cover every pixel (hundreds of pairs a pixel on a tiny image).
PIXELS_PER_INITIAL = 4
MIN_POINTS = 4  # a capture with fewer sparse points starts at random
HULL_CELLS = 64  # along each side of the box: the visual hull that bounded scenes start in
HULL_TRIES = 32  # places along a starting splat's ray tried for one in the hull
#: A capture's sparse points leave parts of its views empty (sky, ground, a background
#: too plain or too far to match): splats start there too, where a view's cell, one of
#: this many along its longer side, holds no point (``uncovered``).
COVER_CELLS = 16
#: ... no nearer to the camera than this quantile of the depths of the points it sees.
COVER_NEAR = 0.1
#: Far splats start out to this many bends of a ray's marching parameter (``contraction``):
#: ten bends from the camera.
FAR_SHELL = 1.9
#: A starting splat has a standard deviation in its nearest training view of at most this
#: share of ``--splats-reach``: its ellipse to 1/255 (2.5 deviations at ``INITIAL_OPACITY``)
#: spans half the reach, so that none starts cut off square, nor covers every pixel of a
#: small view (docs/splats.md, "The start's width").
START_REACH = 0.2
#: Bytes of frozen footprints the palette stage keeps (``_footprints``). When the views'
#: footprints do not all fit, the stage draws from a window of views whose footprints do,
#: and moves the window on to the next views after ``WINDOW_VISITS`` steps a view in it:
#: a view drawn afresh at every visit costs a footprint's making each time.
FOOTPRINT_BYTES = 768 << 20
WINDOW_VISITS = 8
PAIRS_AT_ONCE = 1 << 20  # a view's pairs sorted (``_csr``) or multiplied (the start) at once


class SplatModel(nn.Module):
    """Gaussians in the normalised box: ``means`` (S, 3), log standard deviations ``scales``
    (S, 3), quaternions ``quats`` (S, 4; w, x, y, z), opacity logits ``opacities`` (S,), and
    either an RGB colour in spherical harmonics, ``colours`` (S, 3) of degree 0 and
    ``colours_rest`` (S, B - 1, 3) above (``kind`` RGB), or palette ``weights`` (S, M)
    before their activation and their view-dependent ``residual`` (S, B - 1, M) (``kind``
    the basis); B = (``degree`` + 1)^2."""

    def __init__(self, tensors: dict[str, torch.Tensor], kind: str, degree: int):
        super().__init__()
        self.kind, self.degree = kind, degree
        for name, tensor in tensors.items():
            setattr(self, name, nn.Parameter(tensor))

    def values(self, eye: torch.Tensor, degree: int | None = None) -> torch.Tensor:
        """(S, C) each splat's RGB or palette weights seen from ``eye`` (3,), with the
        spherical harmonics up to ``degree`` (all by default)."""
        degree = self.degree if degree is None else degree
        basis = sh_basis(nn.functional.normalize(self.means - eye, dim=1), degree)[:, 1:]
        if self.kind == RGB:
            return torch.clamp(SH_C0 * self.colours + 0.5 + _rest(basis, self.colours_rest),
                               min=0)
        weights = ACTIVATIONS[self.kind](self.weights)
        if degree == 0:
            return weights
        residual = _rest(basis, self.residual)
        if self.kind == Basis.ADDITIVE:  # on the simplex: the residual sums to zero
            residual = residual - residual.mean(1, keepdim=True)
        return with_residual(weights, residual, self.kind)

    def gaussians(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, 3, 3) covariances and (S,) opacities."""
        return covariances(self.quats, torch.exp(self.scales)), torch.sigmoid(self.opacities)

    def set_output(self, kind: str, weights: torch.Tensor) -> None:
        """Freeze the geometry and replace the RGB colours by (S, M) palette ``weights``
        (after their activation) and a zero residual."""
        for name in GEOMETRY:
            getattr(self, name).requires_grad_(False)
        del self.colours, self.colours_rest
        self.kind = kind
        self.weights = nn.Parameter(INVERSE_ACTIVATIONS[kind](weights.clamp(min=1e-4)))
        self.residual = nn.Parameter(weights.new_zeros(len(weights), sh_terms(self.degree) - 1,
                                                       weights.shape[1]))


def _rest(basis: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
    """(S, C) values of degrees 1 and up: (S, B' - 1) ``basis`` x the first B' - 1 of the
    (S, B - 1, C) ``coefficients``."""
    return torch.einsum("sb,sbc->sc", basis, coefficients[:, :basis.shape[1]])


@dataclass
class SplatRun(RunBase):
    """A ``splats`` run: ``RunBase``'s record and its ``SplatModel``."""

    model: SplatModel | None = None
    appearance: Appearance | None = None

    @property
    def kind(self) -> str:
        return self.model.kind

    @property
    def device(self) -> torch.device:
        return self.model.means.device

    def baked(self, factor: int = 0):
        raise InputError("a splat run has no field to bake", "baked")

    def bounds(self) -> np.ndarray:
        """(2, 3) world corners of the splats in the scene box (their 1st and 99th
        percentiles, within the box)."""
        with torch.no_grad():
            means = self.model.means.cpu().numpy().astype(np.float64)
        inside = means[np.all(np.abs(means) <= self.box.extent, axis=1)]
        corners = (np.percentile(inside, [1, 99], axis=0) if len(inside)
                   else np.stack([-self.box.extent, self.box.extent]))
        return self.box.centre + self.box.scale * corners

    @torch.no_grad()
    def render(self, poses: np.ndarray, progress: bool = False,
               intrinsics: Intrinsics | list[Intrinsics] | None = None,
               samples: bool = False) -> tuple:
        """Draw whole views (``Run.render``'s contract), each splat whole as the browser
        draws it, not cut off at the reach that training draws with: (N, H, W, C) values
        premultiplied by opacity, (N, H, W) opacity and, with ``samples``,
        ``render.samples.PixelSamples``: each pixel's splats at their centres, with their
        contributions (those below ``KEEP_WEIGHT`` dropped, but each pixel's strongest)."""
        cameras = (intrinsics if isinstance(intrinsics, list)
                   else [intrinsics or self.intrinsics] * len(poses))
        covariance, opacity = self.model.gaussians()
        centres = (self.model.means.cpu().numpy().astype(np.float64) * self.box.scale
                   + self.box.centre).astype(np.float32) if samples else None
        values, accs, kept, first = [], [], [], 0
        for pose, camera in tqdm(zip(poses, cameras), desc="draw splats", unit="view",
                                 total=len(poses), disable=not progress):
            local = normalised_pose(pose, self.box, self.device)
            info = {}
            drawn, acc = draw(self.model.means, covariance, self.model.values(local[:3, 3]),
                              opacity, local, camera, None, info,
                              keep_pairs=samples)
            values.append(drawn.view(camera.height, camera.width, -1).cpu().numpy())
            accs.append(acc.view(camera.height, camera.width).cpu().numpy())
            if samples and "pairs" in info:
                pixel, splat, weight = info["pairs"]
                strongest = torch.zeros(len(acc), device=weight.device).scatter_reduce(
                    0, pixel, weight, "amax")
                keep = (weight >= torch.clamp(strongest[pixel], max=KEEP_WEIGHT)).cpu().numpy()
                kept.append((first + pixel.cpu().numpy()[keep],
                             centres[splat.cpu().numpy()[keep]], weight.cpu().numpy()[keep]))
            first += camera.height * camera.width
        rendered = np.stack(values), np.stack(accs)
        if not samples:
            return rendered
        parts = [np.concatenate(part) for part in zip(*kept)] if kept else [
            np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.float32)]
        return (*rendered, PixelSamples(*parts))

    def splats(self, source: dict) -> Splats:
        """The run's splats in world coordinates, with their editable weights, their
        view-dependent residual (summing to zero over the channels for the additive basis,
        as ``SplatModel.values`` uses it) and ``source``."""
        if self.kind == RGB:
            raise InputError("the run was trained on RGB only (strategy 'rgb'): its splats "
                             "have no palette weights")
        model, box = self.model, self.box
        with torch.no_grad():
            weights = ACTIVATIONS[model.kind](model.weights)
            quats = nn.functional.normalize(model.quats, dim=1)
            residual = model.residual.detach()
            if model.kind == Basis.ADDITIVE:
                residual = residual - residual.mean(2, keepdim=True)
            arrays = [model.means * box.scale + torch.as_tensor(box.centre, device=self.device),
                      torch.exp(model.scales) * box.scale, quats,
                      torch.sigmoid(model.opacities).clamp(1e-6, 1 - 1e-6), weights]
        return Splats(*(a.float().cpu().numpy() for a in arrays), self.palette, self.basis,
                      self.order, np.asarray(self.config.background, np.float64), source,
                      residual.float().cpu().numpy() if model.degree else None)

    @torch.no_grad()
    def residual_share(self, poses: np.ndarray) -> float:
        """Mean over splats and ``poses`` of |weights with residual - weights without| summed
        over the channels, halved: the share of the weights that depends on the view."""
        model = self.model
        shares = [(model.values(normalised_pose(p, self.box, self.device)[:3, 3])
                   - model.values(torch.zeros(3, device=self.device), 0)).abs().sum(1).mean() / 2
                  for p in poses]
        return float(torch.stack(shares).mean())


def normalised_pose(pose: np.ndarray, box: SceneBox, device) -> torch.Tensor:
    """(4, 4) float32 camera-to-world ``pose`` in the box's normalised coordinates."""
    local = np.array(pose, np.float64)
    local[:3, 3] = (local[:3, 3] - box.centre) / box.scale
    return torch.as_tensor(local, dtype=torch.float32, device=device)


def initial_splats(box: SceneBox, n: int, degree: int, generator: torch.Generator,
                   views: SeenViews | None = None, points: Points | None = None,
                   eyes: np.ndarray | None = None, widest: float = math.inf) -> dict:
    """Splats to start from, ``INITIAL_OPACITY`` opaque, as wide as the mean distance to
    their three nearest neighbours, with colours of ``degree``: at most ``n`` of the
    capture's ``points`` in their colours (3D Gaussian splatting's start), else at most
    ``n`` where the training ``views`` look (``seen_splats``). With both, splats start
    where the ``views`` see no point, too (``uncovered``), as many for those pixels as
    the points are for the rest, at most ``n``. Starting splats may lie far apart (sparse
    points, far splats of an unbounded scene), so none is wider than ``widest`` times its
    distance to the nearest of the (N, 3) normalised camera centres ``eyes``."""
    if points is None:
        means, rgb = seen_splats(box, n, generator, views)
    else:
        pick = torch.randperm(len(points), generator=generator)[:n].numpy()
        means = torch.as_tensor((points.positions[pick] - box.centre) / box.scale,
                                dtype=torch.float32)
        rgb = torch.as_tensor(points.colours[pick], dtype=torch.float32)
        if views is not None:
            empty = uncovered(points, views)
            share = empty.alpha.sum() / max(1, (views.alpha >= 0.5).sum())
            extra = min(n, round(len(pick) * share / max(1 - share, 1 / len(pick))))
            if extra:
                far, far_rgb = seen_splats(box, extra, generator, empty)
                means, rgb = torch.cat([means, far]), torch.cat([rgb, far_rgb])
    colours = (rgb - 0.5) / SH_C0
    distance = cKDTree(means.numpy()).query(means.numpy(), k=4)[0][:, 1:].mean(1)
    if eyes is not None:
        distance = np.minimum(distance, widest * cKDTree(eyes).query(means.numpy())[0])
    scale = np.log(np.maximum(distance, 1e-7))
    n = len(means)
    return {"means": means, "scales": torch.as_tensor(scale, dtype=torch.float32)[:, None]
            .repeat(1, 3), "quats": torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
            "opacities": torch.full((n,), math.log(INITIAL_OPACITY / (1 - INITIAL_OPACITY))),
            "colours": colours, "colours_rest": torch.zeros(n, sh_terms(degree) - 1, 3)}


@dataclass
class SeenViews:
    """The training views a splat run starts from: N world ``poses``, their ``cameras``,
    (N, H, W, 3) ``images`` and (N, H, W) ``alpha``, the box's visual ``hull`` (X, Y, Z)
    where a bounded scene's images are partly transparent (None elsewhere), and the (N,)
    world distance from each camera within which no splat starts (``near``; None: 0)."""

    poses: np.ndarray
    cameras: list[Intrinsics]
    images: np.ndarray
    alpha: np.ndarray
    hull: np.ndarray | None = None
    near: np.ndarray | None = None


def uncovered(points: Points, views: SeenViews) -> SeenViews:
    """The opaque pixels (alpha at least a half) of ``views`` whose cell (``COVER_CELLS``
    along the view's longer side) no point in front of the camera falls in, as ``alpha``
    (N, H, W) bool, with ``near``: the ``COVER_NEAR`` quantile of the depths of the points
    each view sees (0 where it sees none)."""
    empty, near = views.alpha >= 0.5, np.zeros(len(views.poses))
    for i, (pose, camera) in enumerate(zip(views.poses, views.cameras)):
        x, y, depth = project(points.positions, pose, camera)
        seen = (depth > 0) & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        size = max(camera.width, camera.height) / COVER_CELLS
        covered = np.zeros((COVER_CELLS + 1, COVER_CELLS + 1), bool)
        covered[(y[seen] / size).astype(int), (x[seen] / size).astype(int)] = True
        empty[i] &= ~covered[np.ix_(((np.arange(camera.height) + 0.5) / size).astype(int),
                                    ((np.arange(camera.width) + 0.5) / size).astype(int))]
        near[i] = np.quantile(depth[seen], COVER_NEAR) if seen.any() else 0.0
    return replace(views, alpha=empty, near=near)


def seen_splats(box: SceneBox, n: int, generator: torch.Generator,
                views: SeenViews) -> tuple[torch.Tensor, torch.Tensor]:
    """(at most n, 3) positions and colours of splats where the training ``views`` look:
    each on the ray through a random point of an opaque pixel (alpha at least a half) of a
    random view, in that pixel's colour, at a uniform random place of the ray's marching
    parameter (``contraction``: linear in distance through the box, in disparity beyond it
    out to ``FAR_SHELL``, so that about half of them are far in an unbounded scene; within
    the ``hull`` where there is one, the first of ``HULL_TRIES`` places in it), beyond the
    view's ``near``. Rays that meet no box (or hull) start no splat, unless none does."""
    opaque = np.flatnonzero(views.alpha.reshape(-1) >= 0.5)
    if not len(opaque):
        opaque = np.arange(views.alpha.size)
    pick = opaque[torch.randint(len(opaque), (n,), generator=generator).numpy()]
    view, y, x = np.unravel_index(pick, views.alpha.shape)
    colours = torch.as_tensor(views.images[view, y, x], dtype=torch.float32)
    x = x + torch.rand(n, generator=generator).numpy()
    y = y + torch.rand(n, generator=generator).numpy()
    intrinsics = np.array([[c.fx, c.fy, c.cx, c.cy] for c in views.cameras])[view]
    local = np.stack([(x - intrinsics[:, 2]) / intrinsics[:, 0],
                      -(y - intrinsics[:, 3]) / intrinsics[:, 1], -np.ones(n)], 1)
    directions = np.einsum("nij,nj->ni", views.poses[view, :3, :3], local)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = (views.poses[view, :3, 3] - box.centre) / box.scale
    origins, directions = (torch.as_tensor(a, dtype=torch.float32) for a in (origins, directions))
    start = torch.as_tensor(0.0 if views.near is None else views.near[view] / box.scale,
                            dtype=torch.float32)
    if box.unbounded:
        _, exits = box_intersection(origins, directions, torch.ones(3))
        bend = exits.clamp(min=1.0)
        first = torch.minimum(parameter(start, bend), FAR_SHELL * bend)  # where u starts
        u = first + torch.rand(n, generator=generator) * (FAR_SHELL * bend - first)
        return origins + distance(u, bend)[:, None] * directions, colours
    extent = torch.as_tensor(box.extent, dtype=torch.float32)
    near, far = box_intersection(origins, directions, extent)
    near = torch.maximum(near, start)
    tries = 1 if views.hull is None else HULL_TRIES
    t = near[:, None] + torch.rand(n, tries, generator=generator) * (far - near)[:, None]
    hit = (far > near)[:, None].expand(n, tries)
    if views.hull is not None:
        cells = torch.as_tensor(views.hull.shape)
        unit = (origins[:, None] + t[..., None] * directions[:, None]) / extent * 0.5 + 0.5
        index = (unit * cells).long().clamp(torch.zeros(3, dtype=torch.long), cells - 1)
        hit = hit & torch.as_tensor(views.hull)[index.unbind(-1)]
    first = hit.float().argmax(1)  # the first place that is in (or 0 where none is)
    keep = hit.any(1) if hit.any() else torch.ones(n, dtype=torch.bool)  # none: keep all
    t = t.gather(1, first[:, None])[:, 0]
    return (origins + t[:, None] * directions)[keep], colours[keep]


def train(config: TrainConfig, dataset: Dataset, stack, rundir: str | os.PathLike,
          resume: bool = False, force: bool = False, weights_path: str = "",
          progress: bool = True, device: torch.device | None = None) -> SplatRun:
    """Train (or resume) a splat run and write its run folder (``trainer.train``'s
    contract): RGB for ``pretrain_iters``, then the palette weights for ``finetune_iters``
    (``two-stage``); ``rgb`` stops after the first; ``traditional`` is not offered (the
    geometry needs colours to grow from)."""
    if config.strategy == Strategy.TRADITIONAL:
        raise InputError("the splats backbone trains two-stage or rgb, not traditional")
    device = device or default_device()
    rundir = Path(rundir)
    weights, state = training_targets(config, dataset, stack, rundir, resume, force)
    settings = config.splats
    train_ids = dataset.indices("train")
    if resume:
        run = _from_state(state, str(rundir / CHECKPOINT), device)
    else:
        box = choose_scene_box(config, dataset, stack, train_ids, weights, device, progress)
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
        run = SplatRun(config, box, dataset.intrinsics, np.asarray(stack.palette, np.float64),
                       stack.basis, stack.order, record, model.to(device))
    run.record.weights = weights_path
    if config.appearance and run.appearance is None:
        run.appearance = Appearance(len(train_ids)).to(device)
    views = _training_views(run, dataset, train_ids, weights, device)
    del weights  # the views hold them, until the palette stage's replace them
    rundir.mkdir(parents=True, exist_ok=True)
    config.save(rundir / CONFIG)
    extent = 1.1 * float(max(torch.linalg.norm(v.pose[:3, 3]) for v in views))
    optimiser = _optimiser(run, extent)
    if resume:
        load_optimisers([optimiser], state["optimisers"], rundir)
    strategy = Densification.for_stage(settings, extent, config.pretrain_iters,
                                       sum(v.alpha.numel() for v in views))
    generator = torch.Generator().manual_seed(config.seed)
    if resume:
        generator.set_state(state["generator"])
    terms = torch.as_tensor(run.terms, dtype=torch.float32, device=device)
    background = torch.as_tensor(config.background, dtype=torch.float32, device=device)
    last = config.pretrain_iters if config.strategy == Strategy.RGB else config.total_iters
    log, it = run.record.log, run.record.iteration
    bar = tqdm(desc="train splats", initial=it, total=last, disable=not progress, unit="it")
    clock = time.perf_counter() - (log[-1]["seconds"] if log else 0.0)
    # the palette stage's footprints: their window starts at view ``start``, drawn from
    # ``visits`` times so far
    footprints, start, visits = None, 0, 0
    while it < last:
        if it >= config.pretrain_iters and run.kind == RGB:
            _exposure_free(run, stack, views)
            _start_palette(run, views)
            footprints = _footprints(run, views)
            optimiser = _optimiser(run, extent)
        elif run.kind != RGB and it % config.checkpoint_every == 0:
            _exposure_free(run, stack, views)
        if run.kind != RGB and footprints is None:  # resumed in the palette stage
            footprints = _footprints(run, views)
        held = [i for i, footprint in enumerate(footprints or ()) if footprint]
        if held and len(held) < len(views) and visits >= WINDOW_VISITS * len(held):
            # the window's footprints freed first, the one last drawn from too
            start, footprints, footprint = (start + len(held)) % len(views), None, None
            footprints, visits = _footprints(run, views, start), 0
            held = [i for i, footprint in enumerate(footprints) if footprint]
        window = held or range(len(views))  # none held: every view, drawn afresh
        index = window[int(torch.randint(len(window), (1,), generator=generator))]
        footprint = footprints[index] if footprints else None
        visits += footprint is not None
        progress = stage_progress(config, it, log, last)
        _set_rates(optimiser, config, extent, it, progress)
        view = views[index] if footprint else _patch(views[index], settings.patch, generator)
        info = {}
        loss, psnr = _loss(run, view, terms, background, it, info, footprint)
        optimiser.zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            raise InputError(f"training diverged at iteration {it + 1} (the loss is not "
                             "finite): lower the learning rates or start afresh with another "
                             "seed")
        loss.backward()
        if run.kind == RGB:
            strategy.after_backward(run.model, optimiser, info, it + 1, progress,
                                    view.window[2], view.window[3])
        optimiser.step()
        seconds = time.perf_counter() - clock
        log.append({"iteration": it + 1, "seconds": seconds, "loss": loss.item(), "psnr": psnr,
                    "stage": str(run.kind), "splats": len(run.model.means)})
        it = next_iteration(config, it + 1, seconds, last)
        run.record.iteration = it
        bar.update(it - bar.n)
        bar.set_postfix(stage=run.kind, splats=len(run.model.means), psnr=f"{psnr:.2f}")
        if it % config.checkpoint_every == 0 or it == last:
            save_checkpoint(run, rundir / CHECKPOINT, optimiser, generator)
    bar.close()
    return run


@dataclass
class _View:
    """A training image (or a ``window`` of it: x, y, width, height) on the device: its
    normalised pose, camera, (H, W, 3) colours, (H, W, M) weights (premultiplied by alpha
    for the additive basis), (H, W) alpha and its index among the training images."""

    pose: torch.Tensor
    camera: Intrinsics
    rgb: torch.Tensor
    weights: torch.Tensor
    alpha: torch.Tensor
    image: int
    window: tuple[int, int, int, int]


def _patch(view: _View, size: int, generator: torch.Generator) -> _View:
    """A random ``size`` x ``size`` window of ``view`` (the whole view when it is no larger
    or ``size`` is 0)."""
    width, height = view.camera.width, view.camera.height
    if not size or (size >= width and size >= height):
        return view
    w, h = min(size, width), min(size, height)
    x, y = (int(torch.randint(extent - side + 1, (1,), generator=generator))
            for extent, side in ((width, w), (height, h)))
    rows, columns = slice(y, y + h), slice(x, x + w)
    return replace(view, rgb=view.rgb[rows, columns], weights=view.weights[rows, columns],
                   alpha=view.alpha[rows, columns], window=(x, y, w, h))


def _training_views(run: SplatRun, dataset: Dataset, train_ids, weights, device) -> list:
    def tensor(a):
        return torch.as_tensor(a, dtype=torch.float32, device=device)

    return [_View(normalised_pose(dataset.poses[i], run.box, device), dataset.camera(i),
                  tensor(dataset.images[i]), tensor(weights[n]), tensor(dataset.alpha[i]), n,
                  (0, 0, dataset.camera(i).width, dataset.camera(i).height))
            for n, i in enumerate(train_ids)]


def _loss(run: SplatRun, view: _View, terms, background, it: int, info: dict,
          footprint: _Footprint | None = None) -> tuple[torch.Tensor, float]:
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


def _as_recorded(run: SplatRun, rgb: torch.Tensor, view: _View) -> torch.Tensor:
    """(H, W, 3) colours as the view's image recorded them (``appearance``)."""
    if run.appearance is None:
        return rgb
    image = torch.full((rgb.shape[0] * rgb.shape[1],), view.image, device=rgb.device)
    return run.appearance(rgb.reshape(-1, 3), image).view(rgb.shape)


def _exposure_free(run: SplatRun, stack, views: list) -> None:
    """Give the palette stage's training ``views`` (in place) their weights exposure-free
    under the current colour transforms where the run learns them
    (``appearance.exposure_free_weights``): as the stage starts and at every checkpoint,
    where a resumed run computes them too; a view at a time, so that one view's pixels are
    computed and one view's weights are held twice at once."""
    if run.appearance is None:
        return
    for n, view in enumerate(views):
        image = torch.full((view.alpha.numel(),), view.image, device=view.alpha.device)
        weights = exposure_free_weights(run.appearance, stack, view.rgb.reshape(-1, 3), image,
                                        view.alpha.flatten())
        if weights is None:
            return
        views[n] = replace(view, weights=weights.view(view.weights.shape))


@dataclass
class _Footprint:
    """A view's splats with the geometry frozen: the (H W, S) sparse ``matrix`` of each
    pixel's contributions (transmittance x alpha of its splats), its ``transposed`` (S, H W)
    and the (H W,) ``opacity``, so that the view's values are ``matrix @ values``
    (``draw``), drawn without projecting or sorting. Both are CSR with 32-bit indices: the
    backward's product with the transposed would otherwise transpose ``matrix`` anew."""

    matrix: torch.Tensor
    transposed: torch.Tensor
    opacity: torch.Tensor

    def draw(self, values: torch.Tensor) -> torch.Tensor:
        """(H W, M) values of the view from the splats' (S, M) ``values``."""
        return _SparseProduct.apply(self.matrix, self.transposed, values)

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for m in (self.matrix, self.transposed)
                   for t in (m.crow_indices(), m.col_indices(), m.values()))


class _SparseProduct(torch.autograd.Function):
    """``matrix @ values``, differentiable in ``values`` through ``transposed``."""

    @staticmethod
    def forward(ctx, matrix, transposed, values):
        ctx.transposed = transposed
        return matrix @ values

    @staticmethod
    def backward(ctx, grad):
        return None, None, ctx.transposed @ grad


@torch.no_grad()
def _view_pairs(run: SplatRun, view: _View) -> tuple[torch.Tensor, ...]:
    """The (P,) pixel, splat and contribution (transmittance x alpha) of ``view``'s (its
    window's) pairs under the run's current geometry, by pixel, and its (H W,) opacity."""
    model = run.model
    covariance, opacity = model.gaussians()
    info = {}
    _, acc = draw(model.means, covariance, model.means.new_zeros(len(model.means), 0), opacity,
                  view.pose, view.camera, run.config.splats.reach, info, view.window,
                  keep_pairs=True)
    pixel, splat, contribution = info.get("pairs", (acc.new_zeros(0, dtype=torch.int),) * 2
                                          + (acc.new_zeros(0),))
    return pixel, splat, contribution, acc


def _footprint(run: SplatRun, view: _View) -> _Footprint:
    """The footprint of ``view`` (its window) under the run's current geometry."""
    pixel, splat, contribution, acc = _view_pairs(run, view)
    pixels, splats = len(acc), len(run.model.means)
    # by splat, then pixel (the pairs come by pixel); then by pixel, then splat from it
    transposed = _csr(splat, pixel, contribution, (splats, pixels))
    del pixel, splat, contribution
    splat = torch.repeat_interleave(
        torch.arange(splats, dtype=torch.int32, device=acc.device),
        torch.diff(transposed.crow_indices()).long())
    return _Footprint(_csr(transposed.col_indices(), splat, transposed.values(),
                           (pixels, splats)), transposed, acc)


def _csr(rows: torch.Tensor, columns: torch.Tensor, values: torch.Tensor,
         shape: tuple[int, int]) -> torch.Tensor:
    """A sparse CSR matrix with 32-bit indices from distinct (P,) (row, column, value)
    triplets sorted by column within each row, a row's triplets taken in their order: a
    counting sort by row (stable), ``PAIRS_AT_ONCE`` triplets at a time, so that it holds
    the matrix and a part's sort, not a sort of every triplet."""
    counts = torch.bincount(rows, minlength=shape[0])
    ends = torch.cumsum(counts, 0)
    free = ends - counts  # each row's next place
    sorted_columns, sorted_values = torch.empty_like(columns), torch.empty_like(values)
    for first in range(0, len(rows), PAIRS_AT_ONCE):
        part = slice(first, first + PAIRS_AT_ONCE)
        row, order = torch.sort(rows[part], stable=True)
        place = (free.index_select(0, row) + torch.arange(len(row), device=row.device)
                 - torch.searchsorted(row, row))  # its row's next place, plus its rank
        sorted_columns[place] = columns[part].index_select(0, order)
        sorted_values[place] = values[part].index_select(0, order)
        free += torch.bincount(row, minlength=shape[0])
    with warnings.catch_warnings():  # torch calls its sparse CSR support beta
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(torch.cat([ends.new_zeros(1), ends]).int(),
                                       sorted_columns.int(), sorted_values, shape)


def _footprints(run: SplatRun, views: list, start: int = 0) -> list:
    """The footprints of ``views`` in their order from ``start`` on (around to the first),
    while they fit in ``FOOTPRINT_BYTES`` (the next one taken to be as large as the largest
    so far); None for the views past them."""
    footprints, used, largest = [None] * len(views), 0, 0
    for n in tqdm(range(len(views)), desc="footprints", unit="view", leave=False):
        if used >= FOOTPRINT_BYTES or used + largest > FOOTPRINT_BYTES:
            break
        index = (start + n) % len(views)
        footprints[index] = _footprint(run, views[index])
        used += footprints[index].nbytes
        largest = max(largest, footprints[index].nbytes)
    return footprints


@torch.no_grad()
def _start_palette(run: SplatRun, views: list) -> None:
    """Freeze the geometry and start each splat's weights at the mean of the training
    weights it sends light to, weighted by that light (each pixel's weights over its
    opacity, from each view's pairs drawn afresh, before any footprint is held); transport
    weights are averaged tone-mapped, as the weight loss compares them, so that a splat on
    an emitter's edge does not start at its radiance; a splat no view sees starts at the
    mean weights."""
    model = run.model
    channels = views[0].weights.shape[-1]
    transport = run.basis == Basis.TRANSPORT
    light = model.means.new_zeros(len(model.means), channels + 1)  # weights, then light
    for view in views:
        pixel, splat, contribution, opacity = _view_pairs(run, view)
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
    model.set_output(run.basis, weights.clamp(min=0))


def _optimiser(run: SplatRun, extent: float) -> torch.optim.Adam:
    """One Adam, a group a trained parameter, named by it (``strategy.edit_rows``)."""
    rates = _rates(run.config.splats, extent)
    groups = [{"name": name, "params": [p], "lr": rates[name]}
              for name, p in run.model.named_parameters() if p.requires_grad]
    if run.appearance is not None:
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
    for group in optimiser.param_groups:
        if palette or group["name"] == "means":
            decay = config.lr_decay if palette else 0.01
            group["lr"] = rates[group["name"]] * decay ** progress


def save_checkpoint(run: SplatRun, path: Path, optimiser, generator) -> None:
    """Write the run (``run.write_checkpoint``; the splats' tensors as its ``field``)."""
    model = run.model
    output = {"kind": str(model.kind), "channels": 3 if model.kind == RGB
              else model.weights.shape[1], "degree": model.degree}
    extra = {} if run.appearance is None else {"appearance": run.appearance.state_dict()}
    write_checkpoint(run, path, model.state_dict(), output, [optimiser.state_dict()],
                     generator, extra)


def load_run(state: dict, path: str, device: torch.device) -> SplatRun:
    """The splat run of a checkpoint's ``state`` (read by ``run.load_run``), on ``device``."""
    return _from_state(state, path, device)


def _from_state(state: dict, path: str, device) -> SplatRun:
    try:
        base = run_fields(state, path)
        channels = n_terms(len(base["palette"]), base["basis"], base["order"])
        output, tensors = state["output"], dict(state["field"])
        kind = RGB if output["kind"] == RGB else Basis.parse(output["kind"])
        degree = int(output["degree"])
        model = SplatModel(_check_tensors(tensors, kind, degree, channels, path), kind, degree)
        if kind != RGB:
            for name in GEOMETRY:
                getattr(model, name).requires_grad_(False)
        run = SplatRun(**base, model=model.to(device))
        if run.config.appearance:
            run.appearance = Appearance(len(state["appearance"]["affine"]))
            run.appearance.load_state_dict(state["appearance"])
            run.appearance.to(device)
        return run
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        raise InputError(f"checkpoint {path} is malformed: {first_line(exc)}") from None


def _check_tensors(tensors: dict, kind: str, degree: int, channels: int, path: str) -> dict:
    """The checkpoint's splat tensors as float32, checked: the names and shapes of one
    model of at most ``MAX_SPLATS`` splats, floating-point and finite values and rotations
    that are quaternions (a checkpoint from elsewhere is read as data only,
    ``checkpoint.read_checkpoint``); InputError otherwise."""
    if not 0 <= degree <= 3:
        raise InputError(f"{path}: spherical-harmonics degree must be in [0, 3], got {degree}")
    means = tensors.get("means")
    s = len(means) if isinstance(means, torch.Tensor) and means.ndim else 0
    if not 0 < s <= MAX_SPLATS:
        raise InputError(f"{path}: the splats' means must be a tensor of 1 to {MAX_SPLATS} rows")
    b = sh_terms(degree)
    shapes = {"means": (s, 3), "scales": (s, 3), "quats": (s, 4), "opacities": (s,)}
    shapes.update({"colours": (s, 3), "colours_rest": (s, b - 1, 3)} if kind == RGB
                  else {"weights": (s, channels), "residual": (s, b - 1, channels)})
    if set(tensors) != set(shapes) or any(tuple(tensors[k].shape) != v for k, v in shapes.items()):
        raise InputError(f"{path}: the splats' tensors have the wrong names or shapes")
    if not all(t.is_floating_point() for t in tensors.values()):
        raise InputError(f"{path}: the splats' tensors must hold floating-point numbers")
    tensors = {name: t.float() for name, t in tensors.items()}
    if not all(torch.isfinite(t).all() for t in tensors.values()):
        raise InputError(f"{path}: the splats hold NaN or infinity")
    if (tensors["quats"].norm(dim=1) < 1e-6).any():
        raise InputError(f"{path}: a splat rotation is not a quaternion")
    return tensors
