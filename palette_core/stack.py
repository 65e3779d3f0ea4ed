"""The weight stack: palette and per-image weights in one NPZ file (format v1).

See docs/formats.md, "The weight stack". The file loads with
``numpy.load(path, allow_pickle=False)``; ``read_stack`` validates every key and
names what is wrong.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .basis import Basis, n_terms
from .errors import InputError

FORMAT = "palette-weights/1"


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


def write_stack(stack: WeightStack, file: str | os.PathLike, dtype: str | None = None) -> None:
    """Write ``stack`` as NPZ format v1 to ``file`` (a path or a binary file object).

    ``dtype`` (float32 or float16) converts the weights; None keeps the first image's.
    """
    dtype = str(stack.weights[0].dtype) if dtype is None else dtype
    check_dtype(dtype)
    arrays = {
        "format": np.array(FORMAT),
        "palette": np.asarray(stack.palette, np.float32),
        "basis": np.array(str(stack.basis)),
        "order": np.array(stack.order, np.int64),
        "names": np.array(stack.names, dtype=str),
        "method": np.array(stack.method),
        "meta": np.array(json.dumps(stack.meta)),
    }
    if stack.basis == Basis.ADDITIVE:
        arrays["hull_faces"] = np.asarray(stack.hull_faces, np.int32).reshape(-1, 3)
    shapes = {w.shape for w in stack.weights}
    if len(shapes) == 1:
        arrays["weights"] = np.stack([w.astype(dtype, copy=False) for w in stack.weights])
    else:
        for i, w in enumerate(stack.weights):
            arrays[f"weights_{i:04d}"] = w.astype(dtype, copy=False)
    np.savez(file, **arrays)


def read_stack(path: str | os.PathLike) -> WeightStack:
    """Read and validate an NPZ weight stack.

    Raises
    ------
    InputError
        If the file is missing, not an NPZ, or any key is absent or malformed
        (the message names the key).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"weight stack {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path} is not a readable NPZ weight stack: {exc}") from None

    def need(key: str) -> np.ndarray:
        if key not in data:
            raise InputError(f"{path}: missing key {key!r} (is it a {FORMAT} stack?)")
        return data[key]

    def text(key: str) -> str:
        value = need(key)
        if value.ndim != 0 or value.dtype.kind != "U":
            raise InputError(f"{path}: key {key!r} must be a string")
        return str(value)

    if text("format") != FORMAT:
        raise InputError(f"{path}: format is {text('format')!r}, expected {FORMAT!r}")
    palette = need("palette")
    if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) == 0:
        raise InputError(f"{path}: palette must have shape (K, 3), got {palette.shape}")
    if not np.isfinite(palette).all() or palette.min() < 0 or palette.max() > 1:
        raise InputError(f"{path}: palette values must lie in [0, 1]")
    try:
        basis = Basis.parse(text("basis"))
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    order = need("order")
    if order.ndim != 0 or order.dtype.kind not in "iu" or order < 1:
        raise InputError(f"{path}: order must be an integer >= 1, got {order}")
    order = int(order)
    if basis == Basis.ADDITIVE and order != 1:
        raise InputError(f"{path}: an additive stack has order 1, got {order}")
    names = need("names")
    if names.ndim != 1 or names.dtype.kind != "U":
        raise InputError(f"{path}: names must be a 1-D array of strings")
    if "weights" in data:
        weights = list(data["weights"])
        if data["weights"].ndim != 4:
            raise InputError(f"{path}: weights must have shape (N, H, W, M), "
                             f"got {data['weights'].shape}")
    else:
        weights = [need(f"weights_{i:04d}") for i in range(len(names))]
    if len(weights) != len(names):
        raise InputError(f"{path}: {len(names)} names but {len(weights)} weight images")
    m = n_terms(len(palette), basis, order)
    for name, w in zip(names, weights):
        if w.ndim != 3 or w.shape[2] != m or w.dtype not in (np.float32, np.float16):
            raise InputError(f"{path}: weights of {name} must be float32/float16 of shape "
                             f"(H, W, {m}), got {w.dtype} {w.shape}")
    hull_faces = np.zeros((0, 3), np.int32)
    if basis == Basis.ADDITIVE:
        hull_faces = need("hull_faces")
        if hull_faces.ndim != 2 or hull_faces.shape[1] != 3 or hull_faces.dtype.kind not in "iu":
            raise InputError(f"{path}: hull_faces must be integers of shape (F, 3)")
        if hull_faces.size and (hull_faces.min() < 0 or hull_faces.max() >= len(palette)):
            raise InputError(f"{path}: hull_faces index outside the palette")
    try:
        meta = json.loads(text("meta"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: meta is not valid JSON: {exc}") from None
    return WeightStack(palette.astype(np.float32), weights, names.tolist(), text("method"),
                       basis, order, hull_faces.astype(np.int32), meta)


def check_dtype(dtype: str) -> None:
    """InputError unless ``dtype`` is a storage type of stack weights (float32, float16)."""
    if dtype not in ("float32", "float16"):
        raise InputError(f"dtype must be float32 or float16, got {dtype!r}")
