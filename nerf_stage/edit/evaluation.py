"""Scores of a trained run: PSNR and SSIM on the test views, and edits against re-simulation.

For runs on simulated transport stacks, an edited palette recolours the weight
render, and the scene is path traced again with that palette as the ground truth.
"""

from __future__ import annotations

import os
import time

import numpy as np

from palette_core.basis import Basis
from palette_core.palette_file import read_palette_json

from ..fields import RGB
from ..simulation import SimulationRecord
from ..train.loading import load_run
from ..train.metrics import image_scores
from ..train.run import Run, RunBase
from .editing import WeightRender, render_poses


def resimulated_views(simulation: SimulationRecord, palette: np.ndarray, poses: np.ndarray,
                      background: np.ndarray, only: set[str] | None = None) -> np.ndarray:
    """(N, H, W, 3) views of the simulated scene behind a transport stack, re-traced with
    its editable materials (or those named in ``only``: a local edit) set to ``palette``
    and composited like the dataset's PNGs."""
    from ..simulation import load_scene, render_terms, with_palette

    scene = simulation.applied_to(load_scene(simulation.scene))
    radiance, alpha = render_terms(with_palette(scene, palette, only), poses, split=False)
    return composited(radiance[..., 0, :], alpha, background)


def composited(radiance: np.ndarray, alpha: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) colours as a simulated dataset's PNGs show them, from radiance (N, H, W, 3)
    premultiplied by alpha (N, H, W): the straight colour clipped to [0, 1], over
    ``background``."""
    a = alpha[..., None]
    return np.clip(radiance / np.maximum(a, 1e-12), 0, 1) * a + (1 - a) * background


def rolled_palette(palette: np.ndarray) -> np.ndarray:
    """The default edit of ``eval``: every palette colour takes the next one's."""
    return np.roll(palette, -1, axis=0)


def evaluate_run(rundir: str | os.PathLike, palette: str | os.PathLike | None = None,
                 baked: int | None = None) -> tuple[RunBase, dict]:
    """``nerf-stage eval``: the run in ``rundir`` (baked ``baked`` times finer, when given:
    ``Run.baked``) scored on its dataset (``evaluate``), the edit being the palette file
    ``palette`` when given. Returns the run and its scores."""
    run = load_run(rundir)
    if baked is not None:
        run = run.baked(baked)
    edit = None if palette is None else read_palette_json(palette, k=len(run.palette))
    return run, evaluate(run, run.dataset(), edit)


def evaluate(run: Run, dataset, edit: np.ndarray | None = None,
             progress: bool = True) -> dict:
    """Scores of the run on the dataset's test views.

    Returns a dict with ``reconstruction`` (PSNR, SSIM of the RGB through the
    weights, or of the RGB NeRF, against the test images on the training rig),
    ``off_ring`` (the same on the test views off it, when the dataset has any:
    ``Dataset.off_ring``), the render time per view, and, for runs on simulated
    transport stacks, ``edit``: the render on the rig recoloured with ``edit``
    (default ``rolled_palette``) against the scene re-simulated with that palette.
    """
    names, poses, cameras = render_poses(run, dataset, "test", None)
    ids = dataset.indices("test")
    truth, off = dataset.images[ids], dataset.off_ring[ids]
    start = time.perf_counter()
    values, opacity = run.render(poses, progress, cameras)
    seconds = (time.perf_counter() - start) / len(poses)
    background = np.asarray(run.config.background, np.float64)
    scores = {"views": int((~off).sum()), "seconds_per_view": seconds}
    if run.kind == RGB:
        rgb = np.clip(values + (1 - opacity[..., None]) * background, 0, 1)
        return {**scores, **_split_scores(rgb, truth, off)}
    ring = [name for name, away in zip(names, off) if not away]
    render = WeightRender(values[~off], opacity[~off], ring, run.palette, run.basis,
                          run.order, background, {})
    rgb = WeightRender(values, opacity, names, run.palette, run.basis, run.order, background,
                       {}).recolor()
    scores.update(_split_scores(rgb, truth, off))
    simulation = SimulationRecord.from_meta(run.record.stack_meta)
    if run.basis == Basis.TRANSPORT and simulation is not None:
        edit = rolled_palette(run.palette) if edit is None else edit
        start = time.perf_counter()
        recoloured = render.recolor(edit)
        scores["recolour_seconds_per_view"] = (time.perf_counter() - start) / len(recoloured)
        truth = resimulated_views(simulation, edit, poses[~off], background)
        scores["edit"] = dict(image_scores(recoloured, truth), palette=np.asarray(edit).tolist())
    return scores


def _split_scores(rgb: np.ndarray, truth: np.ndarray, off: np.ndarray) -> dict:
    """``reconstruction`` scores of the views on the rig and, if any, ``off_ring`` ones."""
    scores = {"reconstruction": image_scores(rgb[~off], truth[~off])}
    if off.any():
        scores["off_ring"] = dict(image_scores(rgb[off], truth[off]), views=int(off.sum()))
    return scores


__all__ = ["composited", "evaluate", "resimulated_views", "rolled_palette"]
