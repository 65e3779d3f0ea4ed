"""The weight stack: a palette and per-image weights (docs/formats.md),
and the checks that every reader of one applies.

Stacks are stored as NPZ files (``stack.npz``) or Zarr stores (``stack.zarr``);
``read_stack`` and ``write_stack`` in ``stack/__init__.py`` choose by the path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from ..basis import Basis
from ..errors import InputError

FORMAT = "palette-weights/1"
#: Where ``palette-decompose`` writes its stack, and where the other commands look for one.
DEFAULT_STACK = "weights.npz"
#: Fastest frame rate a stack's video may declare (``meta["videos"]``).
MAX_FPS = 1000.0
#: Each pixel's float16 weights sum to one within this (half a float16 step at 1, plus
#: the float32 sum's rounding); float32 weights hold ``constants.WEIGHT_SUM_TOL``.
FLOAT16_SUM_TOL = 2.5e-4


@dataclass
class WeightStack:
    """Palette and weights of a set of images.

    Attributes
    ----------
    palette : (K, 3) float32
        Palette colours, sRGB in [0, 1].
    weights : list of (H_i, W_i, M) float32 or float16
        One weight image per input image, in stitch order.
    names : list of str
        Image paths relative to the input root.
    method : str
        ``"mvc"``, ``"rgbxy"`` or ``"simulated"``.
    basis : Basis
        ``ADDITIVE`` (M = K) or ``TRANSPORT`` (M = C(K + order, order)).
    order : int
        Transport order; 1 for additive stacks.
    hull_faces : (F, 3) int32
        Outward triangles of the palette polytope; empty when it is flat.
    meta : dict
        Package version, parameters, per-image RMSE, timings.
    """

    palette: np.ndarray
    weights: list[np.ndarray]
    names: list[str]
    method: str = "mvc"
    basis: Basis = Basis.ADDITIVE
    order: int = 1
    hull_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    meta: dict = field(default_factory=dict)


def default_stack(folder: str | os.PathLike = ".") -> Path:
    """``folder``'s ``DEFAULT_STACK``, where ``palette-decompose`` run there writes it.

    Raises
    ------
    InputError
        When it is not there (naming the command that makes it).
    """
    path = Path(folder) / DEFAULT_STACK
    if not path.is_file():
        raise InputError(f"no weight stack given and {path} does not exist: palette-decompose "
                         "of the images writes it there")
    return path


def frame_name(video: str, index: int) -> str:
    """The name of frame ``index`` of ``video`` in a stack: ``clip.mp4#000123``."""
    return f"{video}#{index:06d}"


def video_of(name: str) -> str | None:
    """The video that stack image ``name`` is a frame of (``frame_name``); None for an image."""
    return name.split("#")[0] if "#" in name else None


def is_zarr(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a Zarr store (``NAME.zarr``, an fsspec URL, or a folder not
    named ``.npz``): a suffix decides the format before what lies at the path does."""
    text = str(path).rstrip("/")
    if text.lower().endswith(".npz"):
        return False
    return text.endswith(".zarr") or "://" in text or Path(path).is_dir()


def check_names(names: list[str], source: str) -> None:
    """InputError unless every name is a distinct, non-empty relative path without ``..``
    or NUL: names become output paths (``folders.inside`` checks those again)."""
    seen = set()
    for name in names:
        parts = PurePosixPath(name).parts
        if (not name or "\0" in name or name.startswith(("/", "\\")) or ".." in parts
                or "\\" in name or name in seen):
            raise InputError(f"{source}: image name {name!r} is not a distinct relative path")
        seen.add(name)


def check_meta(meta, names: list[str], source: str) -> None:
    """InputError unless ``meta`` is a JSON object whose ``videos`` (if any) maps videos of
    the stack (names ``clip.mp4`` of frames ``clip.mp4#000123``) to frame rates in
    (0, ``MAX_FPS``]: recolouring encodes them."""
    if not isinstance(meta, dict):
        raise InputError(f"{source}: meta must be a JSON object")
    videos = meta.get("videos", {})
    if not isinstance(videos, dict):
        raise InputError(f"{source}: meta videos must map videos to frame rates")
    sources = {video_of(name) for name in names} - {None}
    for video, fps in videos.items():
        if video not in sources:
            raise InputError(f"{source}: meta videos names {video!r}, which has no frames")
        if (isinstance(fps, bool) or not isinstance(fps, (int, float))
                or not 0 < fps <= MAX_FPS):
            raise InputError(f"{source}: frame rate of {video} must be in (0, {MAX_FPS:g}], "
                             f"got {fps!r}")


def check_dtype(dtype: str) -> None:
    """InputError unless ``dtype`` is a storage type of stack weights (float32, float16)."""
    if dtype not in ("float32", "float16"):
        raise InputError(f"dtype must be float32 or float16, got {dtype!r}")


def stored_weights(weights: np.ndarray, dtype: str) -> np.ndarray:
    """(H, W, K) weights in the storage type; float16 rounding residuals go to each pixel's
    largest weight, so that sums stay within ``FLOAT16_SUM_TOL`` of one."""
    if dtype != "float16":
        return weights.astype(dtype, copy=False)
    rounded = weights.astype(np.float16)
    residual = 1.0 - rounded.astype(np.float32).sum(-1, keepdims=True)
    largest = np.argmax(weights, axis=-1)[..., None]
    corrected = np.take_along_axis(rounded, largest, -1).astype(np.float32) + residual
    np.put_along_axis(rounded, largest, corrected.astype(np.float16), -1)
    return rounded
