"""Weight renders of a trained run: render once, recolour by palette edits, evaluate.

A weight render (``render.npz``) holds the composited weights of some views,
premultiplied by opacity, with the opacity itself. Recolouring it is a matrix
product, ``image = weights @ basis(palette) + (1 - opacity) background``, and
never runs the network again.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from skimage.metrics import structural_similarity

from palette_core.errors import InputError
from palette_core.basis import weights_to_rgb
from palette_core.stack import WeightStack

from .cameras import orbit_poses
from .trainer import Run

RENDER_FILE = "render.npz"


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
    basis : str
    order : int
    background : (3,) float64
    source : dict
        Run directory, checkpoint iteration and views: what the render came from.
    """

    weights: np.ndarray
    opacity: np.ndarray
    names: list[str]
    palette: np.ndarray
    basis: str
    order: int
    background: np.ndarray
    source: dict

    def recolor(self, palette: np.ndarray | None = None) -> np.ndarray:
        """(N, H, W, 3) float64 images in [0, 1] for ``palette`` (K, 3), the run's by default."""
        palette = self.palette if palette is None else np.asarray(palette, np.float64)
        if palette.shape != self.palette.shape:
            raise InputError(f"palette must have shape {self.palette.shape} like the run's, "
                             f"got {palette.shape}")
        rgb = (weights_to_rgb(self.weights, palette, self.basis, self.order)
               + (1 - self.opacity[..., None]) * self.background)
        return np.clip(rgb, 0, 1)

    def as_stack(self) -> WeightStack:
        """The weights as a format-v1 stack (for palette shares and harmonisation)."""
        return WeightStack(self.palette, list(self.weights), self.names, "nerf", self.basis,
                           self.order)


def render_poses(run: Run, dataset, split: str | None, orbit: int | None):
    """Names and (N, 4, 4) poses of a split of the run's dataset, or of an orbit of N views."""
    train = dataset.indices("train")
    if orbit is not None:
        if orbit < 1:
            raise InputError(f"--orbit must be >= 1, got {orbit}")
        return [f"orbit_{i:03d}" for i in range(orbit)], orbit_poses(dataset.poses[train],
                                                                    orbit, run.box.centre)
    ids = dataset.indices(split)
    if len(ids) == 0:
        raise InputError(f"dataset {dataset.root} has no {split} views")
    return [Path(dataset.names[i]).stem for i in ids], dataset.poses[ids]


def render_weights(run: Run, names: list[str], poses: np.ndarray, source: dict,
                   progress: bool = True) -> WeightRender:
    """Render the run's weights for ``poses`` (runs the network)."""
    if run.field.kind == "rgb":
        raise InputError("this run was trained on RGB only (strategy 'rgb'): it has no weights")
    weights, opacity = run.render(poses, progress=progress)
    return WeightRender(weights, opacity, names, run.palette, run.basis, run.order,
                        np.asarray(run.config.background, np.float64), source)


def write_render(render: WeightRender, path: Path) -> None:
    np.savez(path, weights=render.weights, opacity=render.opacity,
             names=np.array(render.names, dtype=str), palette=render.palette,
             basis=np.array(render.basis), order=np.array(render.order),
             background=render.background, source=np.array(json.dumps(render.source)))


def read_render(path: Path) -> WeightRender:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return WeightRender(npz["weights"], npz["opacity"], npz["names"].tolist(),
                                npz["palette"], str(npz["basis"]), int(npz["order"]),
                                npz["background"], json.loads(str(npz["source"])))
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(f"{path} is not a readable weight render: {exc}") from None


def write_gif(path: Path, frames: np.ndarray, seconds_per_frame: float = 0.08) -> None:
    """Write (N, H, W, 3) float frames in [0, 1] as a looping GIF."""
    images = [Image.fromarray(np.round(f * 255).astype(np.uint8)) for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=int(seconds_per_frame * 1000), loop=0)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def image_scores(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """Mean PSNR and SSIM (scikit-image) of (N, H, W, 3) images against the truth."""
    return {
        "psnr": float(np.mean([psnr(p, t) for p, t in zip(predicted, truth)])),
        "ssim": float(np.mean([structural_similarity(p, t, channel_axis=-1, data_range=1.0)
                               for p, t in zip(predicted, truth)])),
    }


def resimulated_views(scene_meta: dict, palette: np.ndarray, poses: np.ndarray,
                      background: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) views of the simulated scene behind a transport stack, re-traced with
    its editable materials set to ``palette`` and composited like the dataset's PNGs."""
    from .simulation import load_scene, render_terms, with_overrides, with_palette

    overrides = {k: scene_meta[k] for k in ("order", "spp", "seed", "max_depth")}
    width, height = scene_meta["resolution"]
    if width == height:  # a square override; the scene's own size otherwise
        overrides["resolution"] = width
    scene = with_overrides(load_scene(scene_meta["scene"]), **overrides)
    radiance, alpha = render_terms(with_palette(scene, palette), poses, split=False)
    radiance = radiance[..., 0, :]
    straight = np.clip(radiance / np.maximum(alpha[..., None], 1e-12), 0, 1)
    return straight * alpha[..., None] + (1 - alpha[..., None]) * background


def rolled_palette(palette: np.ndarray) -> np.ndarray:
    """The default edit of ``eval``: every palette colour takes the next one's."""
    return np.roll(palette, -1, axis=0)


def evaluate(run: Run, dataset, edit: np.ndarray | None = None,
             progress: bool = True) -> dict:
    """Scores of the run on the dataset's test views.

    Returns a dict with ``reconstruction`` (PSNR, SSIM of the RGB through the
    weights, or of the RGB NeRF, against the test images), the render time per
    view, and, for runs on simulated transport stacks, ``edit``: the render
    recoloured with ``edit`` (default ``rolled_palette``) against the scene
    re-simulated with that palette.
    """
    names, poses = render_poses(run, dataset, "test", None)
    truth = dataset.images[dataset.indices("test")]
    start = time.perf_counter()
    values, opacity = run.render(poses, progress=progress)
    seconds = (time.perf_counter() - start) / len(poses)
    background = np.asarray(run.config.background, np.float64)
    scores = {"views": len(poses), "seconds_per_view": seconds}
    if run.field.kind == "rgb":
        scores["reconstruction"] = image_scores(
            np.clip(values + (1 - opacity[..., None]) * background, 0, 1), truth)
        return scores
    render = WeightRender(values, opacity, names, run.palette, run.basis, run.order,
                          background, {})
    scores["reconstruction"] = image_scores(render.recolor(), truth)
    scene_meta = run.meta.get("stack_meta", {})
    if run.basis == "transport" and "scene" in scene_meta:
        edit = rolled_palette(run.palette) if edit is None else edit
        start = time.perf_counter()
        recoloured = render.recolor(edit)
        scores["recolour_seconds_per_view"] = (time.perf_counter() - start) / len(poses)
        truth = resimulated_views(scene_meta, edit, poses, background)
        scores["edit"] = dict(image_scores(recoloured, truth), palette=np.asarray(edit).tolist())
    return scores


__all__ = ["WeightRender", "evaluate", "image_scores", "psnr", "read_render", "render_poses",
           "render_weights", "resimulated_views", "rolled_palette", "write_gif", "write_render"]
