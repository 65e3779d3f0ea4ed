"""Splat bakes: a weight NeRF as 3D Gaussians that a browser draws itself, each carrying the
palette weights of the light it sends (``model.Splats``; docs/splats.md).

The bake keeps only what the training views need. Their pixels are rendered with the
samples their light comes from (``render.samples.PixelSamples``); each pixel adds one point, its
median termination (where its ray reaches half of its light), with its opacity as its light
and its palette weights (divided by that opacity), to a cell of a grid over the scene box,
cells as large as a training pixel where the light stops. The points of a cell are split
by the side of its surface they were seen from (a wall seen from both sides). A cell side
where at least ``MIN_LIGHT`` of a pixel's light stops becomes one Gaussian: at the
light-weighted mean of its points, moved ``SIDE_OFFSET`` cells towards its side, shaped by
their spread (flat on a surface), scaled up to cover its cell and no thinner than
``FILTER`` cells, with the light-weighted mean palette weights, and opaque as the field's
density across a cell makes it (at least ``MIN_ALPHA``). Space no training ray ends in
(floaters that only views off the rig would see, the inside of objects) gets no splat. The
grid is made coarser until at most ``max_splats`` cells are kept. ``refine`` then fits the
splats to the network's weight renders of the training views.

References
----------
Z. Yu et al. Mip-Splatting: alias-free 3D Gaussian splatting. CVPR 2024 (the 3D filter).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from palette_core.basis import Basis
from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_writable

from ..data.cameras import Intrinsics
from ..fields import RGB
from ..render.contraction import contract
from ..train.loading import load_run
from ..train.run import Run, default_device, run_source
from .model import Splats, covariances, matrix_quaternions, read_splats, write_splats
from .rasterise import MAX_ALPHA, draw

#: How the splats were made, recorded in a bake's ``source``: a bake kept by ``cached_bake``
#: from another version of this module is made again. Raise it when the bake changes.
BAKE_VERSION = 4
MAX_SPLATS = 50_000
MIN_LIGHT = 0.5  # of a pixel's light (summed over the training views) that a kept cell stops
COVER = 1.5  # the points' spread in a cell is scaled by this
#: A cell's splats of light from either side of its surface (a wall seen from both sides) are
#: moved this far (cells) towards their side, so that each covers the other from its side.
SIDE_OFFSET = 0.25
#: Smallest standard deviation along any axis, in cells (about a training pixel where the
#: light stops): a 3D smoothing filter (Mip-Splatting), so that splats fitted at the
#: training views' resolution leave no holes where a browser draws them finer.
FILTER = 0.4
MIN_ALPHA = 0.05  # the first splats' opacities at least (``refine`` moves them)
#: Views drawn and fitted by ``refine`` on the CPU and on a CUDA device, where steps are
#: cheap and the steps past 500 still gain on the test views (docs/splats.md measures both).
REFINE_STEPS = {"cpu": 500, "cuda": 3000}
#: Adam learning rates of ``refine``: centres in cells, log scales, quaternions, opacity
#: logits, palette weights (or their logits, for the additive basis); larger ones left the
#: splats jittering (chosen on the still life and the Cornell box).
LEARNING_RATES = {"centres": 0.02, "scales": 0.005, "rotations": 0.001, "opacities": 0.05,
                  "weights": 0.0025}


def bake(run, views: np.ndarray, cameras: list[Intrinsics] | None, source: dict,
         max_splats: int = MAX_SPLATS, refine_steps: int | None = None,
         progress: bool = True, seed: int = 0) -> Splats:
    """Bake ``run`` from its training ``views`` (N, 4, 4) (module docstring), then refine
    the splats against the network's weight renders of those views for ``refine_steps``
    (``refine``; by default ``REFINE_STEPS`` of the device)."""
    if refine_steps is None:
        refine_steps = REFINE_STEPS.get(default_device().type, REFINE_STEPS["cpu"])
    if not 1 <= max_splats <= 10_000_000:
        raise InputError(f"max splats must be in [1, 10000000], got {max_splats}")
    if not 0 <= refine_steps <= 1_000_000:
        raise InputError(f"refine steps must be in [0, 1000000], got {refine_steps}")
    cameras = cameras or [run.intrinsics] * len(views)
    weights, opacity, samples = run.render(views, progress, cameras, samples=True)
    splats = _from_samples(run, views, cameras[0], weights, opacity, samples, source,
                           max_splats)
    splats.source["views"] = len(views)
    if refine_steps:
        splats = refine(splats, views, cameras, weights, opacity, refine_steps, progress, seed)
    return splats


def bake_run(rundir: str | os.PathLike, max_splats: int = MAX_SPLATS,
             refine_steps: int | None = None, progress: bool = True, run=None,
             dataset=None) -> Splats:
    """Bake the run in ``rundir`` (loaded, unless ``run`` is given) from the training views of
    its dataset (read, unless ``dataset`` is given; ``bake``); its ``source`` says which run
    and checkpoint (``run_source``)."""
    run = run or load_run(rundir)
    if not isinstance(run, Run):  # a splat run: its own splats as trained, not a bake
        return run.splats(_bake_source(run, rundir))
    if run.kind == RGB:
        raise InputError(f"{rundir} was trained on RGB only (strategy 'rgb'): it has no "
                         "weights to bake")
    dataset = dataset or run.dataset()
    train = dataset.indices("train")
    return bake(run, dataset.poses[train], dataset.cameras(train), _bake_source(run, rundir),
                max_splats, refine_steps, progress)


def _bake_source(run, rundir: str | os.PathLike) -> dict:
    """What a bake records of where it came from: the run (``run_source``) and
    ``BAKE_VERSION``."""
    return {**run_source(run, rundir), "bake_version": BAKE_VERSION}


SPLAT_CACHE = "splats.npz"  # the bake the studio keeps in a run folder


def cached_bake(run, rundir: str | os.PathLike, progress: bool = True, **options) -> Splats:
    """The bake kept in ``rundir`` (``SPLAT_CACHE``) if it was made from ``run`` as it is
    now by this ``BAKE_VERSION``, else a new one (``bake_run`` with ``options``), kept there
    for next time."""
    path = Path(rundir) / SPLAT_CACHE
    if path.is_file():
        kept = read_splats(path)
        if all(kept.source.get(k) == v for k, v in _bake_source(run, rundir).items()):
            return kept
    splats = bake_run(rundir, progress=progress, run=run, **options)
    with atomic_outputs(force=True) as stage:  # our own cache, of this run
        write_splats(splats, stage(path))
    return splats


def bake_to(rundir: str | os.PathLike, output: str | os.PathLike | None = None,
            max_splats: int = MAX_SPLATS, refine_steps: int | None = None,
            force: bool = False) -> tuple[Splats, Path]:
    """``bake_run`` written to ``output`` (default ``rundir``'s ``SPLAT_CACHE``, where the
    studio and ``splats_of`` find it), atomically; an existing file is replaced only with
    ``force``. Returns the splats and where they went."""
    output = Path(output or Path(rundir) / SPLAT_CACHE)
    check_writable([output], force)
    splats = bake_run(rundir, max_splats, refine_steps)
    with atomic_outputs(force) as stage:
        write_splats(splats, stage(output))
    return splats, output


def splats_of(path: str | os.PathLike) -> Splats:
    """The splats of a bake file, or of a run folder (its kept bake, ``cached_bake``)."""
    return cached_bake(load_run(path), path) if Path(path).is_dir() else read_splats(path)


def _from_samples(run, views: np.ndarray, camera: Intrinsics, weights: np.ndarray,
                  opacity: np.ndarray, samples, source: dict, max_splats: int) -> Splats:
    """The first splats: one a grid cell and side where the training views' light stops
    (module docstring); the cells start as large as a pixel where the light stops (the
    median over the points)."""
    m = weights.shape[-1]
    straight = (weights / np.maximum(opacity, 1e-6)[..., None]).reshape(-1, m)
    box = run.box
    low, high = box.centre - box.half, box.centre + box.half
    front, pixel = samples.front, samples.pixel
    median = front & np.r_[(pixel[1:] != pixel[:-1]) | ~front[1:], True]  # the last in front
    inside = median & np.all((samples.point >= low) & (samples.point <= high), axis=1)
    point = samples.point[inside].astype(np.float64)
    light = opacity.reshape(-1)[pixel[inside]].astype(np.float64)
    colour = straight[pixel[inside]]
    if not len(point):
        raise InputError("no training view's light stops inside the scene box: nothing to bake")
    eyes = views[pixel[inside] // (camera.height * camera.width), :3, 3]
    cell = float(np.median(np.linalg.norm(point - eyes, axis=1))) / camera.fx
    while True:
        index = np.floor((point - low) / cell).astype(np.int64)
        dims = np.maximum(np.ceil((high - low) / cell).astype(np.int64), 1)
        index = np.minimum(index, dims - 1)
        cells, which = np.unique(np.ravel_multi_index(index.T, dims), return_inverse=True)
        normal = _moments(which, point, light, len(cells))[2][:, :, 0]
        # a thin wall seen from both sides is two splats, one a side (a bit towards it)
        side = np.einsum("pc,pc->p", point - eyes, normal[which]) > 0
        groups, which = np.unique(2 * which + side, return_inverse=True)
        total = np.bincount(which, light)
        kept = total >= MIN_LIGHT
        if kept.sum() <= max_splats:
            break
        cell *= 2 ** (1 / 3)
    if not kept.any():
        raise InputError(f"no cell stops {MIN_LIGHT} of a pixel of the training views' light: "
                         "the run is fog still (train it longer)")
    keep = kept[which]
    which = np.searchsorted(np.flatnonzero(kept), which[keep])
    point, light, colour = point[keep], light[keep], colour[keep]
    s = int(kept.sum())
    centre, variance, axes, total = _moments(which, point, light, s)
    facing = np.where(groups[kept] % 2 == 1, -1.0, 1.0)  # towards the eyes of its light
    centre += (SIDE_OFFSET * cell * facing)[:, None] * normal[groups[kept] // 2]
    variance = COVER * variance + (FILTER * cell) ** 2
    axes[np.linalg.det(axes) < 0, :, 0] *= -1  # a rotation
    palette_weights = _weighted_sum(which, light[:, None] * colour, s) / total[:, None]
    sigma = _density(run, point)
    alpha = 1 - np.exp(-(_weighted_sum(which, light * sigma, s) / total) * cell / box.scale)
    alpha = np.clip(alpha, MIN_ALPHA, MAX_ALPHA)
    source = {**source, "cell": cell}
    return Splats(centre.astype(np.float32), np.sqrt(variance).astype(np.float32),
                  matrix_quaternions(axes).astype(np.float32), alpha.astype(np.float32),
                  palette_weights.astype(np.float32), run.palette, run.basis, run.order,
                  np.asarray(run.config.background, np.float64), source)


def _moments(which: np.ndarray, point: np.ndarray, light: np.ndarray, n: int) -> tuple:
    """The light-weighted centre (n, 3), the variances (n, 3) along the axes (n, 3, 3; the
    columns, the least spread first) and the light (n,) of the (P, 3) ``point``s of each of
    the ``n`` cells ``which`` (P,)."""
    total = np.bincount(which, light, n)
    centre = _weighted_sum(which, light[:, None] * point, n) / total[:, None]
    offset = point - centre[which]
    spread = _weighted_sum(which, light[:, None, None] * offset[:, :, None] * offset[:, None, :],
                           n) / total[:, None, None]
    variance, axes = np.linalg.eigh(spread)
    return centre, np.maximum(variance, 0), axes, total


def _weighted_sum(which: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n, ...) sums of ``values`` (P, ...) by cell ``which`` (P,)."""
    flat = values.reshape(len(values), -1)
    return np.stack([np.bincount(which, column, n) for column in flat.T],
                    1).reshape(n, *values.shape[1:])


@torch.no_grad()
def _density(run, points: np.ndarray) -> np.ndarray:
    """(P,) the field's density at world ``points`` (P, 3), per unit of normalised length (in
    NDC space, along the depth: NDC's depth stretches by (1 - z)^2 / (2 near) there)."""
    box = run.box
    device = run.occupancy.extent.device
    x = torch.as_tensor((points - box.centre) / box.scale, dtype=torch.float32, device=device)
    stretch = torch.ones_like(x[:, 0])
    if box.ndc is not None:
        x = box.ndc.from_box(x)
        stretch = (1 - x[:, 2]).square() / (2 * box.ndc.near)
    elif box.unbounded:
        x = contract(x)
    sigma = torch.cat([run.field.density(part)[0].float() for part in x.split(1 << 16)])
    return (sigma * stretch).cpu().numpy().astype(np.float64)


def refine(splats: Splats, views: np.ndarray, cameras: list[Intrinsics], weights: np.ndarray,
           opacity: np.ndarray, steps: int, progress: bool = True, seed: int = 0,
           device: torch.device | None = None) -> Splats:
    """Fit the splats to weight renders: each step draws one of ``views`` (N, 4, 4) with its
    camera, chosen at random, and takes an Adam step on the squared error of its
    (N, H, W, M) ``weights`` and (N, H, W) ``opacity`` (the network's renders: any viewpoint
    would do). Additive weights stay non-negative and sum to one (a softmax). Splats whose
    opacity falls below 1/255 are dropped. Runs on ``device`` (CUDA when present)."""
    device = device or default_device()
    cell = splats.source["cell"]
    floor = FILTER * cell
    raw = np.sqrt(np.maximum(splats.scales.astype(np.float64) ** 2 - floor ** 2,
                             (0.01 * cell) ** 2))
    parameters = {
        "centres": torch.tensor(splats.centres),
        "scales": torch.tensor(np.log(raw), dtype=torch.float32),
        "rotations": torch.tensor(splats.rotations),
        "opacities": torch.tensor(np.log(splats.opacities / (1 - splats.opacities))),
        "weights": torch.tensor(splats.weights),
    }
    simplex = splats.basis == Basis.ADDITIVE  # additive weights stay on it: a softmax
    if simplex:
        parameters["weights"] = torch.log(parameters["weights"].clamp(min=1e-6))
    parameters = {name: tensor.to(device).requires_grad_(True)
                  for name, tensor in parameters.items()}
    scale = {"centres": cell}
    optimiser = torch.optim.Adam([{"params": [tensor], "lr": LEARNING_RATES[name]
                                   * scale.get(name, 1.0)}
                                  for name, tensor in parameters.items()])
    generator = torch.Generator().manual_seed(seed)
    m = weights.shape[-1]
    bar = tqdm(range(steps), desc="refine splats", unit="step", disable=not progress)
    for _ in bar:
        i = int(torch.randint(len(views), (1,), generator=generator))
        drawn, covered = draw(parameters["centres"], _covariances(parameters, floor),
                               _weights(parameters, simplex),
                               torch.sigmoid(parameters["opacities"]),
                               torch.as_tensor(views[i], device=device), cameras[i])
        loss = (torch.mean((drawn - torch.as_tensor(weights[i], device=device).view(-1, m)) ** 2)
                + torch.mean((covered - torch.as_tensor(opacity[i], device=device).view(-1))
                             ** 2))
        if not loss.requires_grad:  # no splat shows in this view
            continue
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        bar.set_postfix(loss=f"{loss.item():.2e}", refresh=False)
    with torch.no_grad():
        alpha = torch.sigmoid(parameters["opacities"]).cpu().numpy()
        keep = alpha >= 1 / 255
        rotations = parameters["rotations"].cpu().numpy()[keep]
        refined = Splats(
            parameters["centres"].cpu().numpy()[keep].astype(np.float32),
            _scales(parameters, floor).cpu().numpy()[keep].astype(np.float32),
            (rotations / np.linalg.norm(rotations, axis=1, keepdims=True)).astype(np.float32),
            np.clip(alpha[keep], 1 / 255, MAX_ALPHA).astype(np.float32),
            _weights(parameters, simplex).cpu().numpy()[keep].astype(np.float32),
            splats.palette, splats.basis, splats.order, splats.background,
            {**splats.source, "refine_steps": steps})
    return refined


def _weights(parameters: dict, simplex: bool) -> torch.Tensor:
    """(S, M) palette weights of ``refine``'s parameters: a softmax of them on the simplex."""
    return torch.softmax(parameters["weights"], 1) if simplex else parameters["weights"]


def _scales(parameters: dict, floor: float) -> torch.Tensor:
    """(S, 3) standard deviations of ``refine``'s log scales, with the ``FILTER`` ``floor``
    added in quadrature."""
    return torch.sqrt(torch.exp(2 * parameters["scales"]) + floor ** 2)


def _covariances(parameters: dict, floor: float) -> torch.Tensor:
    """(S, 3, 3) covariances R diag(s^2) R^T of ``refine``'s parameters (``_scales``,
    quaternions R)."""
    return covariances(parameters["rotations"], _scales(parameters, floor))


