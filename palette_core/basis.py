"""The weight basis: what colour each weight channel stands for (docs/formats.md).

An image is ``weights @ basis_terms(palette, basis, order)``. Two bases exist:

- ``Basis.ADDITIVE``: M = K channels, one per palette colour; the weights of a
  pixel are non-negative and sum to one (``palette-decompose``).
- ``Basis.TRANSPORT``: the terms of the light-transport polynomial in the K
  palette albedos up to degree ``order`` (PaletteNeRF, Sec. 5.2): the constant
  term, then v_1..v_K, then the products v_i * v_j (i <= j) in lexicographic
  order, and so on; M = C(K + order, order) (``nerf-stage simulate``).
"""

from __future__ import annotations

from collections import Counter
from enum import StrEnum
from itertools import combinations_with_replacement
from math import comb

import numpy as np

from .errors import InputError


class Basis(StrEnum):
    """How weight channels combine palette colours; the values are the stack's ``basis`` key."""

    ADDITIVE = "additive"
    TRANSPORT = "transport"

    @classmethod
    def parse(cls, name: str) -> Basis:
        """The basis called ``name``; InputError naming the valid ones otherwise."""
        try:
            return cls(name)
        except ValueError:
            raise InputError(f"basis must be one of {', '.join(cls)}, got {name!r}") from None


def n_terms(k: int, basis: Basis, order: int = 1) -> int:
    """Number of weight channels M for K palette colours (C(K + n, n) for transport order n).

    Examples
    --------
    >>> n_terms(4, Basis.ADDITIVE), n_terms(4, Basis.TRANSPORT, 2)
    (4, 15)
    """
    return k if basis == Basis.ADDITIVE else comb(k + order, order)


#: Most weight channels a basis may have (a transport order of 6 for 8 colours is 3003): a
#: file that declares more is refused before anything is allocated.
MAX_TERMS = 4096


def check_basis(k: int, basis: Basis, order, source: str) -> int:
    """M, the channels of ``basis`` for K colours at ``order``, after checking that ``order``
    is an integer >= 1 (1 for additive) and M at most ``MAX_TERMS``.

    Raises
    ------
    InputError
        Naming ``source``.
    """
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise InputError(f"{source}: order must be an integer >= 1, got {order!r}")
    if basis == Basis.ADDITIVE and order != 1:
        raise InputError(f"{source}: an additive stack has order 1, got {order}")
    m = n_terms(k, basis, int(order))
    if m > MAX_TERMS:
        raise InputError(f"{source}: {k} colours at transport order {order} would need {m} "
                         f"channels, more than {MAX_TERMS}")
    return m


def transport_terms(k: int, order: int) -> list[tuple[int, ...]]:
    """Palette indices multiplied in each transport term, in basis order.

    Examples
    --------
    >>> transport_terms(2, 2)
    [(), (0,), (1,), (0, 0), (0, 1), (1, 1)]
    """
    return [
        combo
        for degree in range(order + 1)
        for combo in combinations_with_replacement(range(k), degree)
    ]


def term_multiplicities(k: int, basis: Basis, order: int = 1) -> np.ndarray:
    """(M, K) how often palette colour i appears in term m (the identity for additive).

    Examples
    --------
    >>> term_multiplicities(2, Basis.TRANSPORT, 2).tolist()
    [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 0.0], [1.0, 1.0], [0.0, 2.0]]
    """
    if basis == Basis.ADDITIVE:
        return np.eye(k)
    counts = np.zeros((n_terms(k, basis, order), k))
    for m, combo in enumerate(transport_terms(k, order)):
        for i, n in Counter(combo).items():
            counts[m, i] = n
    return counts


def transport_basis(palette: np.ndarray, order: int) -> np.ndarray:
    """(M, 3) terms of the light-transport polynomial in the palette colours.

    Examples
    --------
    >>> transport_basis(np.array([[0.5, 1, 1], [1, 0.5, 1]]), 2)[:, 0].tolist()
    [1.0, 0.5, 1.0, 0.25, 0.5, 1.0]
    """
    palette = np.asarray(palette, np.float64)
    terms = [
        np.prod(palette[list(combo)], axis=0) if combo else np.ones(3)
        for combo in transport_terms(len(palette), order)
    ]
    return np.array(terms)


def basis_terms(palette: np.ndarray, basis: Basis = Basis.ADDITIVE, order: int = 1) -> np.ndarray:
    """(M, 3) colour of each weight channel: the palette itself, or its transport terms."""
    palette = np.asarray(palette, np.float64)
    return palette if basis == Basis.ADDITIVE else transport_basis(palette, order)


def weights_to_rgb(
    weights: np.ndarray, palette: np.ndarray, basis: Basis = Basis.ADDITIVE, order: int = 1
) -> np.ndarray:
    """Recompose colours from weights: ``weights @ basis_terms(palette, basis, order)``.

    Parameters
    ----------
    weights : (..., M) float
    palette : (K, 3) float
    basis : Basis
    order : int
        Transport order (ignored for additive weights).

    Returns
    -------
    (..., 3) float64
        Colours, not clipped.
    """
    terms = basis_terms(palette, basis, order)
    if weights.shape[-1] != len(terms):
        raise InputError(f"weights have {weights.shape[-1]} channels, the palette gives "
                         f"{len(terms)} {basis} terms")
    return np.asarray(weights, np.float64) @ terms
