"""Training configuration: dataclasses saved as ``config.json`` beside the checkpoint.

``TrainConfig`` holds the settings every backbone shares and one nested dataclass per
backbone, made from ``backbone_settings.SETTINGS`` (``grid``: ``GridConfig``, ...);
``nerf-stage train`` makes one flag per field (``palette_core.cli.add_config_arguments``):
``--pretrain-iters``, ``--grid-voxels``, ``--mlp-samples``, ... No torch here, so that the
CLI can be built without the ``nerf`` extra.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, fields
from enum import StrEnum
from pathlib import Path

from palette_core.errors import InputError

from ..backbone_settings import SETTINGS, Backbone
from ..checks import MAX_ITERS, MAX_VOXELS, at_least_zero, integers, is_number, member, positive

#: Environment variable naming a JSON file of training defaults (``TrainConfig.defaults``).
CONFIG_ENV = "NERF_STAGE_CONFIG"
#: How many times finer than the field's grid baked renders read the colour part by default
#: (``render --baked``; docs/nerf.md).
BAKE_FACTOR = 4


class Strategy(StrEnum):
    """How a weight NeRF is trained (PaletteNeRF, Sec. 3.3)."""

    TWO_STAGE = "two-stage"
    TRADITIONAL = "traditional"
    RGB = "rgb"


class Space(StrEnum):
    """Where the scene ends (``scene_box.scene_box``)."""

    AUTO = "auto"
    BOX = "box"
    UNBOUNDED = "unbounded"
    NDC = "ndc"


def _backbone_sections(cls: type) -> type:
    """``cls`` as a dataclass with, after its own fields, one per backbone of ``SETTINGS``:
    its settings, named as the backbone (``TrainConfig.grid.voxels``), so that a backbone's
    settings live in one place alone."""
    for name, settings in SETTINGS.items():
        cls.__annotations__[name] = settings
        setattr(cls, name, field(default_factory=settings))
    return dataclass(cls)


@_backbone_sections
class TrainConfig:
    """How to train one weight NeRF (defaults suit the ``grid`` backbone on a CPU), with a
    section of settings per backbone (``backbone_settings.SETTINGS``)."""

    backbone: Backbone = Backbone.AUTO
    """``grid`` (dense voxel grids, fast on CPUs), ``hash`` (a multi-resolution hash encoding:
    detail at a photo's resolution), ``mlp`` (the paper's vanilla NeRF), ``splats`` (3D
    Gaussians, the model the studio and the PLY show as trained) or ``auto``: the splats for
    views finer than the grid resolves, the grid otherwise (``trainer.choose_backbone``,
    docs/decisions/0023-auto-backbone.md); a run's config.json names the one chosen."""
    strategy: Strategy = Strategy.TWO_STAGE
    """``two-stage`` (RGB pretrain, then weights), ``traditional`` (weights from scratch),
    or ``rgb`` (an RGB NeRF only, the baseline)."""
    pretrain_iters: int = 4200
    """P: RGB iterations of ``two-stage`` (``traditional`` and ``rgb`` train P + F on one
    target)."""
    finetune_iters: int = 3000
    """F: weight iterations of ``two-stage`` with the density part frozen."""
    lr_decay: float = 0.3
    """Each stage's learning rates decay exponentially to this fraction of the backbone's by
    the stage's end (``two-stage``: pretraining, then fine-tuning; 1: constant rates). The
    ``splats`` backbone's RGB stage keeps 3D Gaussian splatting's schedule instead."""
    batch_rays: int = 4096
    """Rays per iteration."""
    supersampling: int = 1
    """n: a pixel is the mean of n x n rays through the centres of its sub-pixels, in training
    (``batch_rays`` rays, so n^2 times fewer pixels a batch) and in renders (n^2 times the
    cost). A camera's pixels, and the simulator's, average over their area; one ray a pixel
    can only point-sample edges (docs/decisions/0014-pixels-are-areas.md)."""
    head_width: int = 128
    """Width of the last hidden layer (the paper's 128/256/512 ablation)."""
    occupancy_voxels: int = 64**3
    """Cells of the occupancy grid that lets empty space be skipped (the visual hull of the
    training views, refined from the density by backbones that ask for it)."""
    opacity_weight: float = 0.1
    """Weight of the L2 loss between the accumulated opacity and the images' alpha, while the
    density trains: it clears fog from space that few rays constrain."""
    sparsity_weight: float = 3e-4
    """Weight of the Cauchy sparsity prior on each sample's optical thickness, while the
    density trains: it clears thin fog (fewer samples a ray, faster training and rendering)."""
    distortion_weight: float = 2e-3
    """Weight of mip-NeRF 360's distortion loss while the density trains, in unbounded scenes
    only (``space``): it gathers each ray's weight where the ray ends, against the floaters
    that views from one ring leave (docs/decisions/0007-unbounded-space.md); box scenes do without
    it."""
    depth_weight: float = 0.1
    """Weight of the depth loss (NeRF backbones) on the training pixels where the capture's
    sparse points are seen (``point_depth``, ``losses.depth_loss``), while the density
    trains, against floaters and walls at the wrong depth
    (docs/decisions/0009-floaters-near-gradient-depth.md); captures without points train
    without it; 0: off."""
    near_gradient: float = 2.0
    """In unbounded scenes, gradients of samples nearer to the camera than this (in the
    rays' marching parameter: box half sizes, contracted beyond the box's reach) are scaled
    down by the square of their distance over it (``march.scale_near_gradients``), against
    floaters in front of the cameras (docs/decisions/0009-floaters-near-gradient-depth.md);
    0: off. Box scenes start their
    samples at the box, away from the cameras, and do without it."""
    rgb_weight: float = 1.0
    """Weight of the L2 loss of the colours through the weights (``weights @ basis``) against
    the images, added to the weights' own loss while the output is weights (0: the weights'
    loss alone)."""
    appearance: bool = True
    """Learn a colour transform per training image, applied after compositing, so that
    exposure and white balance that change from photo to photo leak neither into the
    geometry nor into the palette weights (the palette stage fits the weights of each
    pixel's colour with its image's transform undone); renders show the
    images' average appearance (``appearance.Appearance``). Scenes without such changes
    (simulated, rendered) learn transforms near the identity
    (docs/decisions/0008-per-image-appearance.md)."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Colour behind the scene, RGB in [0, 1]."""
    space: Space = Space.AUTO
    """``box``: the scene ends in a box around what the cameras see; ``unbounded``: what lies
    beyond it is contracted into a shell (mip-NeRF 360); ``ndc``: a forward-facing
    capture's frustum in NeRF's normalised device coordinates, for the field backbones
    (``ndc``; it needs depth bounds or points); ``auto``: ``unbounded`` when every
    training pixel is opaque, else ``box`` unless a short probe fits far better unbounded
    (``scene_box.scene_box``, ``trainer.choose_scene_box``)."""
    seed: int = 0
    """Seed of the weight initialisation, ray batches and sample jitter."""
    checkpoint_every: int = 500
    """Iterations between checkpoints."""
    minutes: float = 0.0
    """Wall-clock limit of training (0: none). Each stage stops at its share of it (two-stage
    pretraining: ``pretrain_minutes``, by default P / (P + F) of it) or after its iterations,
    whichever comes first, and its learning rates decay with its iterations or its time,
    whichever is further (``trainer.stage_progress``). For comparing NeRFs at one budget."""
    pretrain_minutes: float = 0.0
    """Wall-clock limit of two-stage pretraining (0: P / (P + F) of ``minutes``), at most
    ``minutes``: with it, fine-tuning planned longer than the time left is ended by the
    clock whatever P / (P + F) is (docs/decisions/0006-minutes.md)."""
    fill_minutes: bool = True
    """Under ``minutes``, plan the iterations to fill the budget (``budget.planned``: a short
    probe's rate, with room to spare), so that the clock ends every stage and the iterations
    set only the stages' shares; false: a stage that reaches its iterations first ends."""
    def __post_init__(self):
        self.backbone = member(Backbone, self.backbone, "backbone")
        self.strategy = member(Strategy, self.strategy, "strategy")
        self.space = member(Space, self.space, "space")
        if self.backbone == Backbone.SPLATS and self.strategy == Strategy.TRADITIONAL:
            raise InputError("the splats backbone trains two-stage or rgb, not traditional "
                             "(the geometry needs colours to grow from)", "strategy")
        if self.backbone == Backbone.SPLATS and self.space == Space.NDC:
            raise InputError("the splats live in world space: --space ndc is for the field "
                             "backbones", "space")
        at_least_zero(self, "opacity_weight", "sparsity_weight", "rgb_weight",
                      "distortion_weight", "depth_weight", "near_gradient", "minutes",
                      "pretrain_minutes")
        positive(self, "lr_decay")
        for name in ("appearance", "fill_minutes"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name} must be true or false, got {getattr(self, name)!r}")
        integers(self, 0, MAX_ITERS, "pretrain_iters", "finetune_iters")
        integers(self, 1, 1 << 20, "batch_rays")
        integers(self, 1, 8, "supersampling")
        integers(self, 1, 4096, "head_width")
        integers(self, 1, MAX_VOXELS, "occupancy_voxels")
        integers(self, 1, MAX_ITERS, "checkpoint_every")
        integers(self, 0, (1 << 63) - 1, "seed")
        if self.minutes and self.pretrain_minutes > self.minutes:
            raise InputError(f"pretrain_minutes ({self.pretrain_minutes}) must be at most "
                             f"minutes ({self.minutes})")
        if self.pretrain_iters + self.finetune_iters == 0:
            raise InputError("pretrain_iters + finetune_iters must be > 0")
        if self.strategy == Strategy.TWO_STAGE and self.finetune_iters == 0:
            raise InputError("the two-stage strategy needs finetune_iters > 0")
        background = self.background
        if (not isinstance(background, (tuple, list)) or len(background) != 3
                or not all(is_number(c) and 0 <= c <= 1 for c in background)):
            raise InputError(f"background must be three numbers in [0, 1], got {background!r}")
        self.background = tuple(float(c) for c in background)
        for name, settings in SETTINGS.items():
            if not isinstance(getattr(self, name), settings):
                raise InputError(f"{name} must be {settings.__name__} settings")

    @property
    def total_iters(self) -> int:
        return self.pretrain_iters + self.finetune_iters

    @property
    def backbone_config(self):
        """The nested settings of the chosen backbone (``backbone_settings.SETTINGS``)."""
        if self.backbone == Backbone.AUTO:
            raise InputError("backbone auto names no settings until the scene chooses one "
                             "(trainer.choose_backbone)", "backbone")
        return getattr(self, self.backbone)

    def to_dict(self) -> dict:
        """Plain JSON types only (strings for the enums), as saved in config.json, with the
        chosen backbone's settings only (``from_dict`` gives the others their defaults, and
        reads files that hold every backbone's)."""
        data = json.loads(json.dumps(asdict(self)))
        return {key: value for key, value in data.items()
                if key not in _NESTED or key == self.backbone}

    def trains_like(self, other: TrainConfig) -> bool:
        """Whether ``other`` trains the same run (``to_dict``: the other backbones' settings
        do not count): what ``--resume`` asks of a run folder's config."""
        return self.to_dict() == other.to_dict()

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> TrainConfig:
        """The config of ``to_dict``; ``source`` names the file in errors. A field that
        ``data`` lacks takes its default, or, for one added since with another default,
        the value the runs that saved such files trained with (``SAVED_WITHOUT``).

        Raises
        ------
        InputError
            On unknown fields or invalid values.
        """
        if not isinstance(data, dict):
            raise InputError(f"{source}: expected an object of config fields")
        data = {**SAVED_WITHOUT, **data}
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise InputError(f"{source}: unknown config fields {', '.join(unknown)}")
        values = {}
        for name, value in data.items():
            nested = _NESTED.get(name)
            if nested is not None:
                if not isinstance(value, dict) or set(value) - {f.name for f in fields(nested)}:
                    raise InputError(f"{source}: {name} must be an object of "
                                     f"{nested.__name__} fields")
                value = nested(**value)
            values[name] = value
        try:
            return cls(**values)
        except TypeError as exc:
            raise InputError(f"{source}: {exc}") from None

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def defaults(cls) -> TrainConfig:
        """The defaults of ``nerf-stage train``: the dataclass's, or, where the environment
        variable ``CONFIG_ENV`` names a JSON file, that file's fields over them (any subset;
        backbone settings as nested objects, ``{"grid": {"voxels": 32768}}``)."""
        path = os.environ.get(CONFIG_ENV)
        if not path:
            return cls()
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, RecursionError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read {CONFIG_ENV}={path}: {exc}") from None
        if not isinstance(data, dict):
            raise InputError(f"{CONFIG_ENV}={path}: expected an object of config fields")
        base = json.loads(json.dumps(asdict(cls())))
        for group in _NESTED:
            section = data.get(group, {})
            if not isinstance(section, dict):
                raise InputError(f"{CONFIG_ENV}={path}: {group} must be an object of "
                                 f"{_NESTED[group].__name__} fields, got {section!r}")
            data[group] = {**base[group], **section}
        return cls.from_dict({**base, **data}, f"{CONFIG_ENV}={path}")

    @classmethod
    def load(cls, path: Path) -> TrainConfig:
        try:
            data = json.loads(path.read_text())
        except (OSError, RecursionError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read training config {path}: {exc}") from None
        return cls.from_dict(data, str(path))


#: Fields added to ``TrainConfig`` with a default that earlier runs did not train with: the
#: value a run folder's ``config.json`` without them stands for.
SAVED_WITHOUT = {"appearance": False, "depth_weight": 0.0, "fill_minutes": False}

#: The nested backbone settings of ``TrainConfig``, by field name.
_NESTED = dict(SETTINGS)
