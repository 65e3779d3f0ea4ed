"""A ``splats`` run: its model of Gaussians in the normalised box (``SplatModel``), the run
that draws whole views and gives its splats in the world (``SplatRun``), and its
checkpoint, read as data and checked (``load_run``; ``train.checkpoint``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from palette_core.basis import Basis, n_terms
from palette_core.errors import InputError, first_line

from ..backbone_settings import MAX_SPLATS
from ..data.cameras import Intrinsics
from ..fields.base import ACTIVATIONS, INVERSE_ACTIVATIONS, RGB
from ..render.samples import KEEP_WEIGHT, PixelSamples
from ..render.scene_box import SceneBox
from ..train.appearance import Appearance
from ..train.checkpoint import write_checkpoint
from ..train.run import RunBase, run_fields
from .model import Splats, covariances, with_residual
from .rasterise import draw
from .sh import SH_C0, sh_basis, sh_terms, sh_values

GEOMETRY = ("means", "scales", "quats", "opacities")


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
            return torch.clamp(SH_C0 * self.colours + 0.5 + sh_values(basis, self.colours_rest),
                               min=0)
        weights = ACTIVATIONS[self.kind](self.weights)
        if degree == 0:
            return weights
        residual = sh_values(basis, self.residual)
        if self.kind == Basis.ADDITIVE:  # on the simplex: the residual sums to zero
            residual = residual - residual.mean(1, keepdim=True)
        return with_residual(weights, residual, self.kind)

    def gaussians(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, 3, 3) covariances and (S,) opacities."""
        return covariances(self.quats, torch.exp(self.scales)), torch.sigmoid(self.opacities)

    def set_output(self, kind: str, weights: torch.Tensor,
                   residual: torch.Tensor | None = None) -> None:
        """Freeze the geometry and replace the RGB colours by (S, M) palette ``weights``
        (after their activation) and their (S, B - 1, M) ``residual`` (zero by default)."""
        for name in GEOMETRY:
            getattr(self, name).requires_grad_(False)
        del self.colours, self.colours_rest
        self.kind = kind
        self.weights = nn.Parameter(INVERSE_ACTIVATIONS[kind](weights.clamp(min=1e-4)))
        self.residual = nn.Parameter(weights.new_zeros(len(weights), sh_terms(self.degree) - 1,
                                                       weights.shape[1])
                                     if residual is None else residual.contiguous())


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


def save_checkpoint(run: SplatRun, path: Path, optimiser, generator, state: dict) -> None:
    """Write the run (``checkpoint.write_checkpoint``; the splats' tensors as its ``field``)
    with its training's ``state`` (the densification's running totals, the palette stage's
    window), so that a resumed run continues exactly."""
    model = run.model
    output = {"kind": str(model.kind), "channels": 3 if model.kind == RGB
              else model.weights.shape[1], "degree": model.degree}
    extra = {"training": state}
    if run.appearance is not None:
        extra["appearance"] = run.appearance.state_dict()
    write_checkpoint(run, path, model.state_dict(), output, [optimiser.state_dict()],
                     generator, extra)


def load_run(state: dict, path: str, device: torch.device) -> SplatRun:
    """The splat run of a checkpoint's ``state`` (read by ``loading.load_run``), on ``device``."""
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
