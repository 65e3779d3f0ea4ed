"""sRGB <-> HCL (polar CIE L*a*b*, i.e. LCh(ab), D65) through colour-science.

HCL arrays are channels-last ``(..., 3)`` in the order of the name: hue in
degrees [0, 360), chroma and lightness in CIE L*a*b* units (L in [0, 100]).

The sRGB matrices are derived from the primaries and white point, so that the
two directions are exact inverses (about 1e-15) and greys have zero chroma;
colour-science's default XYZ -> sRGB matrix is the standard's rounded one, whose
round trip is off by 3e-4 and which would make harmonisation drift.
"""

from __future__ import annotations

import colour
import numpy as np

from palette_core.constants import GAMUT_TOL

_D65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
_SRGB = colour.RGB_COLOURSPACES["sRGB"].copy()
_SRGB.use_derived_transformation_matrices(True)


def srgb_to_hcl(rgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] -> HCL.

    Parameters
    ----------
    rgb : (..., 3) float

    Returns
    -------
    (..., 3) float64
        Hue in degrees [0, 360), chroma, lightness.

    Examples
    --------
    >>> np.round(srgb_to_hcl([1.0, 0.0, 0.0]), 1).tolist()
    [40.0, 104.6, 53.2]
    """
    with colour.domain_range_scale("reference"):
        lab = colour.XYZ_to_Lab(_srgb_to_xyz(np.asarray(rgb, np.float64)), _D65)
        lightness, chroma, hue = np.moveaxis(colour.Lab_to_LCHab(lab), -1, 0)
    return np.stack([np.mod(hue, 360.0), chroma, lightness], axis=-1)


def hcl_to_srgb(hcl: np.ndarray) -> np.ndarray:
    """HCL -> sRGB, not clipped: channels outside [0, 1] mean out of gamut.

    Parameters
    ----------
    hcl : (..., 3) float
        Hue in degrees, chroma, lightness.

    Returns
    -------
    (..., 3) float64
    """
    hue, chroma, lightness = np.moveaxis(np.asarray(hcl, np.float64), -1, 0)
    with colour.domain_range_scale("reference"):
        lab = colour.LCHab_to_Lab(np.stack([lightness, chroma, hue], axis=-1))
        xyz = colour.Lab_to_XYZ(lab, _D65)
        return colour.XYZ_to_RGB(xyz, _SRGB, _D65, None, apply_cctf_encoding=True)


def _srgb_to_xyz(rgb: np.ndarray) -> np.ndarray:
    return colour.RGB_to_XYZ(rgb, _SRGB, _D65, None, apply_cctf_decoding=True)


def in_srgb_gamut(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) -> (...) bool: every channel within [0, 1] up to ``GAMUT_TOL``."""
    rgb = np.asarray(rgb)
    return ((rgb >= -GAMUT_TOL) & (rgb <= 1 + GAMUT_TOL)).all(axis=-1)


def hcl_to_srgb_in_gamut(hcl: np.ndarray, iterations: int = 60) -> np.ndarray:
    """HCL -> sRGB, bringing out-of-gamut colours back by lowering chroma only.

    Hue and lightness are kept; the chroma becomes the largest in gamut, found by
    bisection (the grey of the same lightness, chroma 0, is always in gamut).

    Parameters
    ----------
    hcl : (..., 3) float
        Lightness in [0, 100].
    iterations : int
        Bisection steps; 60 resolve the chroma to ``C * 2**-60``.

    Returns
    -------
    (..., 3) float64 in [0, 1]

    Examples
    --------
    >>> rgb = hcl_to_srgb_in_gamut([140.0, 150.0, 60.0])   # far too saturated a green
    >>> bool(in_srgb_gamut(rgb)), np.round(srgb_to_hcl(rgb)[[0, 2]], 6).tolist()
    (True, [140.0, 60.0])
    """
    hcl = np.array(hcl, np.float64)
    rgb = hcl_to_srgb(hcl)
    outside = ~in_srgb_gamut(rgb)
    if outside.any():
        target = hcl[outside]
        low, high = np.zeros(len(target)), target[:, 1].copy()
        for _ in range(iterations):
            middle = 0.5 * (low + high)
            target[:, 1] = middle
            fits = in_srgb_gamut(hcl_to_srgb(target))
            low, high = np.where(fits, middle, low), np.where(fits, high, middle)
        target[:, 1] = low
        rgb[outside] = hcl_to_srgb(target)
    return np.clip(rgb, 0.0, 1.0)
