"""A splat file's palette and the weights of its splats: the splat stack (format
``palette-splat-stack/1``, docs/formats.md), and the recolouring it makes possible.

One palette for the splats as they are seen: each splat's degree-0 colour counts by how
much of a picture it covers (``coverage``), and the palette methods of ``palette_core``
take those colours and counts as they take an image's. Each splat's weights are its
colour's (a per-colour weight method: MVC by default).

A recolouring adds the change of the palette, ``weights @ (P' - P)``, to each splat's
degree-0 coefficients (docs/splat_files.md): the file's own colours are kept, not the
palette's reconstruction of them, so the unedited palette gives back every value of the
file bit for bit, and a splat outside a selection keeps its bytes. The view-dependent
terms (degrees 1 to 3) are ``RESIDUALS``: kept as they are, scaled with the colour, or
carried by the edit's local linear map of colours.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_writable
from palette_core.palette_file import palette_paths, write_palette_json
from palette_core.palettes import palette_polytope
from palette_core.selection import LocalEdit
from palette_core.stack import NpzReader
from palette_core.swatch import palette_swatch
from palette_core.weights import check_weight_method, colour_weights, palette_weights

from .fields import SH_C0, SplatFields, as_fields

SPLAT_STACK = "palette-splat-stack/1"
#: What happens to a splat's view-dependent colour (degrees 1 to 3) when its colour changes:
#: ``keep`` it; ``scale`` it channel by channel with the colour (c' / c, for c of at least
#: ``SCALE_FLOOR``); ``follow`` the edit's local linear map of colours
#: (``SplatStack.edit_maps``).
RESIDUALS = ("keep", "scale", "follow")
SCALE_FLOOR = 1 / 64
EDIT_STEP = 1 / 64
#: Knud Thomsen's exponent: an ellipsoid's surface ~ 4 pi ((ab^p + ac^p + bc^p) / 3)^(1/p).
_THOMSEN = 1.6075
_ARRAYS = ("means", "sh0", "shN", "opacities", "scales", "quats")


@dataclass
class SplatStack:
    """A splat file's splats with a palette and their weights.

    Attributes
    ----------
    fields : SplatFields
        The splats as the file holds them.
    palette : (K, 3) float64
    weights : (S, K) float32
        Each splat's weights of its degree-0 colour (summing to one).
    hull_faces : (F, 3) int32
        The palette's hull (a stack's, for computing weights of other colours).
    source : dict
        The file it came from, its format, the method and timings.
    """

    fields: SplatFields
    palette: np.ndarray
    weights: np.ndarray
    hull_faces: np.ndarray
    source: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.fields)

    def colours(self) -> np.ndarray:
        """(S, 3) float64 the splats' degree-0 colours in [0, 1]."""
        return np.clip(self.fields.colours(), 0, 1)

    def shares(self) -> np.ndarray:
        """(K,) each palette colour's share of what the splats cover (``coverage``),
        summing to one: what harmonisation weighs the hues by."""
        totals = coverage(self.fields) @ self.weights.astype(np.float64)
        return totals / totals.sum()

    def change(self, palette: np.ndarray, edits: list[LocalEdit] = ()) -> np.ndarray:
        """(S, 3) float64 each splat's change of colour for ``palette`` outside every edit
        and each edit's palette inside its selection (``change_of``)."""
        return change_of(self.weights, self.colours(), self.palette, palette, edits)

    def recoloured(self, palette: np.ndarray, edits: list[LocalEdit] = (),
                   residual: str = "follow", inside: np.ndarray | None = None) -> SplatFields:
        """The splats recoloured (``change``; only those of the (S,) bool mask ``inside``,
        when given): every splat whose colour does not change keeps its coefficients bit
        for bit, the others get ``sh0 + change / SH_C0`` and their view-dependent terms by
        ``residual`` (``RESIDUALS``)."""
        if residual not in RESIDUALS:
            raise InputError(f"the residual is one of {', '.join(RESIDUALS)}, not {residual}")
        change = self.change(palette, edits)
        moved = (change != 0).any(1) & (True if inside is None else inside)
        sh0, shN = self.fields.sh0.copy(), self.fields.shN.copy()  # noqa: N806
        sh0[moved] = self.fields.sh0[moved] + change[moved] / SH_C0
        if residual == "scale" and shN.shape[1]:
            before = np.maximum(self.colours()[moved], SCALE_FLOOR)
            after = np.maximum(np.clip(before + change[moved], 0, 1), SCALE_FLOOR)
            shN[moved] = self.fields.shN[moved] * (after / before)[:, None, :]
        elif residual == "follow" and shN.shape[1]:
            maps = self.edit_maps(palette, edits, moved)
            shN[moved] = np.einsum("sij,sbj->sbi", maps, self.fields.shN[moved])
        return self.fields.with_colour(sh0, shN)

    def edit_maps(self, palette: np.ndarray, edits: list[LocalEdit],
                  which: np.ndarray) -> np.ndarray:
        """(n, 3, 3) float64 the edit's local linear map of colours, d c' / d c with
        c' = c + change(c), at each splat of the (S,) mask ``which``: how a small colour
        variation about the splat's colour (its view dependence) follows the edit. Finite
        differences of ``EDIT_STEP`` (away from the cube's faces) through the stack's
        weight method, once for each colour of 8 bits a channel among them."""
        codes = np.round(self.colours()[which] * 255).astype(np.int64)
        unique, inverse = np.unique(codes @ np.array([1 << 16, 1 << 8, 1]), return_inverse=True)
        colours = np.stack([unique >> 16, (unique >> 8) & 255, unique & 255], 1) / 255.0
        method = self.source.get("method", "mvc")

        def change(c: np.ndarray) -> np.ndarray:
            weights = palette_weights(c, self.palette, self.hull_faces, method)
            return change_of(weights, c, self.palette, palette, edits)

        base = change(colours)
        maps = np.repeat(np.eye(3)[None], len(colours), 0)
        for k in range(3):
            step = np.where(colours[:, k] > 1 - EDIT_STEP, -EDIT_STEP, EDIT_STEP)
            shifted = colours.copy()
            shifted[:, k] += step
            maps[:, :, k] += (change(shifted) - base) / step[:, None]
        return maps[inverse]


def change_of(weights: np.ndarray, colours: np.ndarray, original: np.ndarray,
              palette: np.ndarray, edits: list[LocalEdit] = ()) -> np.ndarray:
    """(S, 3) float64 the change of (S, 3) ``colours`` of (S, K) ``weights`` over the
    ``original`` palette for ``palette`` outside every edit and each edit's palette inside
    its selection, stacked as ``palette_core.selection`` stacks them:
    ``w @ (P - P0) + sum_i s_i w @ (P_i - P)``."""
    weights = np.asarray(weights, np.float64)
    palette = np.asarray(palette, np.float64)
    change = weights @ (palette - original)
    shares = [edit.selection.values("splats", weights, colours) for edit in edits]
    for i, edit in enumerate(edits):
        share = shares[i] * np.prod([1 - m for m in shares[i + 1:]], axis=0)
        change += share[:, None] * (weights @ (np.asarray(edit.palette) - palette))
    return change


def coverage(fields: SplatFields) -> np.ndarray:
    """(S,) float64 how much of a picture each splat covers, averaged over directions: its
    opacity times its ellipsoid's mean projected area, a quarter of its surface (Cauchy),
    at one sigma (Thomsen's approximation of the surface)."""
    s = np.exp(fields.scales.astype(np.float64))
    pairs = (s[:, 0] * s[:, 1]) ** _THOMSEN + (s[:, 0] * s[:, 2]) ** _THOMSEN + (
        s[:, 1] * s[:, 2]) ** _THOMSEN
    area = np.pi * (pairs / 3) ** (1 / _THOMSEN)
    return area / (1 + np.exp(-fields.opacities.astype(np.float64)))


def decompose_splats(fields: SplatFields, k: int | None = 6, max_error: float | None = None,
                     method: str = "mvc", palette_method: str = "refined",
                     method_options: dict | None = None, palette_options: dict | None = None,
                     source: dict | None = None) -> SplatStack:
    """A palette for ``fields`` and every splat's weights (module docstring): the splats'
    colours, rounded to 8 bits a channel, counted by their ``coverage``; ``k``,
    ``max_error`` and the methods as ``palette_core.decompose`` takes them.

    Raises
    ------
    InputError
        If a method or option is unknown, or every splat is invisible.
    """
    method_options, palette_options = method_options or {}, palette_options or {}
    check_weight_method(method, method_options, stream=True)
    start = time.perf_counter()
    colours = np.clip(fields.colours(), 0, 1)
    codes = np.round(colours * 255).astype(np.int64) @ np.array([1 << 16, 1 << 8, 1])
    unique, inverse = np.unique(codes, return_inverse=True)
    counts = np.bincount(inverse, coverage(fields), len(unique))
    if not counts.sum() > 0:
        raise InputError("every splat is invisible (no opacity or no size): there are no "
                         "colours to take a palette from")
    distinct = np.stack([unique >> 16, (unique >> 8) & 255, unique & 255], 1) / 255.0
    poly = palette_polytope(distinct, counts / counts.sum() * len(fields), k, max_error,
                            palette_method, **palette_options)
    timings = {"palette": time.perf_counter() - start}
    start = time.perf_counter()
    weights = colour_weights(distinct, poly, method, **method_options)[inverse]
    timings["weights"] = time.perf_counter() - start
    return SplatStack(fields, poly.vertices.astype(np.float64), weights.astype(np.float32),
                      poly.faces.astype(np.int32),
                      {**(source or {}), "method": method, "palette_method": palette_method,
                       "k": k, "max_error": max_error, "timings": timings})


def write_splat_stack(stack: SplatStack, path: str | os.PathLike,
                      force: bool = False) -> list[Path]:
    """Write ``stack`` as NPZ ``palette-splat-stack/1`` with its palette swatch and JSON
    beside it (``palette_paths``), staged and published together. Returns the paths."""
    path = Path(path)
    if path.suffix != ".npz":
        raise InputError(f"a splat stack is written as .npz, got {path}")
    paths = [path, *palette_paths(path)]
    check_writable(paths, force)
    f = stack.fields
    extras = {f"extra_{i}": value for i, value in enumerate(f.extras.values())}
    with atomic_outputs(force) as stage:
        with open(stage(path), "wb") as out:
            np.savez(out, format=np.array(SPLAT_STACK), palette=stack.palette,
                     weights=stack.weights, hull_faces=stack.hull_faces,
                     source=np.array(json.dumps(stack.source)),
                     comments=np.array(json.dumps(f.comments)),
                     extra_names=np.array(json.dumps(list(f.extras))),
                     **{key: getattr(f, key) for key in _ARRAYS}, **extras)
        palette_swatch(stack.palette).save(stage(paths[1]), format="PNG")
        with open(stage(paths[2]), "w") as out:
            write_palette_json(out, stack.palette)
    return paths


def is_splat_stack(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an NPZ of format ``palette-splat-stack/1`` (read safely)."""
    path = Path(path)
    if path.suffix != ".npz" or not path.is_file():
        return False
    try:
        with NpzReader(path, "a splat stack") as npz:
            return "format" in npz and npz.text("format") == SPLAT_STACK
    except InputError:
        return False


def read_splat_stack(path: str | os.PathLike) -> SplatStack:
    """Read and check a splat stack.

    Raises
    ------
    InputError
        If it is not a ``palette-splat-stack/1`` NPZ, a key is missing or malformed, its
        splats are not ones a renderer can draw, or its weights are not on the simplex.
    """
    path = Path(path)
    with NpzReader(path, f"a splat stack ({SPLAT_STACK})") as npz:
        if npz.text("format") != SPLAT_STACK:
            raise InputError(f"{path} is not a splat stack (format {SPLAT_STACK})")
        arrays = {key: npz.array(key, "f") for key in (*_ARRAYS, "palette", "weights")}
        faces = npz.array("hull_faces", "iu")
        source, comments, names = npz.json("source"), npz.json("comments"), npz.json(
            "extra_names")
        if not (isinstance(source, dict) and isinstance(comments, list)
                and isinstance(names, list) and all(isinstance(c, str) for c in comments)
                and all(isinstance(n, str) for n in names)):
            raise InputError(f"{path}: the splat stack's source, comments or extras are "
                             "malformed")
        extras = {name: npz.array(f"extra_{i}", "fiu") for i, name in enumerate(names)}
    fields = as_fields(*(arrays[key] for key in _ARRAYS), comments=comments,
                       extras=extras).checked(str(path))
    palette, weights = arrays["palette"].astype(np.float64), arrays["weights"]
    k = len(palette)
    if (palette.ndim != 2 or palette.shape[1:] != (3,) or weights.shape != (len(fields), k)
            or any(e.shape != (len(fields),) for e in extras.values())
            or faces.ndim != 2 or (faces.size and (faces.shape[1] != 3 or faces.max() >= k))):
        raise InputError(f"{path}: the splat stack's arrays have the wrong shapes")
    if not (np.isfinite(palette).all() and np.isfinite(weights).all()
            and (weights >= -1e-4).all() and np.allclose(weights.sum(1), 1, atol=1e-3)):
        raise InputError(f"{path}: the splat stack's weights are not on the simplex")
    return SplatStack(fields, palette, weights, faces.astype(np.int32), source)
