"""A folder of photos for structure from motion (``sfm``): which files are photos of one
capture (``list_photos``), the photos as COLMAP must see them (``upright``: turned by their
EXIF orientation, as every other command reads them) and the pairs matched
(``image_pairs``).
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import numpy as np
from PIL import Image

from palette_core.errors import InputError
from palette_core.folders import files_in
from palette_core.io import IMAGE_SUFFIXES, image_size, is_turned, load_image

MIN_PHOTOS = 3  # fewer cannot make a capture to train on
EXHAUSTIVE_UP_TO = 150  # photos matched pair by pair; more are matched sequentially
SEQUENTIAL_OVERLAP = 15
MATCHERS = ("auto", "exhaustive", "sequential")


def list_photos(folder: str | os.PathLike) -> list[str]:
    """Names of the photos in ``folder`` (its files, hidden ones aside), sorted.

    Raises
    ------
    InputError
        If ``folder`` is not a folder, holds fewer than ``MIN_PHOTOS`` files, a file that
        is not an image, a link out of it (``folders.files_in``), or images of different
        sizes.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder of photos")
    names = [p.name for p in files_in(folder, recursive=False) if not p.name.startswith(".")]
    if len(names) < MIN_PHOTOS:
        raise InputError(f"{folder} holds {len(names)} photo(s); structure from motion needs "
                         f"at least {MIN_PHOTOS}")
    sizes, strangers = {}, []
    for name in names:
        if not name.lower().endswith(IMAGE_SUFFIXES):
            strangers.append(name)
            continue
        size = image_size(folder / name)  # as load_image turns it; InputError for a stranger
        sizes.setdefault(size, []).append(name)
    if strangers:
        raise InputError(f"{folder} holds files that are not photos ({', '.join(strangers[:3])}"
                         f"{' ...' if len(strangers) > 3 else ''}): give a folder of photos only")
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h} ({group[0]})" for (w, h), group in sorted(sizes.items()))
        raise InputError(f"{folder} holds photos of different sizes: {listed}; one capture "
                         "needs one size")
    return names


def upright(photos: Path, names: list[str], folder: Path) -> tuple[Path, list[str]]:
    """``folder`` of the photos as ``load_image`` reads them, for COLMAP, which ignores EXIF
    orientation: a turned photo is written upright as ``NAME.png`` (lossless), the others
    linked as they are; and the names there. ``photos`` itself when none is turned."""
    turned = {name for name in names if is_turned(photos / name)}
    if not turned:
        return photos, names
    folder.mkdir()
    upright = []
    for name in names:
        if name in turned:
            image = load_image(photos / name)
            pixels = image.pixels if image.alpha is None else np.concatenate(
                [image.pixels, (image.alpha[..., None] * np.iinfo(image.pixels.dtype).max)
                 .round().astype(image.pixels.dtype)], -1)
            name += ".png"
            _write_png(pixels, folder / name)
        else:
            (folder / name).symlink_to((photos / name).resolve())
        upright.append(name)
    return folder, upright


def _write_png(pixels: np.ndarray, path: Path) -> None:
    """(H, W, 3 or 4) uint8 or uint16 pixels as a PNG of their bit depth."""
    if pixels.dtype == np.uint8:
        Image.fromarray(pixels).save(path)
        return
    import png

    height, width, planes = pixels.shape
    with open(path, "wb") as file:
        png.Writer(width, height, bitdepth=16, greyscale=False,
                   alpha=planes == 4).write(file, pixels.reshape(height, -1))


def image_pairs(names: list[str], matcher: str = "auto") -> list[tuple[str, str]]:
    """The pairs of photos to match (``matcher``: see the module docstring).

    Examples
    --------
    >>> len(image_pairs([f"{i}.png" for i in range(5)]))
    10
    >>> image_pairs([f"{i}.png" for i in range(40)], "sequential")[:2]
    [('0.png', '1.png'), ('0.png', '2.png')]
    """
    if matcher == "exhaustive" or (matcher == "auto" and len(names) <= EXHAUSTIVE_UP_TO):
        return list(itertools.combinations(names, 2))
    offsets = sorted(set(range(1, SEQUENTIAL_OVERLAP + 1))
                     | {2 ** k for k in range(len(names).bit_length())})
    return [(names[i], names[i + d]) for i in range(len(names)) for d in offsets
            if i + d < len(names)]
