"""Gaussians with palette weights and their file (format ``palette-splats/1``,
docs/formats.md): recolouring stays ``weights @ basis`` per splat (docs/splats.md).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from palette_core.basis import Basis, basis_terms, n_terms
from palette_core.errors import InputError
from palette_core.stack import NpzReader

from ..edit.regions import Region
from .sh import sh_basis

SPLAT_FORMAT = "palette-splats/1"


@dataclass
class Splats:
    """Gaussians with palette weights.

    Attributes
    ----------
    centres : (S, 3) float32
        World positions.
    scales : (S, 3) float32
        Standard deviations along the axes of ``rotations``.
    rotations : (S, 4) float32
        Unit quaternions (w, x, y, z), local to world.
    opacities : (S,) float32
        Peak opacity in (0, 1).
    weights : (S, M) float32
        Palette weights of each splat's light (summing to one for the additive basis).
    palette : (K, 3) float64
    basis : Basis
    order : int
    background : (3,) float64
    source : dict
        The run it was baked from: its folder, checkpoint iteration and training time, the
        cell size, the views used.
    residual : (S, B - 1, M) float32 or None
        The weights' view-dependent residual in spherical harmonics of degrees 1 and up
        (``sh.sh_basis``; a splat run's; summing to zero over the channels for the additive
        basis); None for a bake, which is diffuse.
    offset : (S, 3) float32 or None
        What the palette does not explain of each splat's colour, added to it whatever the
        palette: a splat file's own colour less ``weights @ palette``, so that an edit
        changes each colour by ``weights @ (P' - P)`` (docs/splat_files.md); None for a
        bake or a run.
    """

    centres: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray
    opacities: np.ndarray
    weights: np.ndarray
    palette: np.ndarray
    basis: Basis
    order: int
    background: np.ndarray
    source: dict
    residual: np.ndarray | None = None
    offset: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.centres)

    def covariances(self) -> np.ndarray:
        """(S, 3, 3) float64 world covariances R diag(s^2) R^T."""
        return covariances(torch.as_tensor(self.rotations, dtype=torch.float64),
                           torch.as_tensor(self.scales, dtype=torch.float64)).numpy()

    def colours(self, palette: np.ndarray | None = None, regions: Sequence[Region] = (),
                weights: np.ndarray | None = None) -> np.ndarray:
        """(S, 3) float32 colour of every splat for ``palette`` (the run's by default); with
        ``regions``, only the splats whose centres are inside one take it. ``weights`` (S, M)
        are those to colour: ``view_weights(eye)`` for a camera at ``eye``, the editable
        weights by default."""
        palette = self.palette if palette is None else np.asarray(palette, np.float64)
        weights = self.weights if weights is None else weights
        terms = basis_terms(palette, self.basis, self.order).astype(np.float32)
        colours = weights @ terms
        if self.offset is not None:
            colours += self.offset
        colours = np.clip(colours, 0, 1)
        if regions:
            outside = self._outside(regions)
            colours[outside] = self.colours(weights=weights)[outside]
        return colours

    def view_weights(self, eye: np.ndarray | None = None) -> np.ndarray:
        """(S, M) float32 each splat's weights seen from the world position ``eye`` (3,):
        the editable weights plus the residual in the direction from ``eye`` to the splat
        (``with_residual``); the editable weights alone without ``eye`` or residual."""
        if eye is None or self.residual is None:
            return self.weights
        directions = torch.nn.functional.normalize(
            torch.as_tensor(self.centres - np.asarray(eye, np.float32)), dim=1)
        degree = math.isqrt(self.residual.shape[1] + 1) - 1
        rest = torch.einsum("sb,sbm->sm", sh_basis(directions, degree)[:, 1:],
                            torch.as_tensor(self.residual))
        return with_residual(torch.as_tensor(self.weights), rest, self.basis).numpy()

    def rest_colours(self, palette: np.ndarray | None = None,
                     regions: Sequence[Region] = ()) -> np.ndarray | None:
        """(S, B - 1, 3) float32 spherical-harmonics coefficients of degrees 1 and up of
        every splat's colour for ``palette`` (``colours``' arguments): the residual through
        the basis. None without a residual."""
        if self.residual is None:
            return None
        palette = self.palette if palette is None else np.asarray(palette, np.float64)
        rest = self.residual @ basis_terms(palette, self.basis, self.order).astype(np.float32)
        if regions:
            outside = self._outside(regions)
            rest[outside] = self.rest_colours()[outside]
        return rest

    def _outside(self, regions: Sequence[Region]) -> np.ndarray:
        """(S,) bool: the splats whose centres are in none of ``regions``."""
        return ~np.any([region.contains(self.centres) for region in regions], axis=0)


def with_residual(weights: torch.Tensor, rest: torch.Tensor, basis: str) -> torch.Tensor:
    """(S, M) weights seen from one direction: the editable ``weights`` (S, M) plus the
    residual's values ``rest`` (S, M; summing to zero over the channels for the additive
    basis), clamped at zero and, for the additive basis, put back on the simplex."""
    weights = torch.clamp(weights + rest, min=0)
    if basis == Basis.ADDITIVE:
        return weights / weights.sum(1, keepdim=True).clamp(min=1e-12)
    return weights


def covariances(quaternions: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(S, 3, 3) R diag(s^2) R^T from (S, 4) quaternions (w, x, y, z; any length) and (S, 3)
    standard deviations s."""
    rotation = rotation_matrices(quaternions)
    return (rotation * scales[:, None, :] ** 2) @ rotation.transpose(1, 2)


def rotation_matrices(quaternions: torch.Tensor) -> torch.Tensor:
    """(S, 3, 3) rotation matrices of (S, 4) quaternions (w, x, y, z; any length)."""
    w, x, y, z = (quaternions / quaternions.norm(dim=1, keepdim=True)).T
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def matrix_quaternions(r: np.ndarray) -> np.ndarray:
    """(S, 3, 3) rotation matrices -> (S, 4) unit quaternions (w, x, y, z), w >= 0."""
    r = np.asarray(r, np.float64)
    trace = np.trace(r, axis1=1, axis2=2)
    candidates = np.stack([1 + trace, 1 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2],
                           1 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2],
                           1 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2]], 1)
    best = np.argmax(candidates, 1)  # the largest component, divided by without loss
    q = np.empty((len(r), 4))
    for k in range(4):
        at = best == k
        m, c = r[at], np.sqrt(np.maximum(candidates[at, k], 1e-12)) * 2  # 4 |q_k|
        if k == 0:
            q[at] = np.stack([c / 4, (m[:, 2, 1] - m[:, 1, 2]) / c, (m[:, 0, 2] - m[:, 2, 0]) / c,
                              (m[:, 1, 0] - m[:, 0, 1]) / c], 1)
        elif k == 1:
            q[at] = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / c, c / 4, (m[:, 0, 1] + m[:, 1, 0]) / c,
                              (m[:, 0, 2] + m[:, 2, 0]) / c], 1)
        elif k == 2:
            q[at] = np.stack([(m[:, 0, 2] - m[:, 2, 0]) / c, (m[:, 0, 1] + m[:, 1, 0]) / c, c / 4,
                              (m[:, 1, 2] + m[:, 2, 1]) / c], 1)
        else:
            q[at] = np.stack([(m[:, 1, 0] - m[:, 0, 1]) / c, (m[:, 0, 2] + m[:, 2, 0]) / c,
                              (m[:, 1, 2] + m[:, 2, 1]) / c, c / 4], 1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def write_splats(splats: Splats, path: str | os.PathLike) -> None:
    """Write a bake as NPZ format ``palette-splats/1``."""
    residual = {} if splats.residual is None else {"residual": splats.residual}
    np.savez(path, format=np.array(SPLAT_FORMAT), centres=splats.centres, scales=splats.scales,
             rotations=splats.rotations, opacities=splats.opacities, weights=splats.weights,
             palette=splats.palette, basis=np.array(str(splats.basis)),
             order=np.array(splats.order), background=splats.background,
             source=np.array(json.dumps(splats.source)), **residual)


def read_splats(path: str | os.PathLike) -> Splats:
    """Read and validate a bake.

    Raises
    ------
    InputError
        If the file is not a ``palette-splats/1`` NPZ, or a key is missing or malformed.
    """
    with NpzReader(Path(path), f"a splat bake ({SPLAT_FORMAT})") as npz:
        if npz.text("format") != SPLAT_FORMAT:
            raise InputError(f"{path} is not a splat bake (format {SPLAT_FORMAT})")
        arrays = {key: npz.array(key, "f") for key in ("centres", "scales", "rotations",
                                                       "opacities", "weights", "palette",
                                                       "background")}
        basis, order = Basis.parse(npz.text("basis")), int(npz.array("order", "iu"))
        source = npz.json("source")
        residual = npz.array("residual", "f") if "residual" in npz else None
    s = len(arrays["centres"])
    m = n_terms(len(arrays["palette"]), basis, order)
    shapes = {"centres": (s, 3), "scales": (s, 3), "rotations": (s, 4), "opacities": (s,),
              "weights": (s, m), "background": (3,)}
    if (any(arrays[k].shape != shape for k, shape in shapes.items())
            or arrays["palette"].ndim != 2 or arrays["palette"].shape[1:] != (3,)
            or not isinstance(source, dict)):
        raise InputError(f"{path}: the splats' arrays have the wrong shapes")
    if residual is not None:
        if (residual.ndim != 3 or residual.shape[0] != s or residual.shape[2] != m
                or residual.shape[1] not in (3, 8, 15)):
            raise InputError(f"{path}: the splats' residual must have shape (S, B - 1, M) "
                             "with B - 1 of 3, 8 or 15")
        arrays["residual"] = residual
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise InputError(f"{path}: the splats hold NaN or infinity")
    if (arrays["scales"] <= 0).any() or not ((arrays["opacities"] > 0)
                                             & (arrays["opacities"] < 1)).all():
        raise InputError(f"{path}: splat scales must be positive and opacities in (0, 1)")
    if (np.linalg.norm(arrays["rotations"], axis=1) < 1e-6).any():
        raise InputError(f"{path}: a splat rotation is not a quaternion")
    return Splats(arrays["centres"], arrays["scales"], arrays["rotations"], arrays["opacities"],
                  arrays["weights"], arrays["palette"].astype(np.float64), basis, order,
                  arrays["background"].astype(np.float64), source, residual)

