"""Simulate a scene: path trace every view, keep the light-transport weights, write a dataset.

The dataset is a Blender synthetic-scene folder (``transforms_{train,val,test}.json``
and RGBA PNGs, straight alpha = fraction of camera rays that hit the scene), plus,
for scenes with editable materials, ``weights.npz`` (format v1, ``basis`` =
``transport``) and ``materials.json``. Weights are premultiplied by alpha:
``weights @ transport_basis(palette, order)`` is the image's colour times alpha.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from palette_core.basis import Basis, n_terms, transport_basis
from palette_core.errors import InputError
from palette_core.outputs import check_outdir, publish_folder, save_image
from palette_core.palette_file import palette_to_hex
from palette_core.stack import WeightStack, write_stack
from palette_core.version import __version__

from ..data.cameras import (
    SPLIT_PHASES,
    blender_transforms,
    focal_from_fov,
    nerfstudio_transforms,
    off_ring_poses,
    rig_poses,
)
from .geometry import next_term_table, scene_arrays
from .pathtracer import trace_view
from .scene import BUILTIN_SCENES, LIMITS, MAX_TERM_BYTES, SPLITS, Scene
from .scene_file import load_scene

GREY_TOL = 1e-12


@dataclass
class Simulation:
    """Rendered views of one scene, in split order (train, val, test).

    Attributes
    ----------
    names : list of str
        ``<split>/r_<i>.png`` for each view.
    poses : (N, 4, 4) float64
        Camera-to-world matrices (OpenGL axes).
    radiance : (N, H, W, 3) float64
        Mean radiance per pixel, premultiplied by alpha, not clipped.
    alpha : (N, H, W) float64
        Fraction of camera rays that hit the scene.
    weights : (N, H, W, M) float64 or None
        Transport weights when the scene has editable materials.
    palette : (K, 3) float64
        Albedos of the editable materials.
    order : int
        Transport order kept.
    seconds : float
        Path-tracing time.
    """

    names: list[str]
    poses: np.ndarray
    radiance: np.ndarray
    alpha: np.ndarray
    weights: np.ndarray | None
    palette: np.ndarray
    order: int
    seconds: float


@dataclass
class SimulationRecord:
    """How a simulated scene was rendered, kept in its weight stack's meta so that the scene
    can be traced again with an edited palette (``evaluation.resimulated_views``).

    Attributes
    ----------
    scene : str
        A built-in scene's name or the scene file's absolute path.
    order, max_depth, spp, seed : int
    resolution : [width, height]
    views : dict of str to int
        Views per split.
    seconds : float
        Path-tracing time.
    version : str
        Package version that simulated it.
    """

    scene: str
    order: int
    max_depth: int
    spp: int
    seed: int
    resolution: list[int]
    views: dict[str, int]
    seconds: float
    version: str = __version__

    def to_meta(self) -> dict:
        """The stack meta keys (docs/formats.md)."""
        return {"version": self.version, "scene": self.scene, "order": self.order,
                "max_depth": self.max_depth, "spp": self.spp, "seed": self.seed,
                "resolution": list(self.resolution), "views": self.views,
                "seconds": self.seconds}

    @classmethod
    def from_meta(cls, meta: dict) -> SimulationRecord | None:
        """The record in a stack's meta; None for stacks that were not simulated.

        Raises
        ------
        InputError
            If the meta names a scene but its other keys are missing or malformed.
        """
        if "scene" not in meta:
            return None
        try:
            return cls(**{f.name: meta[f.name] for f in fields(cls) if f.name in meta})
        except TypeError as exc:
            raise InputError(f"stack meta of a simulated scene is incomplete: {exc}") from None

    def applied_to(self, scene: Scene) -> Scene:
        """``scene`` with this record's order, sampling, seed and (square) resolution."""
        width, height = self.resolution
        return with_overrides(scene, order=self.order, spp=self.spp, seed=self.seed,
                              max_depth=self.max_depth,
                              resolution=width if width == height else None)


def with_overrides(scene: Scene, order=None, spp=None, resolution=None, views=None,
                   seed=None, max_depth=None, off_ring=None) -> Scene:
    """A copy of ``scene`` with command-line overrides applied (None keeps the scene's value).

    Raises
    ------
    InputError
        If a value is out of range.
    """
    for name, value in (("order", order), ("spp", spp), ("resolution", resolution),
                        ("seed", seed), ("max_depth", max_depth)):
        low, high = LIMITS[name]
        if value is not None and value < low:
            raise InputError(f"{name} must be at least {low}, got {value}")
        if value is not None and value > high:
            raise InputError(f"{name} must be at most {high}, got {value}")
    low, high = LIMITS["views"]
    if views is not None and (len(views) != 3 or min(views) < low or max(views) > high
                              or views[0] < 1):
        raise InputError(f"views must be TRAIN VAL TEST counts in [{low}, {high}] with "
                         f"TRAIN >= 1, got {views}")
    render = scene.render
    if order is not None:
        if not scene.palette_materials:
            raise InputError(f"scene {scene.name} has no editable material, so there is no "
                             "transport order to set")
        render = replace(render, order=order)
    render = replace(render, spp=render.spp if spp is None else spp,
                     seed=render.seed if seed is None else seed,
                     max_depth=render.max_depth if max_depth is None else max_depth)
    camera = scene.camera
    if resolution is not None:
        camera = replace(camera, width=resolution, height=resolution)
    if views is not None:
        camera = replace(camera, views=dict(zip(SPLITS, views)))
    if off_ring is not None:
        if not low <= off_ring <= high:
            raise InputError(f"off-ring views must be in [{low}, {high}], got {off_ring}")
        camera = replace(camera, off_ring=off_ring)
    return replace(scene, render=render, camera=camera)


def with_palette(scene: Scene, palette: np.ndarray, only: set[str] | None = None) -> Scene:
    """A copy of ``scene`` whose editable materials take their (K, 3) ``palette`` albedos, or,
    with ``only``, those materials named in it only (a local edit: the others keep theirs).

    Raises
    ------
    InputError
        If the palette has another size than the scene's, or ``only`` names a material that
        is not editable.
    """
    palette = np.asarray(palette, np.float64)
    k = len(scene.palette_materials)
    if palette.shape != (k, 3):
        raise InputError(f"palette must have shape ({k}, 3) for scene {scene.name}, "
                         f"got {palette.shape}")
    editable = {m.name for m in scene.materials if m.editable}
    if only is not None and not set(only) <= editable:
        unknown = sorted(set(only) - editable)[0]
        raise InputError(f"scene {scene.name} has no editable material {unknown!r} "
                         f"(editable: {', '.join(sorted(editable))})")
    materials = [replace(m, albedo=palette[scene.palette_index(m)])
                 if m.editable and (only is None or m.name in only) else m
                 for m in scene.materials]
    return replace(scene, materials=materials)


def view_poses(scene: Scene) -> tuple[list[str], np.ndarray]:
    """Names (``<split>/r_<i>.png``) and (N, 4, 4) poses of every view, train then val then
    test, then the test views off the rig (``test/o_<i>.png``, ``is_off_ring``)."""
    cam = scene.camera
    names, poses = [], []
    for split in SPLITS:
        n = cam.views[split]
        names += [f"{split}/r_{i:03d}.png" for i in range(n)]
        poses.append(rig_poses(cam.rig, n, cam.target, cam.radius, cam.elevation, cam.arc,
                               SPLIT_PHASES[split]))
    names += [f"test/{OFF_RING_PREFIX}{i:03d}.png" for i in range(cam.off_ring)]
    poses.append(off_ring_poses(cam.rig, cam.off_ring, cam.target, cam.radius, cam.elevation,
                                cam.arc))
    return names, np.concatenate(poses)


OFF_RING_PREFIX = "o_"  # test views off the rig: test/o_000.png, ...


def is_off_ring(name: str) -> bool:
    """Whether the view ``name`` of a simulated scene lies off the rig."""
    return name.startswith(f"test/{OFF_RING_PREFIX}")


def render_terms(scene: Scene, poses: np.ndarray, split: bool, progress: bool = False):
    """Path trace views; contributions sorted by transport term (``split``) or summed as RGB.

    Returns
    -------
    terms : (N, H, W, M, 3) float64
        Mean contribution per term (M = 1 when not ``split``).
    alpha : (N, H, W) float64
    """
    arrays = scene_arrays(scene)
    k, render, cam = len(scene.palette_materials), scene.render, scene.camera
    table = next_term_table(k, render.order)
    m = len(table) if split else 1
    focal = focal_from_fov(cam.width, cam.fov)
    terms = np.zeros((len(poses), cam.height * cam.width, m, 3))
    alpha = np.zeros((len(poses), cam.height * cam.width))
    for view in tqdm(range(len(poses)), desc=f"simulate {scene.name}", unit="view",
                     disable=not progress):
        trace_view(np.ascontiguousarray(poses[view], np.float64), focal, cam.width,
                   cam.height, render.spp, render.max_depth, split, render.seed, view, arrays,
                   table, terms[view], alpha[view])
    shape = (len(poses), cam.height, cam.width)
    return terms.reshape(*shape, m, 3), alpha.reshape(shape)


def simulate(scene: Scene, progress: bool = True) -> Simulation:
    """Render every view of ``scene``; with editable materials, keep the transport weights.

    Raises
    ------
    InputError
        If the scene has editable materials but a fixed material or a light is
        coloured: format-v1 weights hold one number per term, which is exact only
        when everything that is not a palette colour is grey.
    """
    palette = np.array([m.albedo for m in scene.palette_materials]).reshape(-1, 3)
    split = len(palette) > 0
    _check_size(scene, split)
    if split:
        _require_grey_fixed(scene)
    names, poses = view_poses(scene)
    start = time.perf_counter()
    terms, alpha = render_terms(scene, poses, split, progress)
    seconds = time.perf_counter() - start
    if split:
        weights = terms.mean(-1)  # the three channels are equal: fixed factors are grey
        radiance = weights @ transport_basis(palette, scene.render.order)
    else:
        weights, radiance = None, terms[..., 0, :]
    return Simulation(names, poses, radiance, alpha, weights, palette, scene.render.order, seconds)


def _check_size(scene: Scene, split: bool) -> None:
    """InputError if the per-term radiance of all views would exceed ``MAX_TERM_BYTES``."""
    cam = scene.camera
    terms = n_terms(len(scene.palette_materials), Basis.TRANSPORT, scene.render.order) \
        if split else 1
    views = sum(cam.views.values()) + cam.off_ring
    needed = views * cam.width * cam.height * terms * 3 * 8
    if needed > MAX_TERM_BYTES:
        raise InputError(f"scene {scene.name}: {views} views of "
                         f"{cam.width}x{cam.height} with {terms} transport terms need "
                         f"{needed / 2**30:.1f} GiB, more than {MAX_TERM_BYTES / 2**30:.0f} GiB: "
                         "use fewer views, a lower resolution or a lower order")


def _require_grey_fixed(scene: Scene) -> None:
    def grey(rgb) -> bool:
        return np.ptp(rgb, axis=-1).max() <= GREY_TOL

    for m in scene.materials:
        colour = m.texture if m.texture is not None else m.albedo
        if not m.editable and not grey(colour):
            raise InputError(f"scene {scene.name}: fixed material {m.name!r} is coloured, but "
                             "transport weights need grey fixed materials and lights (make it "
                             "grey or editable)")
    for i, light in enumerate(scene.lights):
        if not grey(light.get("emission", light.get("intensity"))):
            raise InputError(f"scene {scene.name}: lights[{i}] is coloured, but transport "
                             "weights need white (grey) lights")


#: Dataset layouts ``write_dataset`` writes.
LAYOUTS = ("blender", "nerfstudio")


def write_dataset(sim: Simulation, scene: Scene, outdir: str | os.PathLike, spec: str,
                  force: bool = False, layout: str = "blender") -> list[str]:
    """Write ``sim`` as a dataset into ``outdir``, atomically.

    ``blender``: ``transforms_{train,val,test}.json``, ``<split>/r_<i>.png`` and, with
    editable materials, ``weights.npz`` and ``materials.json``. ``nerfstudio``: a
    capture folder, ``images/frame_<i>.png`` and ``transforms.json`` only, ready for
    ``palette-decompose images/`` and ``nerf-stage train`` in it. The folder is built
    beside ``outdir`` and renamed onto it at the end (``outputs.publish_folder``); an
    existing non-empty ``outdir`` is replaced only with ``force``.

    Returns
    -------
    list of str
        The files written, relative to ``outdir``.
    """
    if layout not in LAYOUTS:
        raise InputError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    with publish_folder(outdir, force) as staging:
        if layout == "nerfstudio":
            return _write_nerfstudio(sim, scene, staging)
        return _write_files(sim, scene, staging, spec)


def simulate_to(spec: str, outdir: str | os.PathLike, layout: str = "blender",
                force: bool = False, **overrides) -> tuple[Scene, Simulation, list[str]]:
    """``nerf-stage simulate``: the scene ``spec`` (a built-in's name or a scene file,
    ``load_scene``) with ``overrides`` (``with_overrides``) path traced (``simulate``) and
    written into ``outdir`` (``write_dataset``). Returns the scene, its simulation and the
    files written."""
    scene = with_overrides(load_scene(spec), **overrides)
    if scene.camera.off_ring and layout != "blender":
        raise InputError("off-ring test views are written in the blender layout only (its "
                         "transforms_test.json marks them)")
    check_outdir(outdir, force)
    sim = simulate(scene)
    source = spec if spec in BUILTIN_SCENES else str(Path(spec).resolve())
    return scene, sim, write_dataset(sim, scene, outdir, source, force=force, layout=layout)


def _write_images(sim: Simulation, root: Path, names: list[str]) -> None:
    """Straight-alpha RGBA PNGs of the views (alpha: the share of rays that hit)."""
    alpha = sim.alpha[..., None]
    straight = np.divide(sim.radiance, alpha, out=np.zeros_like(sim.radiance), where=alpha > 0)
    for name, image in zip(names, np.concatenate([straight, alpha], axis=-1)):
        (root / name).parent.mkdir(exist_ok=True)
        save_image(root / name, image)


def _write_nerfstudio(sim: Simulation, scene: Scene, root: Path) -> list[str]:
    names = [f"images/frame_{i + 1:05d}.png" for i in range(len(sim.names))]
    _write_images(sim, root, names)
    cam = scene.camera
    frames = nerfstudio_transforms(sim.poses, names, cam.width, cam.height, cam.fov,
                                   [is_off_ring(name) for name in sim.names])
    (root / "transforms.json").write_text(json.dumps(frames, indent=2) + "\n")
    return names + ["transforms.json"]


def _write_files(sim: Simulation, scene: Scene, root: Path, spec: str) -> list[str]:
    _write_images(sim, root, sim.names)
    written = list(sim.names)
    for split in SPLITS:
        index = [i for i, name in enumerate(sim.names) if name.startswith(split + "/")]
        frames = blender_transforms(sim.poses[index], [sim.names[i][:-4] for i in index],
                                    scene.camera.fov, [is_off_ring(sim.names[i]) for i in index])
        (root / f"transforms_{split}.json").write_text(json.dumps(frames, indent=2) + "\n")
        written.append(f"transforms_{split}.json")
    if sim.weights is None:
        return written
    render, cam = scene.render, scene.camera
    record = SimulationRecord(spec, sim.order, render.max_depth, render.spp, render.seed,
                              [cam.width, cam.height], {**cam.views, "off_ring": cam.off_ring},
                              round(sim.seconds, 3))
    stack = WeightStack(palette=sim.palette, weights=list(sim.weights.astype(np.float32)),
                        names=sim.names, method="simulated", basis=Basis.TRANSPORT,
                        order=sim.order, meta=record.to_meta())
    write_stack(stack, root / "weights.npz")
    materials = {"materials": [m.name for m in scene.palette_materials],
                 "palette": palette_to_hex(sim.palette)}
    (root / "materials.json").write_text(json.dumps(materials, indent=2) + "\n")
    return written + ["weights.npz", "materials.json"]
