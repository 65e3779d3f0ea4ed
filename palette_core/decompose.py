"""The decomposition pipeline: images -> one shared palette -> a weight stack."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from .errors import InputError
from .hull import extract_palette
from .io import ColourSet, LoadedImage, find_images, load_images
from .mvc import rgb_to_mvc_weights
from .polytope import Polytope
from .rgbxy import rgbxy_image_weights
from .stack import WeightStack

#: Above this many images, loading and weighting show progress bars.
PROGRESS_MIN_IMAGES = 8


def mvc_image_weights(
    colour_set: ColourSet, images: list[LoadedImage], poly: Polytope
) -> Iterator[np.ndarray]:
    """(H, W, K) MVC weights per image, computed once per distinct colour and scattered."""
    unique = rgb_to_mvc_weights(colour_set.colours, poly)
    for i, image in enumerate(images):
        yield unique[colour_set.image_indices(i)].reshape(*image.opaque.shape, -1)


#: Weight methods by name: (colour set, images, palette polytope, **options) -> weights
#: per image.
WEIGHT_METHODS = {"mvc": mvc_image_weights, "rgbxy": rgbxy_image_weights}


@dataclass
class Decomposition:
    """A weight stack with what it took to make it.

    Attributes
    ----------
    stack : WeightStack
    rmse : dict of str to float
        Per-image RMSE (0-255 scale, per channel, opaque pixels) of the stored
        weights times the stored palette against the image.
    rmse_overall : float
        The same over all pixels of all images.
    timings : dict of str to float
        Seconds per stage: load, palette, weights.
    """

    stack: WeightStack
    rmse: dict[str, float]
    rmse_overall: float
    timings: dict[str, float]


def decompose(
    inputs: list,
    k: int | None = 6,
    max_error: float | None = None,
    method: str = "mvc",
    dtype: str = "float32",
    method_options: dict | None = None,
) -> Decomposition:
    """Decompose image files and folders into one shared palette and per-pixel weights.

    Parameters
    ----------
    inputs : list of path-like
        Image files and/or folders (searched recursively, sorted).
    k, max_error :
        Palette size or reconstruction tolerance, see ``hull.extract_palette``.
    method : str
        A key of ``WEIGHT_METHODS``.
    dtype : {"float32", "float16"}
        Storage type of the weights.
    method_options : dict, optional
        Keyword arguments of the weight method (``spatial_scale`` for rgbxy).

    Raises
    ------
    InputError
        On unreadable inputs or invalid options.
    """
    if method not in WEIGHT_METHODS:
        raise InputError(f"method must be one of {sorted(WEIGHT_METHODS)}, got {method!r}")
    if dtype not in ("float32", "float16"):
        raise InputError(f"dtype must be float32 or float16, got {dtype!r}")
    timings = {}
    start = time.perf_counter()
    root, paths = find_images(inputs)
    progress = len(paths) >= PROGRESS_MIN_IMAGES
    images = load_images(paths, root, progress)
    colour_set = ColourSet.from_images(images)
    timings["load"] = time.perf_counter() - start

    start = time.perf_counter()
    poly = extract_palette(colour_set.colours, colour_set.counts, k, max_error)
    palette = poly.vertices.astype(np.float32)
    timings["palette"] = time.perf_counter() - start

    start = time.perf_counter()
    method_options = method_options or {}
    produced = WEIGHT_METHODS[method](colour_set, images, poly, **method_options)
    weights = [w.astype(dtype) for w in tqdm(produced, total=len(images), desc="weights",
                                             unit="img", disable=not progress)]
    timings["weights"] = time.perf_counter() - start

    rmse, squared, count = {}, 0.0, 0
    for image, w in zip(images, weights):
        error = w.astype(np.float32) @ palette - image.rgb
        sq = float(np.sum(error[image.opaque] ** 2))
        n = int(image.opaque.sum())
        rmse[image.name] = 255.0 * np.sqrt(sq / max(3 * n, 1))
        squared, count = squared + sq, count + n
    overall = 255.0 * np.sqrt(squared / max(3 * count, 1))

    from . import __version__

    meta = {
        "version": __version__,
        "k": k,
        "max_error": max_error,
        "dtype": dtype,
        "method_options": method_options,
        "n_pixels": int(colour_set.offsets[-1]),
        "n_colours": len(colour_set.colours),
        "rmse": rmse,
        "rmse_overall": overall,
        "timings": timings,
    }
    stack = WeightStack(palette, weights, [im.name for im in images], method,
                        hull_faces=poly.faces.astype(np.int32), meta=meta)
    return Decomposition(stack, rmse, overall, timings)
