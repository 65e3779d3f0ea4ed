"""Local edits: an edited palette that applies inside a soft selection of each image only.

Recolouring is linear in the weights, so splitting each pixel's weights w by its selection
value m in [0, 1] and giving each part its own palette is exact, with no retraining and no
leak (docs/selections.md); several edits stack like layers (``recolor_local``):

    rgb = (m w) @ B(P_edit) + ((1 - m) w) @ B(P_orig) = rgb_orig + m w @ (B(P_edit) - B(P_orig))

where B is the basis (``basis.basis_terms``). Where m = 0 a pixel is exactly its
unedited reconstruction. A selection is one of:

- ``mask``: an image whose grey value (or alpha, when it has one) is m, one file for every
  image of the stack, or a folder with one per image named like it (any image suffix);
- ``colour``: the pixels whose weight for palette colour k (its first-order term, for
  transport weights) is at least ``threshold`` ("only this red");
- ``near``: the pixels whose unedited colour lies within ``distance`` of a colour (RGB in
  [0, 1], Euclidean).

``feather`` softens the selection's edge by a Gaussian of that many pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from .basis import Basis, basis_terms, weights_to_rgb
from .errors import InputError
from .folders import inside
from .io import IMAGE_SUFFIXES, load_image
from .stack import video_of


@dataclass(frozen=True)
class Selection:
    """Where an edit applies: exactly one of ``mask``, ``colour`` and ``near``."""

    mask: Path | None = None
    colour: int | None = None
    near: tuple[float, float, float] | None = None
    threshold: float = 0.5
    distance: float = 0.1
    feather: float = 0.0

    def __post_init__(self):
        if sum(x is not None for x in (self.mask, self.colour, self.near)) != 1:
            raise InputError("a selection is a mask, a palette colour or a colour to be near: "
                             "give exactly one")
        numbers = (self.threshold, self.distance, self.feather, *(self.near or ()))
        if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in numbers):
            raise InputError("selection threshold, distance, feather and colour must be finite")
        if self.feather < 0 or self.distance < 0:
            raise InputError("selection feather and distance cannot be negative")
        if self.mask is not None and not Path(self.mask).exists():
            raise InputError(f"mask {self.mask} does not exist")

    def check(self, k: int, longest: int | None = None) -> None:
        """InputError unless the selection fits a stack of ``k`` palette colours whose
        longest image side is ``longest`` pixels: its feather can be no wider (a Gaussian's
        kernel grows with its width)."""
        if self.colour is not None and not 0 <= self.colour < k:
            raise InputError(f"selected palette colour {self.colour} is not one of the "
                             f"palette's {k} (0 to {k - 1})")
        if longest is not None:
            self._check_feather(longest)

    def _check_feather(self, longest: int) -> None:
        if self.feather > longest:
            raise InputError(f"selection feather {self.feather:g} is wider than the images "
                             f"(at most {longest} pixels)")

    def values(self, name: str, weights: np.ndarray, rgb: np.ndarray,
               basis: Basis = Basis.ADDITIVE) -> np.ndarray:
        """(H, W) float64 m in [0, 1] for stack image ``name`` with (H, W, M) ``weights``
        in ``basis`` and its unedited (H, W, 3) ``rgb``.

        Raises
        ------
        InputError
            If the image has no mask in a mask folder, or its mask is not its size.
        """
        if self.mask is not None:
            m = _read_mask(self._mask_file(name), weights.shape[:2], name)
        elif self.colour is not None:
            channel = self.colour + (basis == Basis.TRANSPORT)  # after the constant term
            m = (weights[..., channel] >= self.threshold).astype(np.float64)
        else:
            offset = rgb - np.asarray(self.near)
            m = (np.einsum("...c,...c->...", offset, offset) <= self.distance ** 2
                 ).astype(np.float64)
        if not self.feather:
            return m
        self._check_feather(max(m.shape))
        return _feathered(m, self.feather)

    def _mask_file(self, name: str) -> Path:
        mask = Path(self.mask)
        if mask.is_file():
            return mask
        stem = name if video_of(name) else str(PurePosixPath(name).with_suffix(""))
        for suffix in IMAGE_SUFFIXES:
            candidate = inside(mask, stem + suffix)  # a stack's names cannot climb out
            if candidate.is_file():
                return candidate
        raise InputError(f"no mask for image {name} in {mask} (expected {stem}.png)")


@dataclass(frozen=True)
class LocalEdit:
    """An edited (K, 3) ``palette`` that applies inside ``selection``."""

    selection: Selection
    palette: np.ndarray


def recolor_local(weights: np.ndarray, palette: np.ndarray, edits: list[LocalEdit], name: str,
                  basis, order: int = 1) -> np.ndarray:
    """(H, W, 3) stack image ``name`` (its (H, W, M) ``weights``) recoloured with ``palette``
    outside every edit and with each edit's palette inside its selection.

    Edits stack like layers, a later one over the earlier ones: edit i gets the share
    s_i = m_i prod_{j > i} (1 - m_j) of each pixel's weights (the shares and what is left
    outside sum to one), so

        rgb = w @ B(P) + sum_i s_i w @ (B(P_i) - B(P)),

    which is exactly ``w @ B(P)`` where no selection reaches (module docstring).
    """
    outside = weights_to_rgb(weights, palette, basis, order)
    base = basis_terms(palette, basis, order)
    recoloured = uncovered = None  # uncovered: prod (1 - m_j) over the edits above
    for i, edit in enumerate(reversed(edits)):
        m = edit.selection.values(name, weights, outside, basis)
        share = m if uncovered is None else m * uncovered
        change = weights @ (basis_terms(edit.palette, basis, order) - base)
        change *= share[..., None]
        if recoloured is None:
            recoloured = change
        else:
            recoloured += change
        if i + 1 < len(edits):
            uncovered = 1 - m if uncovered is None else uncovered * (1 - m)
    if recoloured is None:
        return outside
    recoloured += outside  # adds 0 (or -0) where no selection reaches: exactly ``outside``
    return recoloured


def _feathered(m: np.ndarray, sigma: float) -> np.ndarray:
    """(H, W) ``m`` blurred by a Gaussian of ``sigma`` pixels (reflected at the image's
    border, cut at 4 sigma), computed only around the selected pixels, where it is not 0."""
    from scipy.ndimage import gaussian_filter  # here: an import every command would otherwise pay

    rows, columns = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    if not len(rows):
        return m
    reach = int(np.ceil(4 * sigma))  # gaussian_filter's own truncation
    box = (slice(max(rows[0] - reach, 0), rows[-1] + reach + 1),
           slice(max(columns[0] - reach, 0), columns[-1] + reach + 1))
    feathered = np.zeros_like(m)
    feathered[box] = np.clip(gaussian_filter(m[box], sigma), 0.0, 1.0)
    return feathered


def _read_mask(path: Path, size: tuple[int, int], name: str) -> np.ndarray:
    """(H, W) float64 in [0, 1]: the alpha of a mask that has one, else its grey value
    (ITU-R 601 luma, as Pillow's ``L``), read as every image is (``io.load_image``)."""
    image = load_image(path)
    height, width = image.pixels.shape[:2]
    if (height, width) != size:
        raise InputError(f"mask {path} is {width}x{height}, image {name} is "
                         f"{size[1]}x{size[0]}")
    if image.alpha is not None:
        return image.alpha.astype(np.float64)
    return np.clip(image.rgb @ np.array([0.299, 0.587, 0.114]), 0.0, 1.0)


def parse_near(text: str) -> tuple[float, float, float]:
    """``#rrggbb`` -> (3,) RGB in [0, 1]; InputError otherwise."""
    digits = text.lstrip("#")
    if len(digits) != 6 or any(c not in "0123456789abcdefABCDEF" for c in digits):
        raise InputError(f"colour to select near must be #rrggbb, got {text!r}")
    return tuple(int(digits[i:i + 2], 16) / 255.0 for i in (0, 2, 4))

