"""Fitting a hue template to a palette: the weighted hue-distance cost and its minimiser.

The cost of template T at rotation alpha is (Tan, Echevarria, Gingold 2018)

    E(alpha) = sum_i W_i * L_i * C_i * |h_i - nearest axis of T(alpha)|,

hue differences taken on the circle, W_i the palette colour's share of all
weights. Achromatic colours (chroma below ``ACHROMATIC_CHROMA``) are left out.
Each term is piecewise linear in alpha with slopes +-W_i L_i C_i, so E is too,
and its minimum lies at a kink where an axis passes through a palette hue:
alpha = h_i - offset_j. ``fit_template`` evaluates E at all K * A such angles,
which finds the global minimum exactly (no sweep step, no local refinement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from palette_core.basis import term_multiplicities
from palette_core.constants import ACHROMATIC_CHROMA
from palette_core.stack import WeightStack

from .templates import TEMPLATES, Template

#: Costs within this relative margin of the minimum tie; the smallest angle wins.
_TIE_RTOL = 1e-9


@dataclass(frozen=True)
class TemplateFit:
    """A template at its best rotation: ``alpha`` in [0, template.period), degrees."""

    template: Template
    alpha: float
    cost: float

    @property
    def axes(self) -> np.ndarray:
        """(A,) axis hues in degrees."""
        return self.template.axes(self.alpha)


def hue_offset(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Signed circular difference ``target - source`` in degrees, in [-180, 180).

    Examples
    --------
    >>> hue_offset(350.0, 10.0).item(), hue_offset(10.0, 350.0).item()
    (20.0, -20.0)
    """
    return np.mod(np.asarray(target, np.float64) - source + 180.0, 360.0) - 180.0


def is_chromatic(hcl: np.ndarray) -> np.ndarray:
    """(..., 3) HCL -> (...) bool: chroma at least ``ACHROMATIC_CHROMA``."""
    return np.asarray(hcl)[..., 1] >= ACHROMATIC_CHROMA


def nearest_axis_offsets(hues: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Signed change moving each hue onto its nearest axis: hues (K,), axes (..., A) -> (..., K)."""
    offsets = hue_offset(np.asarray(hues)[:, None], np.asarray(axes)[..., None, :])  # (..., K, A)
    nearest = np.abs(offsets).argmin(axis=-1)
    return np.take_along_axis(offsets, nearest[..., None], axis=-1)[..., 0]


def template_cost(
    hcl: np.ndarray, shares: np.ndarray, template: Template, alpha: float | np.ndarray
) -> np.ndarray:
    """The fitting cost E(alpha).

    Parameters
    ----------
    hcl : (K, 3) float
        Palette in HCL.
    shares : (K,) float
        Each palette colour's share of all weights.
    template : Template
    alpha : float or (...) float
        Rotation angles in degrees.

    Returns
    -------
    (...) float64
    """
    hcl = np.asarray(hcl, np.float64)
    importance = np.where(is_chromatic(hcl), shares * hcl[:, 1] * hcl[:, 2], 0.0)
    distance = np.abs(nearest_axis_offsets(hcl[:, 0], template.axes(alpha)))  # (..., K)
    return (distance * importance).sum(axis=-1)


def fit_template(hcl: np.ndarray, shares: np.ndarray, template: Template) -> TemplateFit:
    """The rotation of ``template`` with the least cost (exact; see the module docstring).

    A palette without chromatic colours fits every rotation at cost 0; alpha is 0.

    Examples
    --------
    >>> hcl = np.array([[10.0, 50, 50], [200.0, 50, 50]])
    >>> fit = fit_template(hcl, np.array([0.5, 0.5]), TEMPLATES["complementary"])
    >>> round(fit.alpha, 6), round(fit.cost, 6)
    (10.0, 12500.0)
    """
    hcl = np.asarray(hcl, np.float64)
    hues = hcl[is_chromatic(hcl), 0]
    if hues.size == 0:
        return TemplateFit(template, 0.0, 0.0)
    candidates = np.mod(hues[:, None] - np.array(template.offsets), template.period).ravel()
    costs = template_cost(hcl, shares, template, candidates)
    ties = costs <= costs.min() * (1 + _TIE_RTOL)
    best = np.flatnonzero(ties)[candidates[ties].argmin()]
    return TemplateFit(template, float(candidates[best]), float(costs[best]))


def fit_all_templates(hcl: np.ndarray, shares: np.ndarray) -> dict[str, TemplateFit]:
    """``fit_template`` for every template in ``TEMPLATES``, keyed by name."""
    return {name: fit_template(hcl, shares, template) for name, template in TEMPLATES.items()}


def palette_shares(stack: WeightStack) -> np.ndarray:
    """(K,) share of each palette colour in all weights of a stack, summing to one.

    Additive stacks sum each weight channel over every pixel. In a transport
    stack a term's weight counts once for each time a palette colour appears in
    its product (``v_i * v_j`` counts for i and for j; the constant term for none).
    A stack whose weights are all zero gives equal shares.
    """
    k = len(stack.palette)
    totals = sum(np.clip(w.reshape(-1, w.shape[-1]).astype(np.float64), 0, None).sum(axis=0)
                 for w in stack.weights)
    per_colour = totals @ term_multiplicities(k, stack.basis, stack.order)
    total = per_colour.sum()
    return per_colour / total if total > 0 else np.full(k, 1.0 / k)
