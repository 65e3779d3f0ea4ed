"""Splat bakes: a weight NeRF as 3D Gaussians that a browser draws itself, each carrying the
palette weights of the light it sends, so that recolouring stays ``weights @ basis`` per
splat (docs/splats.md, format ``palette-splats/1`` in docs/formats.md).

The bake keeps only what the training views need. Their pixels are rendered with the
samples their light comes from (``regions.PixelSamples``); each pixel adds one point, its
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

``render_splats`` draws a bake as weight images (EWA splatting, sorted front to back, as
3D Gaussian splatting does), which recolour like any weight render.

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (projection of the covariances, front-to-back blending, the low-pass of 0.3 pixels).
M. Zwicker et al. EWA splatting. IEEE TVCG 8(3), 2002.
Z. Yu et al. Mip-Splatting: alias-free 3D Gaussian splatting. CVPR 2024 (the 3D filter).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from palette_core.basis import Basis, basis_terms, n_terms
from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs
from palette_core.stack import NpzReader

from .cameras import Intrinsics
from .fields import RGB
from .regions import Region
from .run import default_device, load_run, run_source

SPLAT_FORMAT = "palette-splats/1"
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
MIN_ALPHA, MAX_ALPHA = 0.05, 0.99  # the first splats' opacities (``refine`` moves them)
#: Pixels^2 added to every projected covariance: Mip-Splatting's 2D filter. (3D Gaussian
#: splatting's 0.3, which viser adds at the screen's resolution, let splats fitted at the
#: training views' resolution lean on that blur to cover surfaces: holes where a browser
#: draws them finer; docs/splats.md.)
LOW_PASS = 0.1
#: Pairs behind which less light than this is left are not drawn (3D Gaussian splatting's
#: early stop): a pixel changes by less than this.
MIN_TRANSMITTANCE = 1e-4
#: Views drawn and fitted by ``refine`` on the CPU and on a CUDA device, where a step takes
#: about 15 ms (H200) and the steps past 500 still gain 1-2 dB on the training ring's test
#: views (docs/splats.md).
REFINE_STEPS = {"cpu": 500, "cuda": 3000}
#: Adam learning rates of ``refine``: centres in cells, log scales, quaternions, opacity
#: logits, palette weights (or their logits, for the additive basis). Chosen on clay-twins
#: (docs/splats.md): the first rates tried (a fifth of a cell a step for the centres, two to
#: four times these for scales, rotations and weights) left the splats jittering, 4 dB
#: lower.
LEARNING_RATES = {"centres": 0.02, "scales": 0.005, "rotations": 0.001, "opacities": 0.05,
                  "weights": 0.0025}


@dataclass
class Splats:
    """Gaussians with palette weights.

    Attributes
    ----------
    centres : (S, 3) float32
        World positions.
    scales : (S, 3) float32
        Standard deviations along the axes of ``rotations``.
    rotations : (S, 4) float32
        Unit quaternions (w, x, y, z), local to world.
    opacities : (S,) float32
        Peak opacity in (0, 1).
    weights : (S, M) float32
        Palette weights of each splat's light (summing to one for the additive basis).
    palette : (K, 3) float64
    basis : Basis
    order : int
    background : (3,) float64
    source : dict
        The run it was baked from: its folder, checkpoint iteration and training time, the
        cell size, the views used.
    """

    centres: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray
    opacities: np.ndarray
    weights: np.ndarray
    palette: np.ndarray
    basis: Basis
    order: int
    background: np.ndarray
    source: dict

    def __len__(self) -> int:
        return len(self.centres)

    def covariances(self) -> np.ndarray:
        """(S, 3, 3) float64 world covariances R diag(s^2) R^T."""
        return covariances(torch.as_tensor(self.rotations, dtype=torch.float64),
                           torch.as_tensor(self.scales, dtype=torch.float64)).numpy()

    def colours(self, palette: np.ndarray | None = None,
                regions: Sequence[Region] = ()) -> np.ndarray:
        """(S, 3) float32 colour of every splat for ``palette`` (the run's by default); with
        ``regions``, only the splats whose centres are inside one take it."""
        palette = self.palette if palette is None else np.asarray(palette, np.float64)
        terms = basis_terms(palette, self.basis, self.order).astype(np.float32)
        colours = np.clip(self.weights @ terms, 0, 1)
        if regions:
            outside = ~np.any([region.contains(self.centres) for region in regions], axis=0)
            colours[outside] = self.colours()[outside]
        return colours


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
    if run.field.kind == RGB:
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
    """(P,) the field's density at world ``points`` (P, 3), per unit of normalised length."""
    box = run.box
    device = run.occupancy.extent.device
    x = torch.as_tensor((points - box.centre) / box.scale, dtype=torch.float32, device=device)
    if box.unbounded:
        from .contraction import contract

        x = contract(x)
    return torch.cat([run.field.density(part)[0].float()
                      for part in x.split(1 << 16)]).cpu().numpy().astype(np.float64)


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
        drawn, covered = _draw(parameters["centres"], _covariances(parameters, floor),
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


def covariances(quaternions: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(S, 3, 3) R diag(s^2) R^T from (S, 4) quaternions (w, x, y, z; any length) and (S, 3)
    standard deviations s."""
    w, x, y, z = (quaternions / quaternions.norm(dim=1, keepdim=True)).T
    rotation = torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    return (rotation * scales[:, None, :] ** 2) @ rotation.transpose(1, 2)


def matrix_quaternions(r: np.ndarray) -> np.ndarray:
    """(S, 3, 3) rotation matrices -> (S, 4) unit quaternions (w, x, y, z), w >= 0."""
    r = np.asarray(r, np.float64)
    trace = np.trace(r, axis1=1, axis2=2)
    candidates = np.stack([1 + trace, 1 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2],
                           1 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2],
                           1 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2]], 1)
    best = np.argmax(candidates, 1)  # the largest component, divided by without loss
    q = np.empty((len(r), 4))
    for k in range(4):
        at = best == k
        m, c = r[at], np.sqrt(np.maximum(candidates[at, k], 1e-12)) * 2  # 4 |q_k|
        if k == 0:
            q[at] = np.stack([c / 4, (m[:, 2, 1] - m[:, 1, 2]) / c, (m[:, 0, 2] - m[:, 2, 0]) / c,
                              (m[:, 1, 0] - m[:, 0, 1]) / c], 1)
        elif k == 1:
            q[at] = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / c, c / 4, (m[:, 0, 1] + m[:, 1, 0]) / c,
                              (m[:, 0, 2] + m[:, 2, 0]) / c], 1)
        elif k == 2:
            q[at] = np.stack([(m[:, 0, 2] - m[:, 2, 0]) / c, (m[:, 0, 1] + m[:, 1, 0]) / c, c / 4,
                              (m[:, 1, 2] + m[:, 2, 1]) / c], 1)
        else:
            q[at] = np.stack([(m[:, 1, 0] - m[:, 0, 1]) / c, (m[:, 0, 2] + m[:, 2, 0]) / c,
                              (m[:, 1, 2] + m[:, 2, 1]) / c, c / 4], 1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@torch.no_grad()
def render_splats(splats: Splats, poses: np.ndarray, camera: Intrinsics,
                  progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Draw a bake from (N, 4, 4) ``poses`` (OpenGL camera-to-world) with ``camera``.

    Returns
    -------
    weights : (N, H, W, M) float32
        Composited palette weights, premultiplied by opacity (a weight render).
    opacity : (N, H, W) float32
    """
    tensors = _tensors(splats)
    h, w = camera.height, camera.width
    out_weights, out_opacity = [], []
    for pose in tqdm(poses, desc="draw splats", unit="view", disable=not progress):
        weights, opacity = _draw(*tensors, torch.as_tensor(pose), camera)
        out_weights.append(weights.view(h, w, -1).float().numpy())
        out_opacity.append(opacity.view(h, w).float().numpy())
    return np.stack(out_weights), np.stack(out_opacity)


def _tensors(splats: Splats) -> tuple[torch.Tensor, ...]:
    """Centres, covariances, weights and opacities as float32 tensors."""
    return (torch.as_tensor(splats.centres), torch.as_tensor(splats.covariances()).float(),
            torch.as_tensor(splats.weights), torch.as_tensor(splats.opacities))


def _draw(centres, covariances, values, opacities, pose: torch.Tensor,
          camera: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """(H W, M) composited ``values`` and (H W,) opacity of one view (differentiable in the
    splats' parameters)."""
    h, w = camera.height, camera.width
    weights = values.new_zeros(h * w, values.shape[1])
    opacity = values.new_zeros(h * w)
    pairs = _pairs(centres, covariances, opacities, pose, camera)
    if pairs is None:
        return weights, opacity
    pixel, splat, alpha = pairs
    contribution = _transmittance(pixel, alpha) * alpha
    weights = weights.index_add(0, pixel, contribution[:, None] * values.index_select(0, splat))
    return weights, opacity.index_add(0, pixel, contribution)


def _transmittance(pixel: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """(P,) light left in front of each pair (``pixel``, ``alpha``), sorted by pixel, then
    front to back: a product over its pixel's earlier pairs, summed as logarithms in float64
    (a view's running sum spans all of its pairs)."""
    log_keep = torch.log1p(-alpha).double()
    running = torch.cumsum(log_keep, 0)
    starts = torch.ones_like(pixel, dtype=torch.bool)
    starts[1:] = pixel[1:] != pixel[:-1]
    first = torch.cummax(torch.where(starts, torch.arange(len(pixel), device=pixel.device), 0),
                         0).values
    before = running - log_keep - (running - log_keep).index_select(0, first)
    return torch.exp(before).to(alpha.dtype)


def _pairs(centres, covariances, opacities, pose, camera: Intrinsics, reach: int = 32):
    """The (pixel, splat, alpha) pairs of one view above 1/255 with at least
    ``MIN_TRANSMITTANCE`` of light left in front of them, sorted by pixel, then front to
    back; None when no splat shows."""
    pose = pose.to(centres.dtype)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    local = (centres - origin) @ rotation  # camera axes: x right, y up, looking down -z
    depth = -local[:, 2]
    index = torch.nonzero(depth > 1e-3)[:, 0]
    local, depth = local.index_select(0, index), depth.index_select(0, index)
    covariances = covariances.index_select(0, index)
    fx, fy = camera.fx, camera.fy
    u = camera.cx + fx * local[:, 0] / depth
    v = camera.cy - fy * local[:, 1] / depth
    jacobian = depth.new_zeros(len(depth), 2, 3)
    jacobian[:, 0, 0] = fx / depth
    jacobian[:, 0, 2] = fx * local[:, 0] / depth ** 2
    jacobian[:, 1, 1] = -fy / depth
    jacobian[:, 1, 2] = -fy * local[:, 1] / depth ** 2
    transform = jacobian @ rotation.T
    projected = transform @ covariances @ transform.transpose(1, 2)
    a, b, c = projected[:, 0, 0] + LOW_PASS, projected[:, 0, 1], projected[:, 1, 1] + LOW_PASS
    determinant = a * c - b * b
    conic = torch.stack([c, -b, a], 1) / determinant[:, None]  # the inverse, per splat
    # the box around the ellipse outside which a splat's alpha is below 1/255
    opacities = opacities.index_select(0, index)
    level = torch.sqrt(2 * torch.log((255 * opacities.detach()).clamp(min=1)))
    rx = (level * torch.sqrt(a.detach())).clamp(max=reach)
    ry = (level * torch.sqrt(c.detach())).clamp(max=reach)
    x0 = (u.detach() - rx).floor().clamp(0, camera.width)
    x1 = (u.detach() + rx).ceil().clamp(0, camera.width)
    y0 = (v.detach() - ry).floor().clamp(0, camera.height)
    y1 = (v.detach() + ry).ceil().clamp(0, camera.height)
    shown = (x1 > x0) & (y1 > y0)
    if not shown.any():
        return None
    drawn = torch.nonzero(shown)[:, 0]
    drawn = drawn[torch.argsort(depth.detach()[drawn])]  # front to back: pairs come so
    # each splat's projection (u, v, conic, opacity), gathered with gradients only for the
    # pairs that show
    table = torch.cat([u[:, None], v[:, None], conic, opacities[:, None]], 1)
    # the rows of each splat's box, and in each row the pixels inside its ellipse
    row_splat, py = _spans(drawn, y0.index_select(0, drawn).long(),
                           y1.index_select(0, drawn).long())
    row_u, row_v, ca, cb, cc, _ = table.detach().index_select(0, row_splat).T
    row_x0, row_x1, row_level = torch.stack([x0, x1, level], 1).index_select(0, row_splat).T
    dy = py + 0.5 - row_v
    room = (cb * dy) ** 2 - ca * (cc * dy * dy - row_level ** 2)
    half = torch.sqrt(room.clamp(min=0)) / ca
    middle = row_u - 0.5 - cb * dy / ca  # pixel x + 0.5 - u = dx
    first = torch.maximum(torch.ceil(middle - half), row_x0).long()
    last = torch.minimum(torch.floor(middle + half), row_x1 - 1).long()
    row, px = _spans(torch.arange(len(py), device=py.device), first,
                     torch.where(room >= 0, torch.maximum(last + 1, first), first))
    ids, py = row_splat.index_select(0, row), py.index_select(0, row)
    with torch.no_grad():  # the pairs that show, sorted by pixel, then front to back
        alpha = _alpha(table.index_select(0, ids), px, py)
        visible = torch.nonzero(alpha >= 1 / 255)[:, 0]
        pixel = py.index_select(0, visible) * camera.width + px.index_select(0, visible)
        pixel, order = torch.sort(pixel, stable=True)  # by pixel, still front to back
        visible = visible.index_select(0, order)
        kept = _transmittance(pixel, alpha.index_select(0, visible)) >= MIN_TRANSMITTANCE
        shown, pixel = visible[kept], pixel[kept]
    ids, px, py = ids.index_select(0, shown), px.index_select(0, shown), py.index_select(0, shown)
    return pixel, index.index_select(0, ids), _alpha(table.index_select(0, ids), px, py)


def _spans(owners: torch.Tensor, start: torch.Tensor,
           stop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each of ``owners`` (N,) with the whole numbers from its ``start`` to its ``stop``
    (N,; excluded), in order: (owner, number) pairs as two (P,) tensors."""
    count = stop - start
    which = torch.repeat_interleave(torch.arange(len(owners), device=owners.device), count)
    offset = torch.arange(len(which), device=owners.device) - (torch.cumsum(count, 0)
                                                              - count).index_select(0, which)
    return owners.index_select(0, which), start.index_select(0, which) + offset


def _alpha(pairs: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """(P,) opacity at pixels (``px``, ``py``) of splats projected as ``pairs`` (P, 6): centre
    u, v, inverse covariance (a, b, c), peak opacity."""
    dx = px + 0.5 - pairs[:, 0]
    dy = py + 0.5 - pairs[:, 1]
    power = -0.5 * (pairs[:, 2] * dx * dx + 2 * pairs[:, 3] * dx * dy + pairs[:, 4] * dy * dy)
    return torch.clamp(pairs[:, 5] * torch.exp(power), max=MAX_ALPHA)


def write_splats(splats: Splats, path: str | os.PathLike) -> None:
    """Write a bake as NPZ format ``palette-splats/1``."""
    np.savez(path, format=np.array(SPLAT_FORMAT), centres=splats.centres, scales=splats.scales,
             rotations=splats.rotations, opacities=splats.opacities, weights=splats.weights,
             palette=splats.palette, basis=np.array(str(splats.basis)),
             order=np.array(splats.order), background=splats.background,
             source=np.array(json.dumps(splats.source)))


def read_splats(path: str | os.PathLike) -> Splats:
    """Read and validate a bake.

    Raises
    ------
    InputError
        If the file is not a ``palette-splats/1`` NPZ, or a key is missing or malformed.
    """
    with NpzReader(Path(path), f"a splat bake ({SPLAT_FORMAT})") as npz:
        if npz.text("format") != SPLAT_FORMAT:
            raise InputError(f"{path} is not a splat bake (format {SPLAT_FORMAT})")
        arrays = {key: npz.array(key, "f") for key in ("centres", "scales", "rotations",
                                                       "opacities", "weights", "palette",
                                                       "background")}
        basis, order = Basis.parse(npz.text("basis")), int(npz.array("order", "iu"))
        source = npz.json("source")
    s = len(arrays["centres"])
    m = n_terms(len(arrays["palette"]), basis, order)
    shapes = {"centres": (s, 3), "scales": (s, 3), "rotations": (s, 4), "opacities": (s,),
              "weights": (s, m), "background": (3,)}
    if (any(arrays[k].shape != shape for k, shape in shapes.items())
            or arrays["palette"].ndim != 2 or arrays["palette"].shape[1:] != (3,)
            or not isinstance(source, dict)):
        raise InputError(f"{path}: the splats' arrays have the wrong shapes")
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise InputError(f"{path}: the splats hold NaN or infinity")
    if (arrays["scales"] <= 0).any() or not ((arrays["opacities"] > 0)
                                             & (arrays["opacities"] < 1)).all():
        raise InputError(f"{path}: splat scales must be positive and opacities in (0, 1)")
    if (np.linalg.norm(arrays["rotations"], axis=1) < 1e-6).any():
        raise InputError(f"{path}: a splat rotation is not a quaternion")
    return Splats(arrays["centres"], arrays["scales"], arrays["rotations"], arrays["opacities"],
                  arrays["weights"], arrays["palette"].astype(np.float64), basis, order,
                  arrays["background"].astype(np.float64), source)


#: The spherical-harmonics constant of degree 0: a colour c is stored as (c - 0.5) / SH_C0.
SH_C0 = 0.28209479177387814


def write_ply(splats: Splats, path: str | os.PathLike, colours: np.ndarray | None = None) -> None:
    """Write the splats with (S, 3) ``colours`` (default ``splats.colours()``) as a 3D
    Gaussian splatting PLY (binary, little endian): x, y, z, nx, ny, nz, f_dc_0..2 (degree-0
    spherical harmonics), opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z), the
    layout splat viewers read."""
    colours = (splats.colours() if colours is None else colours).astype(np.float64)
    opacity = splats.opacities.astype(np.float64)
    fields = {
        "x": splats.centres[:, 0], "y": splats.centres[:, 1], "z": splats.centres[:, 2],
        "nx": 0.0, "ny": 0.0, "nz": 0.0,
        **{f"f_dc_{i}": (colours[:, i] - 0.5) / SH_C0 for i in range(3)},
        "opacity": np.log(opacity / (1 - opacity)),
        **{f"scale_{i}": np.log(splats.scales[:, i]) for i in range(3)},
        **{f"rot_{i}": splats.rotations[:, i] for i in range(4)},
    }
    table = np.zeros(len(splats), [(name, "<f4") for name in fields])
    for name, value in fields.items():
        table[name] = value
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(splats)}\n"
              + "".join(f"property float {name}\n" for name in fields) + "end_header\n")
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(table.tobytes())

