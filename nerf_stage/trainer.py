"""Train a weight NeRF on a dataset and its weight stack; load a trained run and render it.

A run directory holds ``config.json`` (the ``TrainConfig``) and ``checkpoint.pt``
(field, optimisers, random state, occupancy grid, palette, scene box and the
training log). Training resumes from the checkpoint and then gives the same
result as an uninterrupted run.

Strategies (PaletteNeRF, sec. 3.3):

- ``two-stage``: P iterations on RGB, then the density part is frozen, the output
  layer replaced by one of M channels (first fitted alone, ``_fit_output``), and
  the colour part fine-tuned on the weight images for F iterations (L2 loss).
- ``traditional``: the M-channel field trained from scratch on weights for P + F.
- ``rgb``: an RGB NeRF for P + F iterations (the baseline).

Weight targets are premultiplied by alpha: additive stacks (straight, summing
to one) are multiplied by the frame's alpha; transport stacks from
``nerf-stage simulate`` already are.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from palette_core.errors import InputError
from palette_core.basis import basis_terms
from palette_core.stack import WeightStack, n_terms

from .config import TrainConfig
from .data import Dataset, Intrinsics, join_weights
from .fields import Field, make_field
from .rendering import (
    OccupancyGrid,
    SceneBox,
    camera_rays,
    march_rays,
    render_rays,
    scene_box,
)

CHECKPOINT = "checkpoint.pt"
CONFIG = "config.json"
RENDER_CHUNK = 1 << 13  # rays per forward pass when rendering whole views


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


@dataclass
class Run:
    """A trained (or training) weight NeRF and what is needed to use it.

    Attributes
    ----------
    config : TrainConfig
    field : Field
    occupancy : OccupancyGrid
    box : SceneBox
    intrinsics : Intrinsics
    palette : (K, 3) float64
    basis : str
        ``"additive"`` or ``"transport"``; the field outputs RGB while ``kind`` is ``rgb``.
    order : int
    meta : dict
        Dataset and weight-stack paths, the stack's meta, the training log.
    """

    config: TrainConfig
    field: Field
    occupancy: OccupancyGrid
    box: SceneBox
    intrinsics: Intrinsics
    palette: np.ndarray
    basis: str
    order: int
    meta: dict

    @property
    def terms(self) -> np.ndarray:
        """(M, 3) colour of each weight channel for the run's palette."""
        return basis_terms(self.palette, self.basis, self.order)

    @property
    def step(self) -> float | None:
        grid = getattr(self.field, "voxels_per_unit", None)
        return None if grid is None else self.config.step_voxels / grid

    def render_rays(self, origins, directions, generator=None):
        """Normalised rays -> ((R, C) values, (R,) opacity)."""
        return render_rays(self.field, self.occupancy, origins, directions,
                           self.config.mlp_samples, self.step, generator)

    @torch.no_grad()
    def render(self, poses: np.ndarray, progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Render whole views.

        Returns
        -------
        values : (N, H, W, C) float32
            The field's outputs (weights, or RGB) premultiplied by opacity.
        acc : (N, H, W) float32
        """
        self.field.eval()
        device = self.occupancy.extent.device
        values, accs = [], []
        for pose in tqdm(poses, desc="render", unit="view", disable=not progress):
            origins, directions = normalised_rays(pose, self.intrinsics, self.box, device)
            outputs = [self.render_rays(o, d) for o, d in zip(origins.split(RENDER_CHUNK),
                                                              directions.split(RENDER_CHUNK))]
            shape = (self.intrinsics.height, self.intrinsics.width)
            values.append(torch.cat([v for v, _ in outputs]).reshape(*shape, -1).cpu().numpy())
            accs.append(torch.cat([a for _, a in outputs]).reshape(shape).cpu().numpy())
        return np.stack(values), np.stack(accs)


def normalised_rays(pose, intrinsics, box: SceneBox, device):
    """(H W, 3) origins in the normalised box and unit directions of one camera, float32."""
    origins, directions = camera_rays(pose, intrinsics)
    origins = (origins - box.centre) / box.scale
    return (torch.as_tensor(origins.reshape(-1, 3), dtype=torch.float32, device=device),
            torch.as_tensor(directions.reshape(-1, 3), dtype=torch.float32, device=device))


def train(config: TrainConfig, dataset: Dataset, stack: WeightStack, rundir: str | os.PathLike,
          resume: bool = False, meta: dict | None = None, progress: bool = True,
          device: torch.device | None = None) -> Run:
    """Train (or resume) a weight NeRF and write its run directory.

    Parameters
    ----------
    dataset : Dataset
        Its ``background`` must be ``config.background``.
    stack : WeightStack
        Weights of the dataset's training frames (``join_weights``).
    resume : bool
        Continue from ``rundir``'s checkpoint (same config) instead of starting afresh.
    meta : dict
        Recorded in the checkpoint (paths of the dataset and the stack).

    Raises
    ------
    InputError
        If the weights do not match the dataset or the checkpoint does not match the config.
    """
    device = device or default_device()
    rundir = Path(rundir)
    weights = join_weights(dataset, stack, "train")  # (n, H, W, M)
    train_ids = dataset.indices("train")
    if stack.basis == "additive":
        weights = weights * dataset.alpha[train_ids, ..., None]
    box = scene_box(dataset.poses[train_ids], dataset.intrinsics, dataset.alpha[train_ids])
    run = _new_run(config, box, dataset, stack, train_ids, device)
    run.meta.update(meta or {})
    rays = _ray_bank(run, dataset, train_ids, weights, device)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    start, log, optimiser_states = 0, [], None
    if resume:
        state = _read_checkpoint(rundir / CHECKPOINT)
        if state["config"] != asdict(config):
            raise InputError(f"{rundir} was trained with another config; "
                             "start afresh with --force")
        if state["output"]["kind"] != run.field.kind:
            _start_finetune(run)
        run.field.load_state_dict(state["field"])
        run.occupancy.load_state_dict(state["occupancy"])
        generator.set_state(state["generator"])
        start, log, optimiser_states = state["iteration"], state["log"], state["optimisers"]
    rundir.mkdir(parents=True, exist_ok=True)
    config.save(rundir / CONFIG)
    optimisers = _optimisers(run)
    for optimiser, saved in zip(optimisers, optimiser_states or []):
        optimiser.load_state_dict(saved)
    terms = torch.as_tensor(run.terms, dtype=torch.float32, device=device)
    background = torch.as_tensor(config.background, dtype=torch.float32, device=device)
    bar = tqdm(range(start, config.total_iters), desc=f"train {config.backbone}",
               initial=start, total=config.total_iters, disable=not progress, unit="it")
    clock = time.perf_counter() - (log[-1]["seconds"] if log else 0.0)
    for it in bar:
        finetuning = config.strategy == "two-stage" and it >= config.pretrain_iters
        if finetuning and run.field.kind == "rgb":
            _start_finetune(run)
            _fit_output(run, rays, generator)
            optimisers = _optimisers(run)
        if (config.backbone == "grid" and not finetuning and it >= config.warmup_iters
                and it % config.occupancy_every == 0):
            run.occupancy.update(run.field, run.step, generator)
        batch = torch.randint(len(rays["origins"]), (config.batch_rays,), generator=generator,
                              device=device)
        run.field.train()
        loss, psnr = _loss(run, {key: value[batch] for key, value in rays.items()}, terms,
                           background, generator)
        for optimiser in optimisers:
            optimiser.zero_grad(set_to_none=True)
        loss.backward()
        for optimiser in optimisers:
            optimiser.step()
        log.append({"iteration": it + 1, "seconds": time.perf_counter() - clock,
                    "loss": loss.item(), "psnr": psnr, "stage": run.field.kind})
        bar.set_postfix(stage=run.field.kind, loss=f"{loss.item():.2e}", psnr=f"{psnr:.2f}")
        if (it + 1) % config.checkpoint_every == 0 or it + 1 == config.total_iters:
            _save_checkpoint(run, rundir / CHECKPOINT, optimisers, generator, it + 1, log)
    run.meta["log"] = log
    return run


def _loss(run: Run, rays: dict, terms, background, generator) -> tuple[torch.Tensor, float]:
    """Loss of one batch of rays, and the PSNR of its colours (through the weights).

    L2 on RGB while the output is RGB, else ``_weight_loss``; plus, while the density
    trains, ``opacity_weight`` x L2 of the opacity against alpha.
    """
    values, acc = run.render_rays(rays["origins"], rays["directions"], generator)
    if run.field.kind == "rgb":
        rgb = values + (1 - acc[:, None]) * background
        loss = torch.mean((rgb - rays["rgb"]) ** 2)
    else:
        loss = _weight_loss(run.field.kind, values, rays["weights"])
        rgb = values @ terms + (1 - acc[:, None]) * background
    if acc.requires_grad:
        loss = loss + run.config.opacity_weight * torch.mean((acc - rays["alpha"]) ** 2)
    with torch.no_grad():
        mse = float(torch.mean((rgb.clamp(0, 1) - rays["rgb"]) ** 2))
    return loss, -10 * math.log10(max(mse, 1e-10))


def _weight_loss(kind: str, values: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """L2 of (R, M) premultiplied weights; transport weights are tone-mapped by
    w / (1 + w) first, so that emitters of radiance far above one do not drown the rest."""
    if kind == "transport":
        values, targets = values / (1 + values), targets / (1 + targets)
    return torch.mean((values - targets) ** 2)


def _new_run(config, box, dataset, stack, train_ids, device) -> Run:
    channels = n_terms(len(stack.palette), stack.basis, stack.order)
    kind = "rgb" if config.strategy != "traditional" else stack.basis
    torch.manual_seed(config.seed)
    extent = torch.as_tensor(box.extent, dtype=torch.float32)
    field = make_field(config, extent, kind, 3 if kind == "rgb" else channels).to(device)
    occupancy = OccupancyGrid(extent, config.occupancy_voxels)
    occupancy.carve(box, dataset.poses[train_ids], dataset.intrinsics, dataset.alpha[train_ids])
    meta = {"channels": channels, "stack_meta": stack.meta}
    return Run(config, field, occupancy.to(device), box, dataset.intrinsics,
               np.asarray(stack.palette, np.float64), stack.basis, stack.order, meta)


def _ray_bank(run: Run, dataset: Dataset, train_ids, weights, device) -> dict:
    origins, directions = zip(*(normalised_rays(dataset.poses[i], dataset.intrinsics, run.box,
                                                device) for i in train_ids))

    def flat(a):
        return torch.as_tensor(a.reshape(-1, a.shape[-1]), dtype=torch.float32, device=device)

    return {"origins": torch.cat(origins), "directions": torch.cat(directions),
            "rgb": flat(dataset.images[train_ids]), "weights": flat(weights),
            "alpha": flat(dataset.alpha[train_ids, ..., None])[:, 0]}


def _start_finetune(run: Run) -> None:
    """Freeze the density part and put in a new M-channel output layer."""
    for p in run.field.density_parameters():
        p.requires_grad_(False)
    run.field.set_output(run.basis, run.meta["channels"])


def _fit_output(run: Run, rays: dict, generator: torch.Generator, iterations: int = 100) -> None:
    """Fit the new output layer alone before fine-tuning starts.

    The frozen field is run once over a batch of training rays; the output layer's
    inputs at their visible samples are cached, and the layer is fitted to the
    rays' weights (the training loss) by L-BFGS on that cache. This costs about one
    training step, and fine-tuning then starts near the RGB NeRF's batch PSNR
    instead of far below it (Cornell box after 150 RGB steps: 21.6 dB, not 2.8).
    """
    field = run.field
    batch = torch.randint(len(rays["origins"]), (run.config.batch_rays,), generator=generator,
                          device=rays["origins"].device)
    directions = rays["directions"][batch]
    with torch.no_grad():
        samples = march_rays(field, run.occupancy, rays["origins"][batch], directions,
                             run.config.mlp_samples, run.step).visible()
        features = field.head(samples.h, directions[samples.ray])
    targets = rays["weights"][batch]
    fit = torch.optim.LBFGS(field.output.parameters(), max_iter=iterations,
                            line_search_fn="strong_wolfe")

    def closure():
        fit.zero_grad()
        values = samples.composite(field.colour_output(features))
        loss = _weight_loss(field.kind, values, targets)
        loss.backward()
        return loss

    fit.step(closure)


def _optimisers(run: Run) -> list[torch.optim.Optimizer]:
    """SparseAdam for voxel grids, Adam for networks, over the parameters being trained."""
    trained = [p for p in run.field.parameters() if p.requires_grad]
    sparse = [p for p in run.field.grid_parameters() if p.requires_grad]
    dense = [p for p in trained if all(p is not s for s in sparse)]
    optimisers = [torch.optim.Adam(dense, lr=run.config.network_lr)]
    if sparse:
        optimisers.append(torch.optim.SparseAdam(sparse, lr=run.config.grid_lr))
    return optimisers


def _save_checkpoint(run, path: Path, optimisers, generator, iteration: int, log) -> None:
    state = {
        "iteration": iteration,
        "config": asdict(run.config),
        "field": run.field.state_dict(),
        "output": run.field.extra_state_dict(),
        "optimisers": [o.state_dict() for o in optimisers],
        "generator": generator.get_state(),
        "occupancy": run.occupancy.state_dict(),
        "box": run.box.to_dict(),
        "intrinsics": run.intrinsics.__dict__,
        "palette": run.palette.tolist(),
        "basis": run.basis,
        "order": run.order,
        "meta": run.meta,
        "log": log,
    }
    partial = path.with_name(path.name + ".partial")
    torch.save(state, partial)
    os.replace(partial, path)


def _read_checkpoint(path: Path) -> dict:
    if not path.is_file():
        raise InputError(f"{path.parent} holds no checkpoint ({CHECKPOINT}): train it first")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many types for a damaged file
        raise InputError(f"cannot read checkpoint {path}: {exc}") from None


def load_run(rundir: str | os.PathLike, device: torch.device | None = None) -> Run:
    """The trained run in ``rundir``.

    Raises
    ------
    InputError
        If there is no readable checkpoint.
    """
    device = device or default_device()
    state = _read_checkpoint(Path(rundir) / CHECKPOINT)
    config = TrainConfig(**state["config"])
    box = SceneBox(np.array(state["box"]["centre"]), np.array(state["box"]["half"]))
    extent = torch.as_tensor(box.extent, dtype=torch.float32)
    output = state["output"]
    field = make_field(config, extent, output["kind"], output["channels"])
    field.load_state_dict(state["field"])
    occupancy = OccupancyGrid(extent, config.occupancy_voxels)
    occupancy.load_state_dict(state["occupancy"])
    meta = dict(state["meta"], log=state["log"], iteration=state["iteration"])
    return Run(config, field.to(device), occupancy.to(device), box,
               Intrinsics(**state["intrinsics"]), np.array(state["palette"]), state["basis"],
               state["order"], meta)
