"""Weight renders of a trained run: render once, then recolour by palette edits.

A weight render (``render.npz``, format ``palette-render/2``, docs/formats.md)
holds the composited weights of some views, premultiplied by opacity, with the
opacity itself. Recolouring it is a matrix product,
``image = weights @ basis(palette) + (1 - opacity) background``, and never runs
the network again. A render for regions (``regions``) also holds the samples behind
each pixel and the weights inside the regions, so that a region recolours with its own
palette, and moves, without the network.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from PIL import Image

from palette_core.basis import Basis, basis_terms, n_terms, weights_to_rgb
from palette_core.errors import InputError, OutputExists
from palette_core.folders import inside
from palette_core.outputs import atomic_outputs, publish_folder, save_image
from palette_core.palette_file import read_palette_json
from palette_core.stack import NpzReader, WeightStack, check_names
from palette_core.swatch import palette_swatch

from ..data.cameras import Intrinsics, orbit_poses
from ..fields import RGB
from ..render.samples import PixelSamples
from ..train.loading import load_run
from ..train.run import Run, run_source
from .regions import ColourRegion, Region, check_count, region_from_dict

RENDER_FILE = "render.npz"
RENDER_FORMAT = "palette-render/2"
READ_FORMATS = ("palette-render/1", RENDER_FORMAT)  # version 1: no samples, no regions
MAX_ORBIT = 3600  # views of a turntable


@dataclass
class WeightRender:
    """Weight images of some views of a run.

    Attributes
    ----------
    weights : (N, H, W, M) float32
        Premultiplied by ``opacity``.
    opacity : (N, H, W) float32
    names : list of str
    palette : (K, 3) float64
        The run's palette.
    basis : Basis
    order : int
    background : (3,) float64
    source : dict
        Run directory, checkpoint iteration, when its training ended (the log's last
        ``seconds``, so that a run trained again in the same folder is rendered again)
        and views: what the render came from.
    samples : render.samples.PixelSamples or None
        Where each pixel's light comes from, kept to split the weights by regions.
    regions : list of regions.Region or regions.ColourRegion
    inside : (N, H, W, M) float32 or None
        The part of ``weights`` inside the regions (``regions`` module), when there are any.
    """

    weights: np.ndarray
    opacity: np.ndarray
    names: list[str]
    palette: np.ndarray
    basis: Basis
    order: int
    background: np.ndarray
    source: dict
    samples: PixelSamples | None = None
    regions: list[Region | ColourRegion] = field(default_factory=list)
    inside: np.ndarray | None = None

    def recolor(self, palette: np.ndarray | None = None,
                inside: np.ndarray | None = None) -> np.ndarray:
        """(N, H, W, 3) float64 images in [0, 1]: ``palette`` (K, 3; the run's by default)
        everywhere, or, given ``inside`` (K, 3), ``palette`` outside the regions and
        ``inside`` within them. A pixel without weight inside is exactly as without regions.
        """
        palette = self._checked(self.palette if palette is None else palette)
        rgb = weights_to_rgb(self.weights, palette, self.basis, self.order)
        if inside is not None:
            if self.inside is None:
                raise InputError("this render has no regions to recolour inside")
            change = (basis_terms(self._checked(inside), self.basis, self.order)
                      - basis_terms(palette, self.basis, self.order))
            rgb += self.inside @ change
        rgb += (1 - self.opacity[..., None]) * self.background
        return np.clip(rgb, 0, 1)

    def _checked(self, palette) -> np.ndarray:
        palette = np.asarray(palette, np.float64)
        if palette.shape != self.palette.shape:
            raise InputError(f"palette must have shape {self.palette.shape} like the run's, "
                             f"got {palette.shape}")
        return palette

    def with_regions(self, regions: list[Region | ColourRegion]) -> WeightRender:
        """This render with its weights split by ``regions`` (no network: its samples, and
        its weights for colour regions); a pixel in any region is in.

        Raises
        ------
        InputError
            If a box or ellipsoid is given and the render kept no samples (rendered without
            regions, or format version 1), or a colour region names a colour the run lacks.
        """
        check_count(list(regions), "this edit")
        places = [r for r in regions if isinstance(r, Region)]
        if places and self.samples is None:
            raise InputError("this render kept no samples to split by regions: render it "
                             "again with a region")
        share = (self.samples.shares(places, self.opacity.shape) if places
                 else np.zeros(self.opacity.shape, np.float32))
        for region in regions:
            if isinstance(region, ColourRegion):
                region.selection().check(len(self.palette))
                share = np.maximum(share, region.values(self.weights, self.opacity, self.basis))
        return replace(self, regions=list(regions), inside=self.weights * share[..., None])

    def as_stack(self) -> WeightStack:
        """The weights as a format-v1 stack (for palette shares and harmonisation)."""
        return WeightStack(self.palette, list(self.weights), self.names, "nerf", self.basis,
                           self.order)


def render_poses(run: Run, dataset, split: str | None, orbit: int | None):
    """Names, (N, 4, 4) poses and cameras (None: the run's) of a split of the run's dataset,
    or of an orbit of N views."""
    train = dataset.indices("train")
    if orbit is not None:
        if not 1 <= orbit <= MAX_ORBIT:
            raise InputError(f"must be in [1, {MAX_ORBIT}], got {orbit}", "orbit")
        return ([f"orbit_{i:03d}" for i in range(orbit)],
                orbit_poses(dataset.poses[train], orbit, run.box.centre), None)
    ids = dataset.indices(split)
    if len(ids) == 0:
        raise InputError(f"dataset {dataset.root} has no {split} views")
    return [Path(dataset.names[i]).stem for i in ids], dataset.poses[ids], dataset.cameras(ids)


def render_weights(run: Run, names: list[str], poses: np.ndarray, source: dict,
                   progress: bool = True,
                   intrinsics: Intrinsics | list[Intrinsics] | None = None,
                   samples: bool = False) -> WeightRender:
    """Render the run's weights for ``poses`` (runs the network), with the training
    camera unless ``intrinsics`` gives one or one a view (``Run.render``); ``samples``
    keeps the samples behind each pixel (for ``WeightRender.with_regions``)."""
    if run.kind == RGB:
        raise InputError("this run was trained on RGB only (strategy 'rgb'): it has no weights")
    weights, opacity, *kept = run.render(poses, progress, intrinsics, samples)
    return WeightRender(weights, opacity, names, run.palette, run.basis, run.order,
                        np.asarray(run.config.background, np.float64), source,
                        kept[0] if kept else None)


def write_render(render: WeightRender, path: str | os.PathLike) -> None:
    """Write a weight render as NPZ format ``palette-render/2``."""
    extra = {}
    if render.samples is not None:
        extra.update(sample_pixel=render.samples.pixel, sample_point=render.samples.point,
                     sample_weight=render.samples.weight)
    if render.inside is not None:
        extra.update(inside=render.inside,
                     regions=np.array(json.dumps([r.to_dict() for r in render.regions])))
    np.savez(path, format=np.array(RENDER_FORMAT), weights=render.weights,
             opacity=render.opacity, names=np.array(render.names, dtype=str),
             palette=render.palette, basis=np.array(str(render.basis)),
             order=np.array(render.order), background=render.background,
             source=np.array(json.dumps(render.source)), **extra)


def read_render(path: str | os.PathLike) -> WeightRender:
    """Read and validate a weight render (format version 1 or 2).

    Raises
    ------
    InputError
        If the file is not such an NPZ or a key is missing or malformed.
    """
    with NpzReader(Path(path), f"a weight render ({RENDER_FORMAT})") as npz:
        version = npz.text("format")
        if version not in READ_FORMATS:
            raise InputError(f"{path} is not a weight render (format {RENDER_FORMAT})")
        weights, opacity = npz.array("weights", "f"), npz.array("opacity", "f")
        palette, background = npz.array("palette", "f"), npz.array("background", "f")
        names = npz.array("names", "U").tolist()
        basis, order = Basis.parse(npz.text("basis")), int(npz.array("order", "iu"))
        source = npz.json("source")
        samples = ((npz.array("sample_pixel", "iu"), npz.array("sample_point", "f"),
                    npz.array("sample_weight", "f")) if "sample_pixel" in npz else None)
        inside = npz.array("inside", "f") if "inside" in npz else None
        regions = ([region_from_dict(r, str(path))
                    for r in check_count(npz.json("regions"), str(path))]
                   if inside is not None else [])
    check_names(names, str(path))
    n = len(names)
    m = n_terms(len(palette), basis, order)
    if (weights.shape[:1] != (n,) or weights.ndim != 4 or weights.shape[-1] != m
            or opacity.shape != weights.shape[:3] or palette.ndim != 2
            or palette.shape[1:] != (3,) or background.shape != (3,)
            or not isinstance(source, dict)
            or (inside is not None and inside.shape != weights.shape)):
        raise InputError(f"{path}: weights, opacity, palette, background or the weights inside "
                         "the regions have the wrong shape")
    if not all(np.isfinite(x).all() for x in (weights, opacity, inside) if x is not None):
        raise InputError(f"{path}: weights or opacity hold NaN or infinity")
    if samples is not None:
        samples = PixelSamples(*_checked_samples(*samples, opacity.size, path))
    return WeightRender(weights, opacity, names, palette.astype(np.float64), basis, order,
                        background.astype(np.float64), source, samples, regions, inside)




def _checked_samples(pixel: np.ndarray, point: np.ndarray, weight: np.ndarray, pixels: int,
                     path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples' (P,) int64 pixels, (P, 3) float32 points and (P,) float32 weights,
    InputError unless they fit views of ``pixels`` pixels in all (checked before anything is
    sized by a pixel index)."""
    p = len(pixel) if pixel.ndim == 1 else -1
    if (p < 0 or point.shape != (p, 3) or weight.shape != (p,)
            or (p and not 0 <= pixel.min() <= pixel.max() < pixels)
            or not (np.isfinite(point).all() and np.isfinite(weight).all())):
        raise InputError(f"{path}: the samples behind its pixels are malformed")
    return pixel.astype(np.int64), point.astype(np.float32), weight.astype(np.float32)


def write_gif(path: Path, frames: np.ndarray, seconds_per_frame: float = 0.08) -> None:
    """Write (N, H, W, 3) float frames in [0, 1] as a looping GIF."""
    images = [Image.fromarray(np.round(f * 255).astype(np.uint8)) for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=int(seconds_per_frame * 1000), loop=0)


@dataclass
class EditedRenders:
    """What ``render_edits`` wrote: one folder (and GIF, for orbits) per label."""

    labels: list[str]
    views: int
    reused: bool
    """The saved weight render was recoloured without running the network."""


def render_edits(rundir: str | os.PathLike, out: str | os.PathLike,
                 palette_files: list[str] = (), templates: list[str] = (),
                 split: str = "test", orbit: int | None = None,
                 force: bool = False, progress: bool = True,
                 baked: int | None = None,
                 regions: list[Region | ColourRegion] = ()) -> EditedRenders:
    """Render a run's weights once into ``out/render.npz`` and recolour them.

    One folder per palette file (``out/<file stem>``), per harmonisation template
    (``out/harmonized-<template>``, fitted to the rendered weights), or the run's
    own palette (``out/original``) when neither is given; an orbit also gives
    ``out/<label>.gif``. A render of the same run and views in ``out`` is reused.
    ``baked`` renders through the field baked at that factor (``Run.baked``: no network,
    faster). With ``regions``, each palette applies inside them only and the run's own
    outside (``WeightRender.with_regions``); the render keeps its samples, so that other
    regions reuse it too.

    Raises
    ------
    InputError
        Before any rendering: an unknown template, a palette of the wrong size, an
        output that exists (without ``force``), or a saved render of other views.
    """
    from harmonize import TEMPLATES, harmonize_palette, palette_shares
    from harmonize.batch import BEST


    run = load_run(rundir)
    unknown = [t for t in templates if t != BEST and t not in TEMPLATES]
    if unknown:
        raise InputError(f"unknown template {unknown[0]!r}; choose one of "
                         f"{BEST}, {', '.join(TEMPLATES)}")
    if regions and not (palette_files or templates):
        raise InputError("a region needs a palette to apply inside it",
                         fixes=[("palette", "to give one"), ("harmonize", "to fit one")])
    for region in regions:
        if isinstance(region, ColourRegion):
            region.selection().check(len(run.palette))
    palettes = {} if palette_files or templates else {"original": run.palette}
    for path in palette_files:
        label = Path(path).stem
        if label in palettes:
            raise InputError(f"two palette files are named {label}.json: their outputs collide")
        palettes[label] = read_palette_json(path, k=len(run.palette))
    views = f"orbit:{orbit}" if orbit is not None else split
    source = {**run_source(run, rundir), "views": views, "baked": baked}
    out = Path(out)
    cache = out / RENDER_FILE
    render = read_render(cache) if cache.is_file() else None
    if render is not None and render.source != source and not force:
        raise OutputExists(f"{cache} holds another render ({render.source.get('views')} "
                           f"of {render.source.get('run')})", "to replace it")
    labels = list(palettes) + [f"harmonized-{t}" for t in templates]
    outputs = [out / label for label in labels] + [out / f"{label}.gif" for label in labels
                                                   if orbit is not None]
    existing = [str(path) for path in outputs if path.exists()]
    if existing and not force:
        raise OutputExists(f"output {existing[0]} already exists")
    places = any(isinstance(region, Region) for region in regions)
    reused = (render is not None and render.source == source
              and (render.samples is not None or not places))
    if not reused:
        dataset = run.dataset()
        names, poses, cameras = render_poses(run, dataset, split, orbit)
        renderer = run if baked is None else run.baked(baked)
        render = render_weights(renderer, names, poses, source, progress, cameras,
                                samples=places)
    if regions:
        render = render.with_regions(regions)
    if not reused or regions:
        with atomic_outputs(True) as stage:  # checked above: ours, of the same views
            write_render(render, stage(cache))
    if templates:
        shares = palette_shares(render.as_stack())
        for template in templates:
            palettes[f"harmonized-{template}"] = harmonize_palette(
                render.palette, shares, template).palette
    for label, palette in palettes.items():
        _write_recoloured(render, palette, out / label, orbit is not None, force)
    return EditedRenders(labels, len(render.names), reused)


def _write_recoloured(render: WeightRender, palette: np.ndarray, folder: Path, gif: bool,
                      force: bool) -> None:
    """Views recoloured with ``palette`` into ``folder`` (published whole), plus a GIF;
    inside the render's regions only, when it has some."""
    images = (render.recolor(palette) if render.inside is None
              else render.recolor(render.palette, inside=palette))
    with atomic_outputs(force) as stage, publish_folder(folder, force) as staging:
        for name, image in zip(render.names, images):
            save_image(inside(staging, f"{name}.png"), image)
        palette_swatch(palette).save(staging / "palette.png")
        if gif:
            write_gif(stage(folder.with_suffix(".gif")), images)


__all__ = ["EditedRenders", "WeightRender", "read_render", "render_edits", "render_poses",
           "render_weights", "write_gif", "write_render"]
