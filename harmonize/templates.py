"""The seven hue templates of Tan, Echevarria and Gingold (2018), as data.

Each template is a set of hue axes, given as offsets in degrees from the
rotation angle alpha. ``TEMPLATES`` maps the names to them; ``get_template``
validates a name.

References
----------
J. Tan, J. Echevarria, Y. Gingold. Palette-based image decomposition,
harmonization, and color transfer. arXiv:1804.01225, 2018.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from palette_core.errors import InputError


@dataclass(frozen=True)
class Template:
    """Hue axes ``alpha + offsets`` (degrees).

    Examples
    --------
    >>> TEMPLATES["triad"].axes(10.0).tolist()
    [10.0, 130.0, 250.0]
    >>> TEMPLATES["double-split"].period
    180.0
    """

    name: str
    offsets: tuple[float, ...]

    def axes(self, alpha: float | np.ndarray) -> np.ndarray:
        """(..., A) axis hues in [0, 360) for rotation angles ``alpha`` of shape (...)."""
        return np.mod(np.asarray(alpha, np.float64)[..., None] + np.array(self.offsets), 360.0)

    @property
    def period(self) -> float:
        """Smallest rotation in degrees that maps the axes onto themselves."""
        base = np.sort(self.axes(0.0))
        for step in sorted({360.0 / n for n in range(len(self.offsets), 0, -1)}):
            if np.allclose(np.sort(self.axes(step)), base):
                return step
        return 360.0


TEMPLATES: dict[str, Template] = {
    t.name: t
    for t in [
        Template("monochrome", (0.0,)),
        Template("complementary", (0.0, 180.0)),
        Template("single-split", (0.0, 150.0, 210.0)),
        Template("double-split", (-30.0, 30.0, 150.0, 210.0)),
        Template("triad", (0.0, 120.0, 240.0)),
        Template("square", (0.0, 90.0, 180.0, 270.0)),
        Template("analogous", (-30.0, 0.0, 30.0)),
    ]
}


def get_template(name: str) -> Template:
    """The template called ``name``.

    Raises
    ------
    InputError
        If there is none, listing the valid names.
    """
    try:
        return TEMPLATES[name]
    except KeyError:
        raise InputError(f"unknown template {name!r}; choose one of "
                         f"{', '.join(TEMPLATES)}") from None
