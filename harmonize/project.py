"""Projecting a palette onto a fitted template: hues move, lightness and chroma stay."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from palette_core.errors import InputError

from .fit import (
    TemplateFit,
    fit_all_templates,
    fit_template,
    is_chromatic,
    nearest_axis_offsets,
)
from .hcl import hcl_to_srgb_in_gamut, srgb_to_hcl
from .templates import get_template


@dataclass(frozen=True)
class Harmonization:
    """A harmonised palette and how it came about.

    Attributes
    ----------
    fit : TemplateFit
        The template at its fitted rotation, and the cost there.
    palette : (K, 3) float64
        The harmonised palette, sRGB in [0, 1].
    hcl_before, hcl_after : (K, 3) float64
        The palette before and after, in HCL.
    strength : float
    """

    fit: TemplateFit
    palette: np.ndarray
    hcl_before: np.ndarray
    hcl_after: np.ndarray
    strength: float


def project_palette(palette: np.ndarray, fit: TemplateFit, strength: float = 1.0) -> np.ndarray:
    """Move each chromatic palette hue ``strength`` of the way onto its nearest axis.

    Lightness and chroma are kept; a colour that leaves the sRGB gamut comes back
    by lowering its chroma at the same hue and lightness. Colours that do not
    move (achromatic ones, or all of them at strength 0) are returned bit for bit.

    Parameters
    ----------
    palette : (K, 3) float
        sRGB in [0, 1].
    fit : TemplateFit
    strength : float
        0 leaves the palette unchanged, 1 puts every chromatic hue on its axis.

    Returns
    -------
    (K, 3) float64 in [0, 1]

    Examples
    --------
    >>> from harmonize.templates import TEMPLATES
    >>> fit = TemplateFit(TEMPLATES["monochrome"], 30.0, 0.0)
    >>> moved = project_palette(np.array([[0.8, 0.3, 0.3], [0.5, 0.5, 0.5]]), fit)
    >>> np.round(srgb_to_hcl(moved)[0, 0], 6).item(), moved[1].tolist()
    (30.0, [0.5, 0.5, 0.5])
    """
    palette = np.asarray(palette, np.float64)
    hcl = srgb_to_hcl(palette)
    change = np.where(is_chromatic(hcl), strength * nearest_axis_offsets(hcl[:, 0], fit.axes), 0.0)
    moves = change != 0
    result = palette.copy()
    if moves.any():
        target = hcl[moves]
        target[:, 0] = np.mod(target[:, 0] + change[moves], 360.0)
        result[moves] = hcl_to_srgb_in_gamut(target)
    return result


def harmonize_palette(
    palette: np.ndarray, shares: np.ndarray, template: str = "best", strength: float = 1.0
) -> Harmonization:
    """Fit a hue template to a palette and project the palette onto it.

    Parameters
    ----------
    palette : (K, 3) float
        sRGB in [0, 1].
    shares : (K,) float
        Each colour's share of all weights (``palette_shares``).
    template : str
        A name in ``TEMPLATES``, or ``"best"`` for the one with the least cost.
    strength : float in [0, 1]

    Raises
    ------
    InputError
        For an unknown template, a strength outside [0, 1], or mismatched shapes.

    References
    ----------
    J. Tan, J. Echevarria, Y. Gingold. Palette-based image decomposition,
    harmonization, and color transfer. arXiv:1804.01225, 2018.
    """
    palette = np.asarray(palette, np.float64)
    shares = np.asarray(shares, np.float64)
    if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) == 0:
        raise InputError(f"palette must have shape (K, 3) with K >= 1, got {palette.shape}")
    if shares.shape != (len(palette),):
        raise InputError(f"shares must have shape ({len(palette)},), got {shares.shape}")
    check_strength(strength)
    hcl = srgb_to_hcl(palette)
    if template == "best":
        fit = min(fit_all_templates(hcl, shares).values(), key=lambda f: f.cost)
    else:
        fit = fit_template(hcl, shares, get_template(template))
    return harmonize_with_fit(palette, fit, strength)


def check_strength(strength: float) -> None:
    """InputError unless ``strength`` lies in [0, 1]."""
    if not 0.0 <= strength <= 1.0:
        raise InputError(f"strength must lie in [0, 1], got {strength}")


def harmonize_with_fit(palette: np.ndarray, fit: TemplateFit, strength: float) -> Harmonization:
    """Project ``palette`` (K, 3) onto an already fitted template; no validation."""
    harmonized = project_palette(palette, fit, strength)
    return Harmonization(fit, harmonized, srgb_to_hcl(palette), srgb_to_hcl(harmonized), strength)
