"""Pictures of harmonisations: hue wheels and the template contact sheet.

A hue wheel places each palette colour at its HCL hue (0 degrees to the right,
counter-clockwise, as the a* and b* axes of CIE L*a*b*) and at a radius
proportional to its chroma, with a dot whose area grows with its share of the
weights. Template axes are drawn as spokes; a harmonised colour is joined to
where it came from.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from palette_core.palette_file import palette_to_hex

from .hcl import hcl_to_srgb_in_gamut

#: Chroma at the rim of the wheel; sRGB colours reach about 134 (blue).
_MAX_CHROMA = 140.0
#: The rim's colours: every hue at this chroma and lightness.
_RIM_CHROMA, _RIM_LIGHTNESS = 45.0, 70.0
_SUPERSAMPLE = 2


def hue_wheel(
    hcl_before: np.ndarray,
    shares: np.ndarray,
    hcl_after: np.ndarray | None = None,
    axes: np.ndarray = (),
    title: str = "",
    size: int = 320,
) -> Image.Image:
    """Draw palette hues on a hue wheel, with template axes and before -> after moves.

    Parameters
    ----------
    hcl_before : (K, 3) float
        Palette in HCL (hue degrees, chroma, lightness).
    shares : (K,) float
        Each colour's share of the weights (sets the dot size).
    hcl_after : (K, 3) float, optional
        The harmonised palette; each colour is drawn there, joined to its old place.
    axes : (A,) float
        Template axis hues in degrees.
    title : str
    size : int
        Width and height in pixels.

    Returns
    -------
    PIL.Image.Image
        RGB, ``size`` x ``size``.
    """
    s = size * _SUPERSAMPLE
    centre, radius = s / 2, 0.40 * s
    rim = _hue_rim(s, centre, radius)
    image = Image.fromarray(rim)
    draw = ImageDraw.Draw(image)
    for chroma in (35, 70, 105, 140):
        r = radius * chroma / _MAX_CHROMA
        draw.ellipse([centre - r, centre - r, centre + r, centre + r], outline="#d0d0d0",
                     width=_SUPERSAMPLE)

    def point(hue: float, chroma: float, reach: float | None = None) -> tuple[float, float]:
        r = radius * min(chroma, _MAX_CHROMA) / _MAX_CHROMA if reach is None else reach
        angle = np.deg2rad(hue)
        return centre + r * np.cos(angle), centre - r * np.sin(angle)

    for axis in np.atleast_1d(axes):
        draw.line([(centre, centre), point(axis, 0, 1.08 * radius)], fill="#303030",
                  width=2 * _SUPERSAMPLE)
    before_rgb = palette_to_hex(hcl_to_srgb_in_gamut(hcl_before))
    after = hcl_before if hcl_after is None else hcl_after
    after_rgb = palette_to_hex(hcl_to_srgb_in_gamut(after))
    for i in np.argsort(-np.asarray(shares)):  # large dots first, small ones on top
        dot = s * (0.018 + 0.05 * np.sqrt(shares[i]))
        old, new = point(*hcl_before[i, :2]), point(*after[i, :2])
        if hcl_after is not None and np.hypot(old[0] - new[0], old[1] - new[1]) > 1:
            draw.line([old, new], fill="#606060", width=_SUPERSAMPLE)
            draw.ellipse(_box(old, 0.6 * dot), fill=before_rgb[i], outline="#808080",
                         width=_SUPERSAMPLE)
        draw.ellipse(_box(new, dot), fill=after_rgb[i], outline="black", width=_SUPERSAMPLE)
    if title:
        draw.text((4 * _SUPERSAMPLE, 2 * _SUPERSAMPLE), title, fill="black",
                  font=ImageFont.load_default(size=13 * _SUPERSAMPLE))
    return image.resize((size, size), Image.LANCZOS)


def contact_sheet(
    cells: list[tuple[str, np.ndarray, Image.Image]], width: int = 256, columns: int = 4
) -> Image.Image:
    """Lay out labelled images, each above its hue wheel, in a grid.

    Parameters
    ----------
    cells : list of (label, (H, W, 3) float image in [0, 1], wheel image)
    width : int
        Width of one cell in pixels.
    columns : int

    Returns
    -------
    PIL.Image.Image
    """
    thumbs = [_thumbnail(image, width) for _, image, _ in cells]
    label_h, image_h = 22, max(t.height for t in thumbs)
    cell_h = label_h + image_h + width
    rows = -(-len(cells) // columns)
    sheet = Image.new("RGB", (columns * width, rows * cell_h), "white")
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=14)
    for n, ((label, _, wheel), thumb) in enumerate(zip(cells, thumbs)):
        x, y = (n % columns) * width, (n // columns) * cell_h
        draw.text((x + 6, y + 4), label, fill="black", font=font)
        sheet.paste(thumb, (x + (width - thumb.width) // 2, y + label_h))
        sheet.paste(wheel.resize((width, width), Image.LANCZOS), (x, y + label_h + image_h))
    return sheet


def _hue_rim(s: int, centre: float, radius: float) -> np.ndarray:
    """(s, s, 3) uint8: white, with a ring of every hue just outside ``radius``."""
    yy, xx = np.mgrid[0:s, 0:s] + 0.5
    distance = np.hypot(xx - centre, yy - centre)
    hue = np.mod(np.rad2deg(np.arctan2(centre - yy, xx - centre)), 360.0)
    image = np.full((s, s, 3), 255, np.uint8)
    image[distance <= radius] = 247
    ring = (distance > 1.02 * radius) & (distance <= 1.10 * radius)
    image[ring] = _rim_colours()[np.round(hue[ring]).astype(int) % 360]
    return image


@lru_cache(maxsize=1)
def _rim_colours() -> np.ndarray:
    """(360, 3) uint8: each whole hue at the rim's chroma and lightness, in gamut."""
    hcl = np.stack([np.arange(360.0), np.full(360, _RIM_CHROMA), np.full(360, _RIM_LIGHTNESS)],
                   axis=-1)
    return np.round(hcl_to_srgb_in_gamut(hcl) * 255).astype(np.uint8)


def _box(xy: tuple[float, float], r: float) -> list[float]:
    return [xy[0] - r, xy[1] - r, xy[0] + r, xy[1] + r]


def _thumbnail(rgb: np.ndarray, width: int) -> Image.Image:
    image = Image.fromarray(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    image.thumbnail((width - 8, width - 8), Image.LANCZOS)
    return image
