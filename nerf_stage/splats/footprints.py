"""The training views of a splat run on the device, and the palette stage's footprints: with
the geometry frozen, a view's splats are a sparse matrix of each pixel's contributions, so
that a step draws the view as one product, without projecting or sorting (``Footprint``);
the footprints that fit are held in a window of views that moves on (``Window``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import torch
from tqdm import tqdm

from ..data.cameras import Intrinsics
from ..data.dataset import Dataset
from ..train.run import free_memory
from .rasterise import draw
from .run import SplatRun, normalised_pose

#: The share of the memory free on the device as the palette stage starts that its frozen
#: footprints may take (``footprint_budget``). When the views' footprints do not all fit,
#: the stage draws from a window of views whose footprints do, and moves the window on to
#: the next views after ``WINDOW_VISITS`` steps a view in it: a view drawn afresh at every
#: visit costs a footprint's making each time (docs/splats.md).
FOOTPRINT_SHARE = 0.5
FOOTPRINT_BYTES = 256 << 20  # the budget's floor, where little memory is free
WINDOW_VISITS = 8
PAIRS_AT_ONCE = 1 << 20  # a view's pairs sorted (``_csr``) or multiplied (the start) at once


@dataclass
class TrainingView:
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


def patch(view: TrainingView, size: int, generator: torch.Generator) -> TrainingView:
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


def training_views(run: SplatRun, dataset: Dataset, train_ids, weights, device) -> list:
    def tensor(a):
        return torch.as_tensor(a, dtype=torch.float32, device=device)

    return [TrainingView(normalised_pose(dataset.poses[i], run.box, device), dataset.camera(i),
                  tensor(dataset.images[i]), tensor(weights[n]), tensor(dataset.alpha[i]), n,
                  (0, 0, dataset.camera(i).width, dataset.camera(i).height))
            for n, i in enumerate(train_ids)]


@dataclass
class Footprint:
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
def view_pairs(run: SplatRun, view: TrainingView) -> tuple[torch.Tensor, ...]:
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


def footprint(run: SplatRun, view: TrainingView) -> Footprint:
    """The footprint of ``view`` (its window) under the run's current geometry."""
    pixel, splat, contribution, acc = view_pairs(run, view)
    pixels, splats = len(acc), len(run.model.means)
    # by splat, then pixel (the pairs come by pixel); then by pixel, then splat from it
    transposed = _csr(splat, pixel, contribution, (splats, pixels))
    del pixel, splat, contribution
    splat = torch.repeat_interleave(
        torch.arange(splats, dtype=torch.int32, device=acc.device),
        torch.diff(transposed.crow_indices()).long())
    return Footprint(_csr(transposed.col_indices(), splat, transposed.values(),
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


def footprint_budget(device: torch.device) -> int:
    """Bytes of footprints the palette stage may hold on ``device``: ``FOOTPRINT_SHARE`` of
    its free memory, at least ``FOOTPRINT_BYTES``."""
    return int(max(FOOTPRINT_BYTES, min(FOOTPRINT_SHARE * free_memory(device), 1 << 60)))


def make_footprints(run: SplatRun, views: list, budget: int, start: int = 0) -> list:
    """The footprints of ``views`` in their order from ``start`` on (around to the first),
    while they fit in ``budget`` bytes (the next one taken to be as large as the largest so
    far); None for the views past them."""
    made, used, largest = [None] * len(views), 0, 0
    for n in tqdm(range(len(views)), desc="footprints", unit="view", leave=False):
        if used >= budget or used + largest > budget:
            break
        index = (start + n) % len(views)
        made[index] = footprint(run, views[index])
        used += made[index].nbytes
        largest = max(largest, made[index].nbytes)
    return made


@dataclass
class Window:
    """The palette stage's footprints (``make_footprints``; None for the views past the
    window) within ``budget`` bytes, the view the window starts at and the steps drawn from
    it so far: the state a resumed run continues from (``state``)."""

    footprints: list
    budget: int = 0
    start: int = 0
    visits: int = 0

    @classmethod
    def made(cls, run: SplatRun, views: list, start: int = 0, visits: int = 0) -> Window:
        """The window from view ``start`` on, within the budget the device has now."""
        budget = footprint_budget(run.device)
        return cls(make_footprints(run, views, budget, start), budget, start, visits)

    def pick(self, run: SplatRun, views: list,
             generator: torch.Generator) -> tuple[int, Footprint | None]:
        """A random view among those whose footprints are held (every view when none is),
        and its footprint; after ``WINDOW_VISITS`` steps a view, the window moves on to the
        next views first (its footprints freed before the next are made)."""
        held = self._held()
        if held and len(held) < len(views) and self.visits >= WINDOW_VISITS * len(held):
            self.start, self.footprints = (self.start + len(held)) % len(views), []
            self.footprints = make_footprints(run, views, self.budget, self.start)
            self.visits = 0
            held = self._held()
        window = held or range(len(views))
        index = window[int(torch.randint(len(window), (1,), generator=generator))]
        footprint = self.footprints[index] if self.footprints else None
        self.visits += footprint is not None
        return index, footprint

    def _held(self) -> list[int]:
        return [i for i, footprint in enumerate(self.footprints) if footprint]

    def state(self) -> dict:
        return {"start": self.start, "visits": self.visits}
