"""The ``refined`` palette method: hull simplification, then a count-weighted refinement.

Hull simplification (``hull.py``) keeps every colour inside the palette polytope
but ignores how many pixels each colour covers, and the final clip to the RGB cube
cuts away whatever it cuts: on stitched sets of different photos it can drop a
colour that covers a whole photo. This method starts from the simplified hull and
minimises what the palette is for, the reconstruction error of the pixels,

    E(V) = sum_c n_c |c - P_V(c)|^2,    V in [0, 1]^(K x 3),

with n_c the pixel count of colour c and P_V(c) its closest point in the hull of
the palette V: mean value coordinates reproduce every colour inside the polytope
exactly (``mvc.py``), so only colours outside contribute. It alternates two exact
steps, as archetypal analysis does (Cutler and Breiman 1994):

- weights: W = the mean value coordinates of each colour's projection, which
  reconstruct P_V(c), the best any weights can do for this V;
- palette: V = argmin sum_c n_c |c - W_c V|^2 over the cube, a K-variable
  box-constrained quadratic per channel, solved exactly by an active-set method
  (``_box_qp``); a small pull towards the last palette keeps it well posed.

Both steps lower E, but slowly (each gains less than the last, linearly). So each
palette step is extrapolated, as Ang and Gillis (2019) do for NMF: it goes on past
the update V' by beta (V' - V), beta growing by half while that lowers E by the
tolerance and halving, back at V', when it does not. On the 63 palettes of
``bench_decompose.py`` this ends a quarter fewer steps at a 13 % lower RMSE (median;
docs/decisions/0001-refined-palette.md). A colour that falls inside the hull of the
others is re-seeded at the worst-explained colour. Then each palette colour is pulled
towards colours that really occur, so that it stays editable: towards
``COMMON_RADIUS`` (60 on 0-255) of the nearest common colour, one that covers
``COMMON_SHARE`` (0.05 %) of the pixels after binning, as far as that costs at
most ``NEAR_COMMON_COST`` of the RMSE. Fidelity comes first: a colour that a set
needs far from its common colours (the red of a flag, a star in a night sky)
stays where it is needed. Colours are
binned first (``BIN_BITS`` per channel, count-weighted means), so one iteration
costs milliseconds; the result is kept only if it explains every distinct colour
at least as well as the hull method's palette it started from.

References
----------
A. Cutler, L. Breiman. Archetypal analysis. Technometrics 36(4), 1994.
A. M. S. Ang, N. Gillis. Accelerating nonnegative matrix factorization algorithms using
extrapolation. Neural Computation 31(2), 2019.
J. Tan, J.-M. Lien, Y. Gingold. Decomposing images into layers via RGB-space
geometry. ACM TOG 36(1), 2017 (the initial palette).
"""

from __future__ import annotations

import numpy as np

from .hull import check_palette_size, extract_palette, simplified_hull
from .mvc import rgb_to_mvc_weights
from .polytope import Polytope, polytope_from_points, polytope_rmse

#: Bits per channel of the colour bins the refinement works on (32^3 bins).
BIN_BITS = 5
#: A bin covering at least this share of the pixels is a common colour.
COMMON_SHARE = 5e-4
#: Every palette colour lies within this distance (0-1 RGB; 60 on 0-255) of a common colour.
COMMON_RADIUS = 60 / 255
#: Weight of a pull towards the last palette, per unit of pixel share: it keeps the
#: palette step well posed for colours that explain few pixels.
ANCHOR_WEIGHT = 1e-4
#: Iterations stop when the binned RMSE (0-255) improves by less than this.
RMSE_STEP_TOL = 0.005
MAX_ITERATIONS = 100
#: Extrapolation of the palette steps (module docstring): its first factor beta, the
#: factor beta grows by while that pays, its largest value, and the factor it shrinks by
#: when not.
EXTRAPOLATION = 1.0
EXTRAPOLATION_GROWTH = 1.5
EXTRAPOLATION_MAX = 8.0
EXTRAPOLATION_SHRINK = 2.0
#: A palette colour is pulled towards the nearest common colour as long as the binned
#: RMSE rises by at most this share (the "equal within 2 %" of the benchmark).
NEAR_COMMON_COST = 0.02
#: With ``max_error``, palettes of up to this many colours are refined; larger ones are
#: the hull method's.
MAX_REFINED_K = 16


def refined_palette(colours: np.ndarray, counts: np.ndarray, k: int | None = 6,
                    max_error: float | None = None) -> Polytope:
    """The palette polytope that explains the pixels: see the module docstring.

    Parameters and returns are those of ``hull.extract_palette``, whose palette is
    the starting point; it is returned as it is when it explains every distinct
    colour at least as well (the refinement works on binned colours), when it is
    the whole hull, or when it is degenerate (a point, a segment, a polygon). With
    ``max_error``, palettes of 4, 5, ... colours are refined until one has an RMSE
    of at most ``max_error``, so that ``-k K`` and ``--max-error E`` give the same
    palette when they land on the same K; beyond ``MAX_REFINED_K`` colours the
    hull method's palette is taken.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> colours = rng.random((500, 3))
    >>> poly = refined_palette(colours, np.ones(500, int), k=5)
    >>> poly.vertices.shape, bool(((poly.vertices >= 0) & (poly.vertices <= 1)).all())
    ((5, 3), True)
    """
    k = check_palette_size(k, max_error)
    used = counts > 0
    colours, counts = colours[used], counts[used]
    if max_error is not None:
        return _smallest_within(colours, counts, k, max_error)
    hull = polytope_from_points(colours)
    start = simplified_hull(hull, k)
    if start.dim < 3 or len(hull.vertices) <= k:
        return start  # degenerate, or the whole hull: exact
    bins, shares = binned_colours(colours, counts)
    initial = start.vertices
    if len(initial) < k:  # the clip to the cube merged colours: add the worst-explained bins
        initial = _reseeded(start, k, bins, shares)
    refined = polytope_from_points(
        refine_palette(initial, bins, shares, common_colours(bins, shares)))
    if (len(refined.vertices) == k
            and polytope_rmse(colours, counts, refined) <= polytope_rmse(colours, counts, start)):
        return refined
    return start


def _smallest_within(colours, counts, k: int | None, max_error: float) -> Polytope:
    """The refined palette of the fewest colours whose RMSE is at most ``max_error``."""
    n_vertices = len(polytope_from_points(colours).vertices)
    largest = min(n_vertices if k is None else k, n_vertices, MAX_REFINED_K)
    for size in range(4, largest + 1):
        poly = refined_palette(colours, counts, size)
        if polytope_rmse(colours, counts, poly) <= max_error:
            return poly
    return extract_palette(colours, counts, k, max_error)


def binned_colours(colours: np.ndarray, counts: np.ndarray,
                   bits: int = BIN_BITS) -> tuple[np.ndarray, np.ndarray]:
    """Count-weighted mean colour (B, 3) and pixel share (B,) of each bin of a
    2^bits-per-channel grid that holds pixels."""
    used = counts > 0
    colours, counts = colours[used], counts[used]
    q = np.minimum((colours * (1 << bits)).astype(np.int64), (1 << bits) - 1)
    code = (q[:, 0] << (2 * bits)) | (q[:, 1] << bits) | q[:, 2]
    _, inverse = np.unique(code, return_inverse=True)
    totals = np.bincount(inverse, counts.astype(np.float64))
    means = np.stack([np.bincount(inverse, counts * colours[:, j]) for j in range(3)], 1)
    return means / totals[:, None], totals / totals.sum()


def common_colours(bins: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """(C, 3) bins covering at least ``COMMON_SHARE`` of the pixels (the most common bin
    when none does)."""
    common = bins[shares >= COMMON_SHARE]
    return common if len(common) else bins[[np.argmax(shares)]]


def refine_palette(palette: np.ndarray, bins: np.ndarray, shares: np.ndarray,
                   common: np.ndarray) -> np.ndarray:
    """Alternate weight and palette steps from ``palette`` (K, 3) on binned colours (and
    once more after swapping the least-used colour for the worst-explained bin), then
    pull each colour towards the nearest common colour while that costs at most
    ``NEAR_COMMON_COST`` of the binned RMSE (farthest colours first)."""
    palette, error = _alternate(palette, bins, shares)
    swapped, swapped_error = _alternate(_swapped(palette, bins, shares), bins, shares)
    if swapped_error < error:
        palette, error = swapped, swapped_error
    budget = error * (1 + NEAR_COMMON_COST) + 1e-9
    distance = _common_distance(palette, common)
    for i in np.argsort(-distance)[: np.count_nonzero(distance > COMMON_RADIUS)]:
        target = _near_common(palette[i], common)
        for t in (1.0, 0.75, 0.5, 0.25):
            moved = palette.copy()
            moved[i] += t * (target - palette[i])
            poly = polytope_from_points(moved)
            if len(poly.vertices) == len(palette) and polytope_rmse(bins, shares, poly) <= budget:
                palette = moved
                break
    return palette


def _alternate(palette, bins, shares) -> tuple[np.ndarray, float]:
    """Weight and extrapolated palette steps while the binned RMSE (0-255) falls by at least
    ``RMSE_STEP_TOL``; the best palette and its error."""
    k = len(palette)
    best, best_error = palette, np.inf
    beta, update = EXTRAPOLATION, None  # update: the last palette step, before extrapolation
    for _ in range(MAX_ITERATIONS):
        poly = polytope_from_points(palette)
        if len(poly.vertices) < k:
            poly = polytope_from_points(_reseeded(poly, k, bins, shares))
            if len(poly.vertices) < k:
                break
        palette = poly.vertices
        weights = rgb_to_mvc_weights(bins, poly)  # (B, K): reconstruct each projection
        residual = bins - weights @ palette
        error = 255.0 * np.sqrt(np.dot(shares, np.einsum("ij,ij->i", residual, residual)) / 3)
        if error > best_error - RMSE_STEP_TOL:
            if update is not None:  # the extrapolation did not pay: back to the update
                palette, update, beta = update, None, beta / EXTRAPOLATION_SHRINK
                continue
            if error < best_error:
                best, best_error = palette, error
            break
        best, best_error = palette, error
        update = _palette_step(weights, shares, bins, palette)
        palette = np.clip(update + beta * (update - palette), 0.0, 1.0)
        beta = min(beta * EXTRAPOLATION_GROWTH, EXTRAPOLATION_MAX)
    return best, best_error


def _common_distance(palette: np.ndarray, common: np.ndarray) -> np.ndarray:
    """(K,) distance of each palette colour to the nearest common colour."""
    return np.sqrt(((palette[:, None] - common[None]) ** 2).sum(-1)).min(axis=1)


def _near_common(colour: np.ndarray, common: np.ndarray) -> np.ndarray:
    """``colour`` (3,), moved onto the sphere of radius ``COMMON_RADIUS`` around the nearest
    common colour when it lies farther out (it stays in the cube)."""
    anchor = common[np.argmin(((colour - common) ** 2).sum(-1))]
    distance = np.linalg.norm(colour - anchor)
    return anchor + (colour - anchor) * min(1.0, COMMON_RADIUS / max(distance, 1e-300))


def _palette_step(weights, shares, bins, palette) -> np.ndarray:
    """argmin over the cube of sum_c s_c |c - W_c V|^2 + lam |V - V_prev|^2."""
    k = len(palette)
    weighted = weights * shares[:, None]
    a = weighted.T @ weights + ANCHOR_WEIGHT * np.eye(k)
    b = weighted.T @ bins + ANCHOR_WEIGHT * palette
    return np.stack([_box_qp(a, b[:, j], palette[:, j].copy()) for j in range(3)], axis=1)


def _box_qp(a: np.ndarray, b: np.ndarray, x: np.ndarray, low: float = 0.0,
            high: float = 1.0) -> np.ndarray:
    """argmin 1/2 x'Ax - b'x over the box [low, high]^K for positive definite A (K, K), from a
    feasible x, by the primal active-set method.

    Variables at a bound are held there; the others move towards the minimiser on
    their subspace until one meets a bound, which is then held too. At the
    subspace minimiser, the held variable whose gradient points most into the box
    is released; when none does, the KKT conditions hold and x is the minimiser.
    """
    held = (x <= low) | (x >= high)
    for _ in range(8 * len(x) + 8):
        free = ~held
        target = x.copy()
        target[free] = np.linalg.solve(a[np.ix_(free, free)],
                                       b[free] - a[np.ix_(free, held)] @ x[held])
        step = target - x
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(step > 0, (high - x) / step,
                            np.where(step < 0, (low - x) / step, np.inf))
        room[held] = np.inf
        blocking = int(np.argmin(room))
        if room[blocking] < 1:
            x = x + room[blocking] * step
            x[blocking] = high if step[blocking] > 0 else low
            held[blocking] = True
            continue
        x = target
        gradient = a @ x - b
        inward = held & (((x <= low) & (gradient < 0)) | ((x >= high) & (gradient > 0)))
        if not inward.any():
            break
        held[np.argmax(np.abs(gradient) * inward)] = False
    return np.clip(x, low, high)


def _swapped(palette: np.ndarray, bins: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """The palette with its least-used colour replaced by the worst-explained bin: a move
    that alternating steps cannot make (they only slide colours), tried once."""
    poly = polytope_from_points(palette)
    weights = rgb_to_mvc_weights(bins, poly)
    residual = bins - weights @ poly.vertices
    worst = np.argmax(shares * np.einsum("ij,ij->i", residual, residual))
    swapped = poly.vertices.copy()
    swapped[np.argmin(shares @ weights)] = bins[worst]
    return swapped


def _reseeded(poly: Polytope, k: int, bins: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """The polytope's vertices plus the worst-explained bins, K in all."""
    weights = rgb_to_mvc_weights(bins, poly)
    residual = bins - weights @ poly.vertices
    worst = np.argsort(-shares * np.einsum("ij,ij->i", residual, residual))
    return np.vstack([poly.vertices, bins[worst[: k - len(poly.vertices)]]])
