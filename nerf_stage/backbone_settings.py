"""Each backbone's settings, without torch: a config dataclass a backbone, the section of
``TrainConfig`` of the same name (``SETTINGS``), from which ``nerf-stage train`` makes its
flags. The models themselves are found through ``backbones.BACKBONES``; the settings live
apart from that table so that a backbone's module can import its settings without
importing the table that names it (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from palette_core.errors import InputError

from .checks import MAX_ITERS, MAX_VOXELS, integers, positive

MAX_SPLATS = 10_000_000  # splats a ``splats`` run may hold at most


def _check_head_and_occupancy(settings) -> None:
    """InputError unless the head's and the occupancy schedule's settings that the grid and
    hash backbones share are valid."""
    if not isinstance(settings.deferred, bool):
        raise InputError(f"deferred must be true or false, got {settings.deferred!r}")
    integers(settings, 1, 16, "head_layers")
    integers(settings, 1, MAX_ITERS, "occupancy_every")
    integers(settings, 0, MAX_ITERS, "warmup_iters")
    if settings.view_frequencies is not None:
        integers(settings, 0, 16, "view_frequencies")


@dataclass
class GridConfig:
    """Settings of the ``grid`` backbone (dense voxel grids and a small MLP head)."""

    voxels: int = 96**3
    """Voxels of the density and feature grids, spread over the scene box."""
    features: int = 12
    """Feature channels per voxel of the colour grid."""
    view_frequencies: int | None = 4
    """Frequencies of the view direction's encoding in the head; None (``none`` on the command
    line): diffuse."""
    deferred: bool = True
    """Shade each ray once, from its features composited along it, rather than each sample
    (deferred shading; docs/decisions/0003-deferred-two-layer-head.md): faster, and a
    view-dependent head then tells a thin wall's two sides apart. False: the paper's
    per-sample colours, which ``render --baked`` needs."""
    head_layers: int = 2
    """Hidden layers of the head, each ``head_width`` wide
    (docs/decisions/0003-deferred-two-layer-head.md)."""
    lr: float = 0.1
    """Adam learning rate of the voxel grids."""
    network_lr: float = 1e-3
    """Adam learning rate of the head."""
    step_voxels: float = 1.0
    """Ray-marching step of training, in voxels."""
    render_step_voxels: float = 0.5
    """Ray-marching step of renders, in voxels: finer than training's, so that surfaces that
    training made thinner than a step render without bands."""
    occupancy_every: int = 16
    """Iterations between updates of the occupancy grid from the learned density."""
    warmup_iters: int = 64
    """Iterations before occupancy is refined from the learned density."""

    def __post_init__(self):
        _check_head_and_occupancy(self)
        integers(self, 1, MAX_VOXELS, "voxels")
        integers(self, 1, 256, "features")
        positive(self, "lr", "network_lr", "step_voxels", "render_step_voxels")


@dataclass
class HashConfig:
    """Settings of the ``hash`` backbone (a multi-resolution hash encoding and small MLPs;
    nerfacto's field)."""

    levels: int = 16
    """Resolution levels of the encoding."""
    features: int = 2
    """Features a level."""
    log2_entries: int = 19
    """Table rows a level, as a power of two (levels with fewer vertices index them directly)."""
    coarsest: int = 16
    """Cells along the space's longest side at the coarsest level."""
    finest: int = 2048
    """Cells along it at the finest level."""
    density_width: int = 64
    """Hidden width of the density MLP."""
    geometry_features: int = 15
    """Outputs of the density MLP besides the density: the colour part's input."""
    view_frequencies: int | None = 4
    """As the grid backbone's."""
    deferred: bool = True
    """As the grid backbone's."""
    head_layers: int = 2
    """As the grid backbone's."""
    lr: float = 1e-2
    """Adam learning rate of the hash tables."""
    network_lr: float = 1e-2
    """Adam learning rate of the MLPs."""
    samples: int = 128
    """Ray-marching steps of training across the field's space (its longest side)."""
    render_samples: int = 256
    """Ray-marching steps of renders across it."""
    occupancy_every: int = 16
    """Iterations between updates of the occupancy grid from the learned density."""
    warmup_iters: int = 64
    """Iterations before occupancy is refined from the learned density."""

    def __post_init__(self):
        _check_head_and_occupancy(self)
        integers(self, 1, 32, "levels")
        integers(self, 1, 8, "features")
        integers(self, 4, 24, "log2_entries")
        integers(self, 1, 1 << 16, "coarsest", "finest", "density_width", "samples",
                 "render_samples")
        integers(self, 0, 256, "geometry_features")
        if self.levels * self.features << self.log2_entries > MAX_VOXELS * 16:
            raise InputError("levels x features x 2^log2_entries must be at most "
                             f"{MAX_VOXELS * 16} table entries")
        if self.finest < self.coarsest:
            raise InputError(f"finest must be at least coarsest, got {self.finest} < "
                             f"{self.coarsest}")
        positive(self, "lr", "network_lr")


@dataclass
class MLPConfig:
    """Settings of the ``mlp`` backbone (the paper's vanilla NeRF)."""

    samples: int = 96
    """Samples per ray, evenly across the scene box."""
    network_lr: float = 5e-4
    """Adam learning rate."""

    def __post_init__(self):
        integers(self, 1, 4096, "samples")
        positive(self, "network_lr")


@dataclass
class SplatConfig:
    """Settings of the ``splats`` backbone (3D Gaussians trained from the images, one image
    an iteration; 3D Gaussian splatting's recipe, ``splats.backbone``)."""

    initial: int = 20_000
    """Splats at the start: at the capture's sparse points where it has them (at most this
    many of them, in their colours), else on the rays of random training pixels, in their
    colours (at most one for four pixels of a training image; beyond an unbounded box as
    well: far splats for what lies beyond; in the visual hull of a bounded scene with
    transparent pixels)."""
    max_splats: int = 300_000
    """Densification never grows the splats beyond this, nor beyond one for ten training
    pixels (``strategy.PIXELS_PER_SPLAT``)."""
    sh_degree: int = 3
    """Degree of the spherical harmonics of the view-dependent colour (RGB stage) and of the
    weights' view-dependent residual (palette stage); 0: diffuse."""
    sh_every: int = 1000
    """Iterations between raising the degree in use by one, from 0 (3D Gaussian
    splatting's schedule)."""
    ssim_weight: float = 0.2
    """Weight of 1 - SSIM beside L1 in the RGB stage's loss."""
    triangulate: bool = True
    """A capture without sparse points gets them triangulated from its training views at
    their poses when a run starts (COLMAP's point triangulator, the ``poses`` extra), so
    that the splats start at them; false, or when none triangulate: the splats start where
    the views look."""
    reach: int = 64
    """Pixels from its centre that training draws a splat to at most (a bound on a view's
    pairs; densification splits the splats it cuts off); renders draw each splat whole."""
    patch: int = 0
    """Side in pixels of the random square of a training image that an iteration draws and
    compares (0: the whole image): an iteration's cost follows its pixels."""
    refine_start: int = 100
    """Iteration of the first densification (3D Gaussian splatting's 500 is for a stage of
    30,000: a stage that the clock ends after a few hundred would barely densify)."""
    refine_stop: float = 0.5
    """Densification stops at this share of the RGB stage: of its iterations or, when the
    clock ends it (``--minutes``), of its time if more (``trainer.stage_progress``)."""
    refine_every: int = 100
    """Iterations between densifications."""
    reset_every: int = 3000
    """Iterations between resets of every splat's opacity to twice ``prune_opacity``."""
    schedule_iters: int = 0
    """The RGB stage's length that ``refine_start``, ``refine_every`` and ``reset_every`` are
    given for: a shorter stage scales them down in proportion (gsplat's ``steps_scaler``;
    3D Gaussian splatting's are for 30,000); 0 takes them as given."""
    grow_grad2d: float = 2e-5
    """Mean screen-space gradient (normalised image units) above which a splat is cloned
    (small) or split (large). 3D Gaussian splatting's 2e-4 densifies a hundred and more
    times in its 30,000 iterations; a stage of a thousand densifies a few times and has to
    grow more each time (docs/decisions/0012-splat-densification.md)."""
    grow_scale: float = 0.01
    """Largest standard deviation, as a share of the cameras' extent, of a splat cloned
    rather than split."""
    prune_opacity: float = 0.005
    """Splats less opaque than this are removed."""
    prune_scale: float = 0.1
    """Splats larger than this share of the cameras' extent are removed (after the first
    opacity reset)."""
    means_lr: float = 1.6e-4
    """Adam learning rate of the centres, times the cameras' extent; it decays to a
    hundredth by the RGB stage's end."""
    scales_lr: float = 5e-3
    """Adam learning rate of the log standard deviations."""
    quats_lr: float = 1e-3
    """Adam learning rate of the rotations."""
    opacities_lr: float = 5e-2
    """Adam learning rate of the opacity logits."""
    colours_lr: float = 2.5e-3
    """Adam learning rate of the degree-0 colour (RGB stage); degrees above it take a
    twentieth."""
    weights_lr: float = 3e-3
    """Adam learning rate of the palette weights at the start of the palette stage (it
    decays to ``lr_decay`` of this over the stage); their view-dependent residual takes a
    twentieth (docs/decisions/0021-palette-stage-rate.md)."""

    def __post_init__(self):
        integers(self, 1, MAX_SPLATS, "initial", "max_splats")
        integers(self, 0, 3, "sh_degree")
        integers(self, 1, MAX_ITERS, "sh_every", "refine_every", "reset_every")
        integers(self, 0, MAX_ITERS, "refine_start", "schedule_iters")
        integers(self, 1, 4096, "reach")
        integers(self, 0, 1 << 16, "patch")
        if not isinstance(self.triangulate, bool):
            raise InputError(f"triangulate must be true or false, got {self.triangulate!r}")
        if self.initial > self.max_splats:
            raise InputError(f"initial splats must be at most max_splats, got {self.initial} > "
                             f"{self.max_splats}")
        if not 0 <= self.ssim_weight <= 1 or not 0 <= self.refine_stop <= 1:
            raise InputError("ssim_weight and refine_stop must be in [0, 1], got "
                             f"{self.ssim_weight} and {self.refine_stop}")
        positive(self, "grow_grad2d", "grow_scale", "prune_opacity", "prune_scale", "means_lr",
                 "scales_lr", "quats_lr", "opacities_lr", "colours_lr", "weights_lr")
        if self.prune_opacity >= 0.5:
            raise InputError(f"prune_opacity must be below 0.5, got {self.prune_opacity}")


#: The settings of each backbone, by name (``TrainConfig``'s sections).
SETTINGS = {"grid": GridConfig, "mlp": MLPConfig, "hash": HashConfig, "splats": SplatConfig}

#: The backbones' names, as ``TrainConfig.backbone`` takes them, and ``auto``: the one
#: ``trainer.choose_backbone`` chooses for the scene as training starts.
Backbone = StrEnum("Backbone", {"AUTO": "auto", **{name.upper(): name for name in SETTINGS}})
Backbone.__doc__ = ("Backbone names (``SETTINGS``), each with a settings section of its name, "
                    "and ``auto``.")
