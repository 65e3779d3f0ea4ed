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
from numba import njit, prange

from palette_core.basis import Basis, basis_terms, n_terms
from palette_core.errors import InputError
from palette_core.stack import NpzReader

from ..edit.regions import Region
from .sh import sh_basis

SPLAT_FORMAT = "palette-splats/1"
BLOCK = 1024  # splats a numba thread takes at a time, its scratch allocated once


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
    standard deviations s (on a CPU in numba, forward and backward: ``_CpuCovariances``)."""
    if not quaternions.is_cuda:
        return _CpuCovariances.apply(quaternions, scales)
    rotation = rotation_matrices(quaternions)
    return (rotation * scales[:, None, :] ** 2) @ rotation.transpose(1, 2)


class _CpuCovariances(torch.autograd.Function):
    """``covariances`` on a CPU, where PyTorch's batched 3 x 3 products cost more than the
    arithmetic: ``_covariances_forward`` and its backward, in float64."""

    @staticmethod
    def forward(ctx, quaternions, scales):
        arrays = (quaternions.detach().double().numpy(), scales.detach().double().numpy())
        ctx.arrays = arrays
        out = np.empty((len(arrays[0]), 3, 3))
        _covariances_forward(*arrays, out)
        return torch.from_numpy(out).to(scales.dtype)

    @staticmethod
    def backward(ctx, grad):
        grad_quaternions, grad_scales = np.empty_like(ctx.arrays[0]), np.empty_like(ctx.arrays[1])
        _covariances_backward(*ctx.arrays, grad.double().numpy(), grad_quaternions, grad_scales)
        return (torch.from_numpy(grad_quaternions).to(grad.dtype),
                torch.from_numpy(grad_scales).to(grad.dtype))


@njit(cache=True, inline="always")
def _rotation(q, r):
    """Into ``r`` (3, 3) the rotation of quaternion ``q`` (w, x, y, z; any length); returns
    the unit quaternion and the length."""
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm
    r[0, 0], r[0, 1], r[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return w, x, y, z, norm


@njit(cache=True, parallel=True)
def _covariances_forward(quaternions, scales, out):
    """``out`` (S, 3, 3): R diag(s^2) R^T of each splat."""
    for block in prange(-(-len(quaternions) // BLOCK)):
        r = np.empty((3, 3))
        for s in range(block * BLOCK, min(len(quaternions), (block + 1) * BLOCK)):
            _rotation(quaternions[s], r)
            for k in range(3):
                for n in range(3):
                    out[s, k, n] = (r[k, 0] * scales[s, 0] ** 2 * r[n, 0]
                                    + r[k, 1] * scales[s, 1] ** 2 * r[n, 1]
                                    + r[k, 2] * scales[s, 2] ** 2 * r[n, 2])


@njit(cache=True, parallel=True)
def _covariances_backward(quaternions, scales, grad, grad_quaternions, grad_scales):
    """The gradients of ``_covariances_forward`` from ``grad`` (S, 3, 3): dL/dR = (G + G^T)
    R diag(s^2), dL/ds_j = 2 s_j (R^T G R)_jj, then through the rotation of the unit
    quaternion and its normalisation."""
    for block in prange(-(-len(quaternions) // BLOCK)):
        r, g = np.empty((3, 3)), np.empty((3, 3))
        for s in range(block * BLOCK, min(len(quaternions), (block + 1) * BLOCK)):
            w, x, y, z, norm = _rotation(quaternions[s], r)
            for j in range(3):
                total = 0.0
                for k in range(3):
                    for n in range(3):
                        total += r[k, j] * grad[s, k, n] * r[n, j]
                grad_scales[s, j] = 2.0 * scales[s, j] * total
            for k in range(3):
                for j in range(3):
                    total = 0.0
                    for n in range(3):
                        total += (grad[s, k, n] + grad[s, n, k]) * r[n, j]
                    g[k, j] = total * scales[s, j] ** 2
            dw = 2 * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0]
                      + x * g[2, 1])
            dx = 2 * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - 2 * x * g[1, 1] - w * g[1, 2]
                      + z * g[2, 0] + w * g[2, 1] - 2 * x * g[2, 2])
            dy = 2 * (-2 * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2]
                      - w * g[2, 0] + z * g[2, 1] - 2 * y * g[2, 2])
            dz = 2 * (-2 * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - 2 * z * g[1, 1]
                      + y * g[1, 2] + x * g[2, 0] + y * g[2, 1])
            along = w * dw + x * dx + y * dy + z * dz  # the unit quaternion's normalisation
            grad_quaternions[s, 0] = (dw - w * along) / norm
            grad_quaternions[s, 1] = (dx - x * along) / norm
            grad_quaternions[s, 2] = (dy - y * along) / norm
            grad_quaternions[s, 3] = (dz - z * along) / norm


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

