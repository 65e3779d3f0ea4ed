"""Train a weight NeRF on a dataset and its weight stack, whatever its backbone: the
backbone chosen for ``auto``, the run folder checked, the training weights joined, the
scene box chosen (the same for every backbone), then the backbone's steps run by the one
loop (``loop.train_loop``; the field backbones' are ``field_steps.FieldSteps``). The run
folder (``run.py``) is checkpointed as training goes; training resumes from the checkpoint
and then gives the same result as an uninterrupted run.

Weight targets are premultiplied by alpha: additive stacks (straight, summing
to one) are multiplied by the frame's alpha; transport stacks from
``nerf-stage simulate`` already are.
"""

from __future__ import annotations

import importlib.util
import os
import resource
import tempfile
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from palette_core.basis import Basis, n_terms
from palette_core.errors import InputError
from palette_core.stack import WeightStack, default_stack, read_stack

from ..backbone_settings import Backbone
from ..backbones import BACKBONES
from ..data.dataset import Dataset, join_weights, load_dataset
from ..fields import RGB, make_field
from ..render.ndc import forward_facing
from ..render.occupancy import OccupancyGrid
from ..render.scene_box import SceneBox, box_from_dict, normalised_rays, scene_box
from . import budget
from .appearance import Appearance
from .checkpoint import CHECKPOINT, load_optimisers, read_checkpoint
from .config import Space, Strategy, TrainConfig
from .field_steps import FieldSteps, batch_loss, field_optimisers, start_palette_stage
from .loop import train_loop
from .point_depth import point_targets
from .run import (
    CONFIG,
    Run,
    RunBase,
    RunRecord,
    check_rundir,
    default_device,
    free_memory,
    restore,
)
from .schedule import stage_progress

#: ``--backbone auto`` (``choose_backbone``) chooses the splats for views at least this many
#: times as many pixels across as the grid has voxels.
SPLATS_FROM_GRID_RESOLUTION = 2
#: ``--space auto`` on images with transparent pixels (``choose_scene_box``): iterations of each
#: space's probe, pixels it is scored on, and by how many dB the unbounded probe must beat
#: the box's to be chosen.
PROBE_ITERS = 150
PROBE_PIXELS = 16384
PROBE_MARGIN = 6.0


@dataclass(frozen=True)
class TrainedCapture:
    """What ``train_capture`` trained: the run, its folder, the dataset and the stack."""

    run: RunBase
    rundir: Path
    dataset: Dataset
    weights: Path


def train_capture(data: str | os.PathLike, config: TrainConfig,
                  weights: str | os.PathLike | None = None,
                  output: str | os.PathLike | None = None, frames_outside: bool = False,
                  downscale: int = 1, resume: bool = False, force: bool = False
                  ) -> TrainedCapture:
    """``nerf-stage train``: the dataset folder ``data`` (``load_dataset``) with its weight
    stack (``weights``, default ``data``'s ``DEFAULT_STACK``) trained with ``config`` into
    the run folder ``output`` (default ``DATA-BACKBONE`` beside ``data``; ``train``)."""
    data = Path(data).resolve()
    dataset = load_dataset(data, config.background, frames_outside, downscale)
    config = choose_backbone(config, dataset)
    rundir = Path(output or data.with_name(f"{data.name}-{config.backbone}"))
    weights = (Path(weights) if weights else default_stack(data)).resolve()
    run = train(config, dataset, read_stack(weights), rundir, resume=resume, force=force,
                weights_path=str(weights))
    return TrainedCapture(run, rundir, dataset, weights)


def train(config: TrainConfig, dataset: Dataset, stack: WeightStack, rundir: str | os.PathLike,
          resume: bool = False, force: bool = False, weights_path: str = "",
          progress: bool = True, device: torch.device | None = None) -> Run:
    """Train (or resume) a weight NeRF and write its run directory (a backbone that is not a
    field trains itself: ``backbones.BackboneSpec``).

    Parameters
    ----------
    dataset : Dataset
        Its ``background`` must be ``config.background``.
    stack : WeightStack
        Weights of the dataset's training frames (``join_weights``).
    resume, force : bool
        Continue from ``rundir``'s checkpoint (same config), or start afresh over it;
        without either, a ``rundir`` that holds a checkpoint is an error.
    weights_path : str
        Where the stack came from, recorded in the checkpoint with the dataset's path.

    Raises
    ------
    InputError
        If the weights do not match the dataset, the run folder is not as ``resume`` and
        ``force`` say, or the checkpoint does not match the config.
    """
    with _subnormals_flushed():
        return _train(config, dataset, stack, rundir, resume, force, weights_path, progress,
                      device)


@contextmanager
def _subnormals_flushed():
    """Subnormal floats flushed to zero while it lasts, IEEE arithmetic after: Adam's
    moments of what a step does not touch (voxels off its rays, splats out of its view)
    decay into subnormals, on which CPUs compute many times slower (docs/training.md)."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def _train(config: TrainConfig, dataset: Dataset, stack: WeightStack, rundir: str | os.PathLike,
           resume: bool, force: bool, weights_path: str, progress: bool,
           device: torch.device | None) -> Run:
    device = device or default_device()
    rundir = Path(rundir)
    config = choose_backbone(config, dataset)
    config, weights, state = training_targets(config, dataset, stack, rundir, resume, force)
    train_ids = dataset.indices("train")
    if (state is None and dataset.points is None
            and getattr(config.backbone_config, "triangulate", False)):
        dataset = _with_points(dataset, train_ids, progress)
    box = (box_from_dict(state["box"], str(rundir / CHECKPOINT)) if resume else
           choose_scene_box(config, dataset, stack, train_ids, weights, device, progress))
    if state is None and budget.needs_plan(config):
        config = _planned(config, dataset, stack, rundir, weights, box, device, progress)
    return _train_in_box(config, dataset, stack, rundir, weights, state, box, weights_path,
                         progress, device)


def _with_points(dataset: Dataset, train_ids, progress: bool) -> Dataset:
    """``dataset`` with sparse points triangulated from its training views at their poses
    (``sfm.points_from_poses``), for a backbone that starts from them; as it is, with a
    warning, when none can be (no pycolmap, too few views, no match)."""
    from ..data.sfm import points_from_poses

    try:
        points = points_from_poses(dataset, train_ids, progress)
    except InputError as error:
        warnings.warn(f"the capture has no sparse points and none could be triangulated "
                      f"({error}): the splats start where the views look", stacklevel=2)
        return dataset
    if progress:
        tqdm.write(f"triangulated {len(points)} sparse points from the {len(train_ids)} "
                   "training views' poses")
    return replace(dataset, points=points)


def _planned(config: TrainConfig, dataset: Dataset, stack: WeightStack, rundir: Path,
             weights: np.ndarray, box: SceneBox, device, progress: bool) -> TrainConfig:
    """``config`` with its iterations planned for its ``minutes`` from a probe of its first
    stage trained beside ``rundir`` (``budget``)."""
    rundir.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".plan-", dir=rundir.parent) as folder:
        probe = _train_in_box(budget.probe_config(config), dataset, stack, Path(folder) / "run",
                              weights, None, box, "", False, device)
        rate = budget.probe_rate(probe.record.log)
    planned = budget.planned(config, rate)
    if progress:
        tqdm.write(f"planned {planned.pretrain_iters} + {planned.finetune_iters} iterations "
                   f"for {config.minutes:g} minutes ({rate:.2f} it/s in a probe of "
                   f"{budget.PROBE_ITERS}): the clock ends each stage")
    return planned


def _train_in_box(config: TrainConfig, dataset: Dataset, stack: WeightStack, rundir: Path,
                  weights: np.ndarray, state: dict | None, box: SceneBox, weights_path: str,
                  progress: bool, device) -> Run:
    """``train`` once the targets are joined and the box chosen."""
    train_ids = dataset.indices("train")
    resume = state is not None
    spec = BACKBONES[config.backbone]
    if not spec.is_field:
        return spec.module().train(config, dataset, stack, rundir, weights, state, box,
                                   weights_path, progress, device)
    stack = replace(stack, weights=[])  # the stack's own maps (full-size) can be freed now
    run = _new_run(config, box, dataset, stack, train_ids, device)
    run.record.weights = weights_path
    _check_fits(weights, config.supersampling, device)
    rays = _ray_bank(run, dataset, train_ids, weights, device)
    depth = _depth_targets(config, dataset, train_ids, run.box, device)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    optimiser_states = []
    if resume:
        if state["output"]["kind"] != run.field.kind:
            start_palette_stage(run)
        restore(run, state)
        generator.set_state(state["generator"])
        optimiser_states = state["optimisers"]
    rundir.mkdir(parents=True, exist_ok=True)
    config.save(rundir / CONFIG)
    optimisers = field_optimisers(run)
    if resume:
        load_optimisers(optimisers, optimiser_states, rundir)
    steps = FieldSteps(run, optimisers, rays, stack, generator, depth)
    train_loop(config, steps, rundir, config.total_iters, str(config.backbone), progress)
    return run


def training_targets(config: TrainConfig, dataset: Dataset, stack: WeightStack, rundir: Path,
                     resume: bool, force: bool) -> tuple[TrainConfig, np.ndarray, dict | None]:
    """What every backbone's training starts from, once ``rundir`` is as ``resume`` and
    ``force`` ask (``check_rundir``): the config (when resuming, the checkpoint's, which
    must train like ``config`` or be its plan: ``budget.plans_like``), the (n, H, W, M)
    weights of the training frames (premultiplied by alpha for the additive basis) and,
    when resuming, the checkpoint's state."""
    check_rundir(rundir, resume, force)
    weights = join_weights(dataset, stack, "train")
    if stack.basis == Basis.ADDITIVE:
        weights = weights * dataset.alpha[dataset.indices("train"), ..., None]
    state = read_checkpoint(rundir / CHECKPOINT) if resume else None
    if resume:
        saved = TrainConfig.from_dict(state["config"])
        if not (saved.trains_like(config) or budget.plans_like(saved, config)):
            raise InputError(f"{rundir} was trained with another config",
                             fixes=[("force", "to start afresh")])
        config = saved
    return config, weights, state


def peak_memory(device: torch.device) -> str:
    """What this process has held at most: its peak resident memory, and on CUDA the
    device's peak allocation (``torch.cuda.max_memory_allocated``)."""
    text = f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GB resident"
    if device.type == "cuda":
        text += f", {torch.cuda.max_memory_allocated(device) / 2**30:.2f} GB on {device}"
    return text


def choose_backbone(config: TrainConfig, dataset: Dataset) -> TrainConfig:
    """``config`` with ``--backbone auto`` made a backbone for ``dataset``: ``splats`` where
    its views are at least ``SPLATS_FROM_GRID_RESOLUTION`` times as many pixels across as
    the grid has voxels (detail the grid blurs) and the splats have points to start from
    (the capture's own, or pycolmap to triangulate them: ``_with_points``), ``grid``
    otherwise and for the ``traditional`` strategy, which the splats do not train
    (docs/decisions/0023-auto-backbone.md)."""
    if config.backbone != Backbone.AUTO:
        return config
    across = max(dataset.images.shape[1:3])
    voxels_across = round(config.grid.voxels ** (1 / 3))
    points = dataset.points is not None or (config.splats.triangulate
                                            and importlib.util.find_spec("pycolmap"))
    splats = (config.strategy != Strategy.TRADITIONAL and config.space != Space.NDC and points
              and across >= SPLATS_FROM_GRID_RESOLUTION * voxels_across)
    return replace(config, backbone=Backbone.SPLATS if splats else Backbone.GRID)


def choose_scene_box(config: TrainConfig, dataset: Dataset, stack: WeightStack, train_ids,
                     weights, device, progress: bool) -> SceneBox:
    """Where the scene ends (``scene_box.scene_box``), for every backbone: as
    ``config.space`` says; for ``auto``, NDC space for a field backbone on an LLFF capture
    (depth bounds, cameras that all face one way: ``ndc.forward_facing``;
    docs/decisions/0024-ndc-for-llff.md), and on images with transparent pixels the box
    unless a short RGB probe of ``PROBE_ITERS`` iterations in each space fits the training
    pixels at least ``PROBE_MARGIN`` dB better unbounded: a ground that runs on under an
    open sky has transparent pixels too, and no box holds it
    (docs/decisions/0007-unbounded-space.md). The probe is a NeRF of the run's backbone, or
    the grid's for a backbone that is not a field: where the scene ends does not depend on
    what draws it."""
    poses, cameras, alpha = (dataset.poses[train_ids], dataset.cameras(train_ids),
                             dataset.alpha[train_ids])
    depth = dataset.scene_depth(train_ids)
    space = config.space
    if (space == Space.AUTO and dataset.bounds is not None and forward_facing(poses)
            and BACKBONES[config.backbone].is_field):
        space = Space.NDC
    box = scene_box(poses, cameras, alpha, space, depth=depth,
                    nearest=dataset.nearest_depth(train_ids))
    if space != Space.AUTO or box.unbounded:
        return box
    unbounded = scene_box(poses, cameras, alpha, Space.UNBOUNDED, depth=depth)
    iters = min(PROBE_ITERS, config.total_iters)
    field = config.backbone if BACKBONES[config.backbone].is_field else "grid"
    probe = replace(config, backbone=field, strategy=Strategy.RGB, pretrain_iters=iters,
                    finetune_iters=0, appearance=False)
    fits = [_probe(probe, candidate, dataset, stack, train_ids, weights, device, progress)
            for candidate in (box, unbounded)]
    return unbounded if fits[1] >= fits[0] + PROBE_MARGIN else box


def _probe(config: TrainConfig, box: SceneBox, dataset, stack, train_ids, weights, device,
           progress: bool) -> float:
    """PSNR on a fixed batch of training pixels of an RGB NeRF trained in ``box`` for
    ``config``'s iterations."""
    run = _new_run(config, box, dataset, stack, train_ids, device)
    rays = _ray_bank(run, dataset, train_ids, weights, device)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    steps = FieldSteps(run, field_optimisers(run), rays, stack, generator, None)
    space = "unbounded" if box.unbounded else "box"
    for it in tqdm(range(config.total_iters), desc=f"probe {space}", disable=not progress,
                   unit="it"):
        steps.update(steps.loss(it, stage_progress(config, it, []))[0], it)
    pixels = torch.randperm(len(rays["rgb"]), generator=generator, device=device)[:PROBE_PIXELS]
    with torch.no_grad():
        run.field.eval()
        return batch_loss(run, {key: value[pixels] for key, value in rays.items()}, None,
                     steps.background, None)[1]


def _new_run(config, box, dataset, stack, train_ids, device) -> Run:
    channels = n_terms(len(stack.palette), stack.basis, stack.order)
    kind = RGB if config.strategy != Strategy.TRADITIONAL else stack.basis
    torch.manual_seed(config.seed)
    field = make_field(config, box, kind, 3 if kind == RGB else channels)
    occupancy = OccupancyGrid.over(box, config.occupancy_voxels)
    if not box.unbounded and box.ndc is None:
        occupancy.carve(box, dataset.poses[train_ids], dataset.cameras(train_ids),
                        dataset.alpha[train_ids])
    record = RunRecord(str(Path(dataset.root).resolve()), channels=channels,
                       stack_meta=stack.meta, frames_outside=dataset.frames_outside,
                       downscale=dataset.downscale)
    appearance = Appearance(len(train_ids)).to(device) if config.appearance else None
    return Run(config, box, dataset.intrinsics, np.asarray(stack.palette, np.float64),
               stack.basis, stack.order, record, field.to(device), occupancy.to(device),
               appearance)


def _ray_bank(run: Run, dataset: Dataset, train_ids, weights, device) -> dict:
    """Every training pixel: (N, n^2, 3) origins and directions of its rays, (N, 3) rgb,
    (N, M) weights, (N,) alpha, (N,) its image among the training images."""
    origins, directions = zip(*(normalised_rays(dataset.poses[i], dataset.camera(i), run.box,
                                                device, run.config.supersampling)
                                for i in train_ids))

    def flat(a):
        return torch.as_tensor(a.reshape(-1, a.shape[-1]), dtype=torch.float32, device=device)

    return {"origins": torch.cat(origins), "directions": torch.cat(directions),
            "rgb": flat(dataset.images[train_ids]), "weights": flat(weights),
            "alpha": flat(dataset.alpha[train_ids, ..., None])[:, 0],
            "image": torch.arange(len(train_ids), device=device).repeat_interleave(
                dataset.alpha[0].size)}


def _depth_targets(config: TrainConfig, dataset: Dataset, train_ids, box: SceneBox,
                   device) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The training pixels where the capture's sparse points are seen and their rays'
    targets (``point_depth.point_targets``), on ``device``; None without ``depth_weight``,
    points or a pixel that sees one."""
    if not config.depth_weight or dataset.points is None:
        return None
    pixels, targets = point_targets(dataset.points.positions, dataset.poses[train_ids],
                                    dataset.cameras(train_ids), box)
    if not len(pixels):
        return None
    return (torch.as_tensor(pixels, device=device),
            torch.as_tensor(targets, dtype=torch.float32, device=device))


def _check_fits(weights: np.ndarray, supersampling: int, device: torch.device) -> None:
    """InputError unless the ray bank of the (n, H, W, M) training ``weights`` fits in the
    memory ``device`` has free: it holds every training pixel's n^2 rays (origins and
    directions), colour, weights, alpha and image index, float32 (``_ray_bank``)."""
    pixels = int(np.prod(weights.shape[:3]))
    needed = pixels * 4 * (6 * supersampling ** 2 + 3 + weights.shape[-1] + 1 + 2)
    free = free_memory(device)
    if needed > free:
        raise InputError(f"the rays of {pixels} training pixels need {needed / 2**30:.1f} GB, "
                         f"more than the {free / 2**30:.1f} GB free on {device}: train on "
                         "smaller images (downscale them) or fewer of them")
