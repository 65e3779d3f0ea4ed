"""The decomposition pipeline: images -> one shared palette -> a weight stack, and its files."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .colour_set import ColourSet
from .errors import InputError, OutputExists
from .io import DEFAULT_MAX_PIXELS, find_images, load_images
from .outputs import atomic_outputs, check_apart, check_writable, save_image
from .palette_file import palette_paths, write_palette_json
from .palettes import PALETTE_METHODS, check_palette_size, palette_polytope
from .registry import check_options
from .stack import DEFAULT_STACK, WeightStack, check_dtype, stored_weights, write_stack
from .swatch import layer_paths, palette_swatch
from .version import __version__
from .weights import check_weight_method, image_weights

#: Above this many images, loading and weighting show progress bars.
PROGRESS_MIN_IMAGES = 8


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
        Seconds per stage: load, palette, weights (and write, once written).
    requested_k : int or None
        The palette size asked for.
    inputs : list of Path
        The image files and folders it was made from (outputs may not land among them).
    """

    stack: WeightStack
    rmse: dict[str, float]
    rmse_overall: float
    timings: dict[str, float]
    requested_k: int | None = None
    inputs: list[Path] = field(default_factory=list)

    @property
    def hull_too_small(self) -> bool:
        """The colours' hull has fewer vertices than the K asked for (the whole hull is used)."""
        k, max_error = self.requested_k, self.stack.meta["max_error"]
        return k is not None and max_error is None and len(self.stack.palette) < k

    def output_paths(self, output: str | Path) -> list[Path]:
        """The stack, and beside it the palette swatch and JSON named after it
        (``w.npz``: ``w.palette.png``, ``w.palette.json``; docs/formats.md)."""
        return [Path(output), *palette_paths(output)]

    def write(self, output: str | Path, layers: str | Path | None = None,
              force: bool = False) -> list[Path]:
        """Write the stack, its palette swatch and JSON, and optionally weight-map PNGs.

        Every file is staged and published together (``outputs.atomic_outputs``).
        No output may be an input or lie inside an input folder, where the next
        run would read it as an image.

        Returns
        -------
        list of Path
            The stack, the swatch, the palette JSON and the layers folder (if any).

        Raises
        ------
        InputError
            If ``output`` does not end in .npz, an output exists (without ``force``),
            or a folder cannot be written.
        """
        stack_path, swatch, palette_json = paths = self.output_paths(output)
        if stack_path.suffix != ".npz":
            raise InputError(f"output must end in .npz, got {stack_path}")
        check_writable(paths, force)
        layers = None if layers is None else Path(layers)
        check_apart(paths + ([layers] if layers is not None else []), self.inputs)
        if layers is not None:
            if layers.exists() and (not layers.is_dir() or (any(layers.iterdir()) and not force)):
                raise OutputExists(f"layers folder {layers} exists and is not empty",
                                   "to write into it")
            check_writable([layers / "probe"], True)
        start = time.perf_counter()
        stack = self.stack
        with atomic_outputs(force) as stage:
            with open(stage(stack_path), "wb") as f:
                write_stack(stack, f)
            palette_swatch(stack.palette).save(stage(swatch), format="PNG")
            with open(stage(palette_json), "w") as f:
                write_palette_json(f, stack.palette)
            for name, weights in zip(stack.names, stack.weights) if layers else ():
                for j, path in enumerate(layer_paths(layers, name, len(stack.palette))):
                    save_image(stage(path), weights[..., j].astype(np.float32))
        self.timings["write"] = time.perf_counter() - start
        return paths + ([layers] if layers is not None else [])


def decompose(
    inputs: list,
    k: int | None = None,
    max_error: float | None = None,
    method: str = "mvc",
    dtype: str = "float32",
    method_options: dict | None = None,
    palette_method: str = "refined",
    max_pixels: int = DEFAULT_MAX_PIXELS,
    palette_options: dict | None = None,
) -> Decomposition:
    """Decompose image files and folders into one shared palette and per-pixel weights.

    Parameters
    ----------
    inputs : list of path-like
        Image files and/or folders (searched recursively, sorted).
    k, max_error :
        Palette size or reconstruction tolerance, see ``hull.extract_palette``
        (neither: ``hull.DEFAULT_K`` colours).
    method : str
        A key of ``weights.WEIGHT_METHODS``.
    dtype : {"float32", "float16"}
        Storage type of the weights.
    method_options : dict, optional
        Keyword options of the weight method (``spatial_scale`` for rgbxy).
    palette_method : str
        A key of ``palettes.PALETTE_METHODS``.
    max_pixels : int
        Largest image to decode (``io.DEFAULT_MAX_PIXELS``); larger ones are refused
        from their header.
    palette_options : dict, optional
        Keyword options of the palette method.

    Raises
    ------
    InputError
        On unreadable inputs, images with no opaque pixel at all, or invalid options.

    Notes
    -----
    float16 weights are rounded so that each pixel's weights still sum to one
    within ``FLOAT16_SUM_TOL`` (the residual of the rounding goes to its largest weight).
    """
    k = check_palette_size(k, max_error)
    method_options, palette_options = method_options or {}, palette_options or {}
    _check_settings(method, method_options, palette_method, palette_options, dtype, max_pixels)
    start = time.perf_counter()
    images, colour_set = _colour_set(inputs, max_pixels)
    progress = len(images) >= PROGRESS_MIN_IMAGES
    timings = {"load": time.perf_counter() - start}

    start = time.perf_counter()
    poly = palette_polytope(colour_set.colours, colour_set.counts, k, max_error, palette_method,
                            **palette_options)
    palette = poly.vertices.astype(np.float32)
    timings["palette"] = time.perf_counter() - start

    from tqdm import tqdm

    start = time.perf_counter()
    produced = image_weights(colour_set, poly, method, **method_options)
    weights = [stored_weights(w, dtype) for w in tqdm(produced, total=len(images), desc="weights",
                                               unit="img", disable=not progress)]
    timings["weights"] = time.perf_counter() - start

    rmse, overall = _reconstruction_errors(images, weights, palette)
    meta = {"version": __version__, "k": k, "max_error": max_error, "dtype": dtype,
            "method_options": method_options, "palette_method": palette_method,
            "palette_options": palette_options, "n_pixels": int(colour_set.offsets[-1]),
            "n_colours": len(colour_set.colours), "rmse": rmse, "rmse_overall": overall,
            "timings": timings}
    stack = WeightStack(palette, weights, [im.name for im in images], method,
                        hull_faces=poly.faces.astype(np.int32), meta=meta)
    return Decomposition(stack, rmse, overall, timings, k, [Path(p) for p in inputs])


def _colour_set(inputs: list, max_pixels: int) -> tuple[list, ColourSet]:
    """The images of ``inputs`` and their colour set, refused when no pixel is opaque."""
    root, paths = find_images(inputs)
    images = load_images(paths, root, len(paths) >= PROGRESS_MIN_IMAGES, max_pixels)
    colour_set = ColourSet.from_images(images)
    if not colour_set.counts.any():
        raise InputError("every pixel of every image is fully transparent: there are no colours "
                         "to take a palette from")
    return images, colour_set


def _check_settings(method: str, method_options: dict, palette_method: str,
                    palette_options: dict, dtype: str, max_pixels: int) -> None:
    """InputError unless ``decompose``'s settings name known methods with their options."""
    check_weight_method(method, method_options)
    check_options(PALETTE_METHODS, palette_method, "palette method", palette_options)
    check_dtype(dtype)
    if not max_pixels >= 1:
        raise InputError(f"max_pixels must be at least 1, got {max_pixels}")


def _reconstruction_errors(images: list, weights: list,
                           palette: np.ndarray) -> tuple[dict[str, float], float]:
    """RMSE (0-255 scale) of ``weights @ palette`` against each image's opaque pixels, by
    image name, and over all of them."""
    rmse, squared, count = {}, 0.0, 0
    for image, w in zip(images, weights):
        error = w.astype(np.float32) @ palette - image.rgb
        sq = float(np.sum(error[image.opaque] ** 2))
        n = int(image.opaque.sum())
        rmse[image.name] = 255.0 * np.sqrt(sq / max(3 * n, 1))
        squared, count = squared + sq, count + n
    return rmse, 255.0 * np.sqrt(squared / max(3 * count, 1))


def decompose_to(inputs: list, output: str | os.PathLike = DEFAULT_STACK,
                 layers: str | os.PathLike | None = None, force: bool = False,
                 workers: int | None = None, scheduler: str | None = None,
                 resume: bool = False, **settings) -> tuple:
    """``palette-decompose``: ``inputs`` into the weight stack ``output``, in memory to an
    NPZ (``decompose``, then ``Decomposition.write`` with weight maps in ``layers``) or
    streamed into a Zarr store, which videos need (``collection.decompose_collection``, on
    a dask cluster of ``workers`` local processes or at ``scheduler``, ``resume`` finishing
    a stopped one). ``settings`` are ``decompose``'s (``k``, ``max_error``, ``method``, ...).
    Returns the ``Decomposition`` or ``Collection`` and the paths written."""
    from .cluster import check_workers, dask_client
    from .sources import is_video
    from .stack import is_zarr

    check_workers(workers, scheduler)
    if not (is_zarr(output) or any(is_video(path) for path in inputs)):
        if workers is not None or scheduler is not None or resume:
            raise InputError("a cluster and resuming need a Zarr stack: name the output "
                             "NAME.zarr", "output")
        result = decompose(inputs, **settings)
        return result, result.write(output, layers, force)
    from .collection import decompose_collection

    if not is_zarr(output):
        raise InputError(f"videos are decomposed into a Zarr stack: name the output "
                         f"NAME.zarr, not {output}", "output")
    if layers:
        raise InputError("a Zarr stack is written without weight maps: write an NPZ stack "
                         "for them", "layers")
    with dask_client(workers, scheduler) as client:
        done = decompose_collection(inputs, str(output), client=client, resume=resume,
                                    force=force, **settings)
    return done, [output, *palette_paths(output)]
