"""The run folder of a weight NeRF: its config, its checkpoint, and the trained run itself.

A run folder holds ``config.json`` (the ``TrainConfig``) and ``checkpoint.pt``, written and
read by ``checkpoint`` (docs/formats.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from palette_core.basis import Basis, basis_terms, check_basis
from palette_core.errors import InputError

from ..data.cameras import Intrinsics
from ..data.dataset import Dataset, check_downscale, load_dataset
from ..fields.base import Field, RaySampling
from ..render.march import render_rays, sample_positions
from ..render.occupancy import OccupancyGrid
from ..render.samples import KEEP_WEIGHT, PixelSamples
from ..render.scene_box import SceneBox, box_from_dict, normalised_rays
from .appearance import Appearance
from .checkpoint import CHECKPOINT, write_checkpoint
from .config import BAKE_FACTOR, TrainConfig

CONFIG = "config.json"
#: Rays per forward pass when rendering whole views, by device type: on the CPU larger
#: chunks run slower; a GPU marches a half-size photo's rays at once.
RENDER_CHUNK = {"cpu": 1 << 15, "cuda": 1 << 19}


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def free_memory(device: torch.device) -> float:
    """Bytes ``device`` can give this process now: a GPU's free memory; on a CPU the
    system's ``MemAvailable`` (free pages where there is no /proc; unbounded where neither
    is known)."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    try:
        with open("/proc/meminfo") as info:
            fields = dict(line.split(":", 1) for line in info)
        return int(fields["MemAvailable"].split()[0]) * 1024
    except (OSError, KeyError, ValueError):
        try:
            return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError):
            return float("inf")


@dataclass
class RunRecord:
    """Where a run came from and how far it got (saved in the checkpoint).

    Attributes
    ----------
    dataset : str
        Absolute path of the dataset folder.
    weights : str
        Path of the weight stack, when known.
    channels : int
        M, the weight channels of the stack.
    stack_meta : dict
        The stack's meta (``simulation.SimulationRecord`` keys for simulated scenes).
    iteration : int
        Iterations trained.
    log : list of dict
        Per iteration: ``iteration``, ``seconds``, ``loss``, ``psnr`` (batch), ``stage``.
    frames_outside : bool
        The dataset's frames may lie outside its folder (``train --frames-outside``); its
        renders and evaluations read them too.
    downscale : int
        The dataset's images were read this many times smaller (``train --downscale``).
    """

    dataset: str
    weights: str = ""
    channels: int = 0
    stack_meta: dict = field(default_factory=dict)
    iteration: int = 0
    log: list[dict] = field(default_factory=list)
    frames_outside: bool = False
    downscale: int = 1


@dataclass
class RunBase:
    """What every trained (or training) run has, whatever its backbone.

    Attributes
    ----------
    config : TrainConfig
    box : SceneBox
    intrinsics : Intrinsics
    palette : (K, 3) float64
    basis : Basis
        The model outputs RGB while ``kind`` is ``fields.RGB``.
    order : int
    record : RunRecord
    """

    config: TrainConfig
    box: SceneBox
    intrinsics: Intrinsics
    palette: np.ndarray
    basis: Basis
    order: int
    record: RunRecord

    @property
    def terms(self) -> np.ndarray:
        """(M, 3) colour of each weight channel for the run's palette."""
        return basis_terms(self.palette, self.basis, self.order)

    def dataset(self) -> Dataset:
        """The run's dataset, read as training read it."""
        record = self.record
        return load_dataset(record.dataset, self.config.background, record.frames_outside,
                            record.downscale)


@dataclass
class Run(RunBase):
    """A weight NeRF whose model is a radiance field (``Field``), and what is needed to use
    it (``RunBase``).

    Attributes
    ----------
    field : Field
    occupancy : OccupancyGrid
    appearance : Appearance or None
        The training images' colour transforms (``TrainConfig.appearance``), while training.
    """

    field: Field | None = None
    occupancy: OccupancyGrid | None = None
    appearance: Appearance | None = None

    @property
    def kind(self) -> str:
        """What the field outputs: ``fields.RGB`` or the weights' basis."""
        return self.field.kind

    @property
    def device(self) -> torch.device:
        return self.occupancy.extent.device

    def bounds(self) -> np.ndarray:
        """(2, 3) world corners of what the run found occupied (``OccupancyGrid.bounds``; in
        NDC space, of its cells' corners taken out of NDC, within the box, as in an unbounded
        scene)."""
        bounds = self.occupancy.bounds()
        if self.box.ndc is not None:
            corners = torch.as_tensor(np.stack(np.meshgrid(*bounds.T, indexing="ij"), -1))
            outside = self.box.ndc.to_box(corners.reshape(-1, 3)).numpy()
            bounds = np.clip(np.stack([outside.min(0), outside.max(0)]), -1, 1)
        return self.box.centre + self.box.scale * bounds

    @property
    def sampling(self) -> RaySampling:
        """How training samples rays."""
        return replace(self.field.sampling(), sky=self.box.sky)

    @property
    def render_sampling(self) -> RaySampling:
        """How renders sample rays (``GridConfig.render_step_voxels``)."""
        return replace(self.field.sampling(render=True), sky=self.box.sky)

    def baked(self, factor: int = BAKE_FACTOR) -> Run:
        """This run with its field baked for fast rendering (``Field.baked``)."""
        return replace(self, field=self.field.baked(self.occupancy, factor))

    def render_pixels(self, origins, directions, generator=None):
        """Pixels of n^2 rays each, sampled as in training (``render_rays``).

        Parameters
        ----------
        origins, directions : (B, n^2, 3)
            Normalised origins and unit directions of each pixel's rays (``normalised_rays``).

        Returns
        -------
        values : (B, C) the rays' values (premultiplied) averaged over each pixel.
        opacity : (B,) averaged likewise.
        samples : the rays' ``rendering.Samples``.
        """
        rays = directions.shape[1]
        near = self.config.near_gradient if self.box.unbounded else 0.0
        values, samples = render_rays(self.field, self.occupancy,
                                      origins.flatten(0, 1), directions.flatten(0, 1),
                                      self.sampling, generator,
                                      near if near and torch.is_grad_enabled() else None)
        return (values.view(-1, rays, values.shape[-1]).mean(1),
                samples.opacity.view(-1, rays).mean(1), samples)

    @torch.no_grad()
    def render(self, poses: np.ndarray, progress: bool = False,
               intrinsics: Intrinsics | list[Intrinsics] | None = None,
               samples: bool = False) -> tuple:
        """Render whole views, with the training camera unless ``intrinsics`` gives one
        camera or one a view (of one size); a pixel is the mean of its
        ``TrainConfig.supersampling``^2 rays.

        Returns
        -------
        values : (N, H, W, C) float32
            The field's outputs (weights, or RGB) premultiplied by opacity.
        acc : (N, H, W) float32
        pixel_samples : render.samples.PixelSamples
            Only with ``samples``: where each pixel's light comes from (to split its
            weights by regions).
        """
        self.field.eval()
        device = self.occupancy.extent.device
        cameras = (intrinsics if isinstance(intrinsics, list)
                   else [intrinsics or self.intrinsics] * len(poses))
        rays = self.config.supersampling ** 2
        chunk_rays = RENDER_CHUNK.get(device.type, RENDER_CHUNK["cpu"])
        values, accs, kept = [], [], []
        for view, (pose, camera) in enumerate(tqdm(zip(poses, cameras), desc="render",
                                                   unit="view", total=len(poses),
                                                   disable=not progress)):
            shape = (camera.height, camera.width, rays)
            origins, directions = normalised_rays(pose, camera, self.box, device,
                                                  self.config.supersampling)
            outputs = []
            for start in range(0, origins.shape[0] * rays, chunk_rays):
                o, d = (x.flatten(0, 1)[start:start + chunk_rays] for x in (origins, directions))
                v, chunk = render_rays(self.field, self.occupancy, o, d, self.render_sampling)
                outputs.append((v, chunk.opacity))
                if samples:
                    first_pixel = view * camera.height * camera.width
                    kept.append(self._pixel_samples(chunk, o, d, start, first_pixel, rays))
            values.append(torch.cat([v for v, _ in outputs]).reshape(*shape, -1).mean(2)
                          .cpu().numpy())
            accs.append(torch.cat([a for _, a in outputs]).reshape(shape).mean(2).cpu().numpy())
        rendered = np.stack(values), np.stack(accs)
        if not samples:
            return rendered
        return (*rendered, PixelSamples(*(np.concatenate(part) for part in zip(*kept))))

    def _pixel_samples(self, chunk, origins, directions, first_ray: int, first_pixel: int,
                       rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel, world position and weight (``PixelSamples``) of the visible samples of a
        chunk of rays (from ray ``first_ray`` of a view whose first pixel is ``first_pixel``,
        ``rays`` rays a pixel) above ``KEEP_WEIGHT``, and each ray's strongest (a foggy ray's
        samples may all lie below it)."""
        visible = chunk.visible()
        weight = visible.weight / rays
        strongest = torch.zeros(len(chunk.opacity), device=weight.device).scatter_reduce(
            0, visible.ray, weight, "amax")  # each ray keeps at least its strongest sample
        keep = weight >= torch.clamp(strongest[visible.ray], max=KEEP_WEIGHT)
        points = sample_positions(visible, self.occupancy, origins, directions)[keep]
        world = points.cpu().numpy().astype(np.float64) * self.box.scale + self.box.centre
        pixel = first_pixel + (first_ray + visible.ray[keep]).cpu().numpy() // rays
        return pixel, world.astype(np.float32), weight[keep].cpu().numpy()


def run_source(run: Run, rundir: str | os.PathLike) -> dict:
    """What a render or a bake records of the run it came from: its folder, checkpoint
    iteration and when its training ended (the log's last ``seconds``, so that a run trained
    again in the same folder is rendered again)."""
    log = run.record.log
    return {"run": str(Path(rundir).resolve()), "iteration": run.record.iteration,
            "trained_seconds": log[-1]["seconds"] if log else 0.0}


def check_rundir(rundir: Path, resume: bool, force: bool) -> None:
    """InputError unless ``rundir`` holds a checkpoint exactly when ``resume`` wants one
    (``force`` starts afresh over one)."""
    exists = (rundir / CHECKPOINT).is_file()
    if resume and not exists:
        raise InputError(f"{rundir} holds no checkpoint", "resume")
    if exists and not (resume or force):
        raise InputError(f"{rundir} already holds a run",
                         fixes=[("resume", "to continue it"), ("force", "to start afresh")])


def save_checkpoint(run: Run, path: Path, optimisers, generator: torch.Generator) -> None:
    """Write the field run, its optimisers and random state to ``path``, atomically."""
    extra = {"occupancy": run.occupancy.state_dict()}
    if run.appearance is not None:
        extra["appearance"] = run.appearance.state_dict()
    write_checkpoint(run, path, run.field.state_dict(), run.field.output_state(),
                     [o.state_dict() for o in optimisers], generator, extra)


def run_record(state: dict) -> RunRecord:
    """The ``RunRecord`` of a checkpoint's state."""
    meta = state["meta"]
    return RunRecord(meta.get("dataset", ""), meta.get("weights", ""), meta.get("channels", 0),
                     meta.get("stack_meta", {}), state["iteration"], state["log"],
                     meta.get("frames_outside", False) is True,
                     check_downscale(meta.get("downscale", 1)))


def restore(run: Run, state: dict) -> None:
    """Load a checkpoint's trained state into ``run``, built with the checkpoint's config: the
    field (its output layer as the checkpoint has it), the occupancy grid, and how far it
    trained. What ``load_run`` and ``trainer.train(resume=True)`` share."""
    output = state["output"]
    if (output["kind"] != run.field.kind
            or output["channels"] != run.field.output.out_features):
        run.field.set_output(output["kind"], output["channels"])
    run.field.load_state_dict(state["field"])
    run.occupancy.load_state_dict(state["occupancy"])
    if run.appearance is not None:
        try:
            run.appearance.load_state_dict(state["appearance"])
        except (KeyError, RuntimeError, TypeError, AttributeError):
            raise InputError("the checkpoint holds no colour transforms of the training "
                             "images as this run needs",
                             fixes=[("force", "to start afresh")]) from None
    saved = run_record(state)
    run.record.iteration, run.record.log = saved.iteration, saved.log


def run_fields(state: dict, path: str) -> dict:
    """``RunBase``'s fields, by name, of a checkpoint's ``state``, checked (a checkpoint
    from elsewhere is read as data only); KeyError, TypeError or ValueError where one is
    missing or malformed."""
    palette = np.array(state["palette"], np.float64)
    if (palette.ndim != 2 or palette.shape[1:] != (3,) or len(palette) == 0
            or not np.all((palette >= 0) & (palette <= 1))):
        raise InputError(f"{path}: palette must have shape (K, 3) with values in [0, 1]")
    basis = Basis.parse(state["basis"])
    check_basis(len(palette), basis, state["order"], path)
    return {"config": TrainConfig.from_dict(state["config"], path),
            "box": box_from_dict(state["box"], path),
            "intrinsics": Intrinsics.from_dict(state["intrinsics"], path), "palette": palette,
            "basis": basis, "order": int(state["order"]), "record": run_record(state)}
