"""Image input: finding image files and decoding them.

Images are read with Pillow (PNG, JPEG, TIFF, BMP, WebP and whatever else it
knows); 16-bit RGB(A) PNG and TIFF, which Pillow reduces to 8 bits, are read with
pypng and tifffile instead. EXIF orientation is applied, greyscale and palette images
become RGB, an embedded colour profile other than sRGB is converted to sRGB (8-bit
images; littlecms through Pillow), and alpha is kept so that the palette can leave fully
transparent pixels out and training can composite them.

``load_image`` is the one reader of pixels: every command (``palette-decompose``, ``nerf-stage
poses`` and ``train``, the studio) sees the same pixels for the same file, and
``image_size`` gives the size those pixels have, from the header alone.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import InputError
from .folders import files_in

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")

#: Largest image decoded by default, in pixels (``--max-pixels``): 2^26, a 67 MP photo.
#: Decomposing one peaks near 100 bytes per pixel, so this stays within a few GB, and a
#: file whose header declares more is refused before anything is decoded.
DEFAULT_MAX_PIXELS = 1 << 26

# EXIF orientation tag -> numpy operation that undoes it (as PIL.ImageOps.exif_transpose).
_ORIENT = {
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.swapaxes(0, 1),
    6: lambda a: np.rot90(a, -1),
    7: lambda a: a[::-1, ::-1].swapaxes(0, 1),
    8: lambda a: np.rot90(a, 1),
}


@dataclass
class LoadedImage:
    """One decoded image.

    Attributes
    ----------
    name : str
        Path relative to the input root, with forward slashes.
    pixels : (H, W, 3) uint8 or uint16
        RGB values; the dtype gives the bit depth.
    opaque : (H, W) bool
        False where the pixel is fully transparent.
    alpha : (H, W) float32 in [0, 1], or None
        The file's alpha channel; None for an image without one (opaque).
    """

    name: str
    pixels: np.ndarray
    opaque: np.ndarray
    alpha: np.ndarray | None = None

    @property
    def rgb(self) -> np.ndarray:
        """(H, W, 3) float64 colours in [0, 1]."""
        return self.pixels / float(np.iinfo(self.pixels.dtype).max)


def find_images(inputs: list[str | os.PathLike],
                suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> tuple[Path, list[Path]]:
    """Expand files and folders (recursively, sorted) into the paths of files with
    ``suffixes`` (images by default).

    Returns the input root (the deepest folder holding every input) and the paths.

    Raises
    ------
    InputError
        If a path does not exist, a folder holds no image or a link out of it
        (``folders.files_in``).
    """
    if not inputs:
        raise InputError("no input given: name image files or folders")
    paths: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = files_in(item, suffixes=suffixes)
            if not found:
                raise InputError(f"no images ({', '.join(suffixes)}) found in folder {item}")
            paths.extend(found)
        elif item.is_file():
            paths.append(item)
        elif item.exists():
            raise InputError(f"input {item} is neither an image file nor a folder")
        else:
            raise InputError(f"input path does not exist: {item}")
    paths = list(dict.fromkeys(Path(os.path.abspath(p)) for p in paths))  # links keep names
    root = Path(os.path.commonpath([p.parent for p in paths]))
    return root, paths


class SizedFile(io.FileIO):
    """A file whose reads never ask for more than it holds: a decoder told a crafted chunk
    length (a PNG's IDAT of 2 GiB in a file of a few kilobytes) would otherwise allocate
    that length before reading."""

    def __init__(self, path: str | os.PathLike):
        super().__init__(path)
        self.size = os.fstat(self.fileno()).st_size

    def read(self, size: int | None = -1) -> bytes:
        if size is not None and size > 0:
            size = min(size, max(self.size - self.tell(), 0))
        return super().read(size)


@contextlib.contextmanager
def open_image(path: Path, max_pixels: int = DEFAULT_MAX_PIXELS):
    """Pillow's image of ``path``, its header checked against ``max_pixels`` before decoding.

    Raises
    ------
    InputError
        If the file is not an image Pillow knows, or declares more than ``max_pixels``.
    """
    try:
        file = SizedFile(path)
    except FileNotFoundError:
        raise InputError(f"image {path} does not exist") from None
    except OSError as exc:
        raise InputError(f"cannot read image {path}: {exc}") from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(file)
    except Image.DecompressionBombError:
        file.close()
        raise InputError(f"image {path} declares more than {max_pixels} pixels",
                         fixes=[("max_pixels", "to allow more")]) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        file.close()
        raise InputError(f"cannot read image {path}: {exc}") from None
    with file, im:
        if im.width * im.height > max_pixels:
            raise InputError(f"image {path} is {im.width}x{im.height}, more than {max_pixels} "
                             "pixels", fixes=[("max_pixels", "to allow more")])
        yield im


def image_size(path: str | os.PathLike, max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[int, int]:
    """(width, height) of the pixels ``load_image`` gives for ``path`` (EXIF orientation
    applied), read from the header without decoding.

    Raises
    ------
    InputError
        As ``open_image``.
    """
    with open_image(Path(path), max_pixels) as im:
        swapped = _orientation(im) in (5, 6, 7, 8)
        return (im.height, im.width) if swapped else (im.width, im.height)


def is_turned(path: str | os.PathLike) -> bool:
    """Whether ``path``'s EXIF orientation makes ``load_image`` turn or mirror its stored
    pixels (which tools that ignore the tag, COLMAP among them, read as they are stored)."""
    with open_image(Path(path)) as im:
        return _orientation(im) in _ORIENT


def _orientation(im: Image.Image) -> int:
    """The EXIF orientation tag of ``im`` (1, upright, when absent or unreadable)."""
    try:
        return int(im.getexif().get(0x0112, 1))
    except (OSError, SyntaxError, ValueError, TypeError):
        return 1


def load_image(path: str | os.PathLike, name: str | None = None,
               max_pixels: int = DEFAULT_MAX_PIXELS) -> LoadedImage:
    """Decode one image file (see the module docstring for what is supported).

    Raises
    ------
    InputError
        If the file cannot be decoded as an image, declares more than ``max_pixels``
        pixels, or holds NaN (the message names it).
    """
    path = Path(path)
    try:
        with open_image(path, max_pixels) as im:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                im.load()
            orientation = _orientation(im)
            if _is_16bit_rgb(path, im):
                pixels = _read_16bit_rgb(path, im)
            else:
                pixels = _pil_to_array(_in_srgb(im))
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"cannot read image {path}: {exc}") from None
    if orientation in _ORIENT:
        pixels = _ORIENT[orientation](pixels)
    if pixels.size == 0:
        raise InputError(f"image {path} has no pixels")
    alpha = None
    if pixels.shape[-1] == 4:
        alpha = np.ascontiguousarray(pixels[..., 3] / np.float32(np.iinfo(pixels.dtype).max),
                                     np.float32)
        pixels = pixels[..., :3]
    opaque = np.ones(pixels.shape[:2], bool) if alpha is None else alpha > 0
    return LoadedImage(name or path.name, np.ascontiguousarray(pixels), opaque, alpha)


def _in_srgb(im: Image.Image) -> Image.Image:
    """``im`` converted from its embedded colour profile to sRGB; as it is when it has none,
    it is sRGB already, or the profile cannot be parsed (then it is taken as sRGB, as
    browsers do)."""
    icc = im.info.get("icc_profile")
    if not icc or im.mode not in ("RGB", "RGBA"):
        return im
    from PIL import ImageCms

    try:
        profile = ImageCms.ImageCmsProfile(io.BytesIO(icc))
        if "srgb" in ImageCms.getProfileDescription(profile).lower():
            return im
        return ImageCms.profileToProfile(im, profile, ImageCms.createProfile("sRGB"),
                                         outputMode=im.mode)
    except (ImageCms.PyCMSError, OSError, ValueError, TypeError):
        return im


def _pil_to_array(im: Image.Image) -> np.ndarray:
    """(H, W, 3 or 4) uint8 or uint16 array of a Pillow image."""
    if im.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        grey = np.clip(np.asarray(im), 0, 65535).astype(np.uint16)
        return np.repeat(grey[..., None], 3, axis=-1)
    if im.mode == "F":
        values = np.asarray(im)
        if not np.isfinite(values).all():
            raise ValueError("it holds NaN or infinite values")
        grey = np.round(np.clip(values, 0.0, 1.0) * 65535).astype(np.uint16)
        return np.repeat(grey[..., None], 3, axis=-1)
    has_alpha = im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    return np.asarray(im.convert("RGBA" if has_alpha else "RGB"))


def _is_16bit_rgb(path: Path, im: Image.Image) -> bool:
    """Whether Pillow would silently reduce this 16-bit colour image to 8 bits."""
    if im.format == "PNG":
        with open(path, "rb") as f:
            header = f.read(26)
        return header[24] == 16 and header[25] in (2, 6)  # bit depth, colour type RGB(A)
    if im.format == "TIFF":
        import tifffile

        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            return page.dtype == np.uint16 and page.samplesperpixel in (3, 4)
    return False


def _read_16bit_rgb(path: Path, im: Image.Image) -> np.ndarray:
    """(H, W, 3 or 4) uint16 pixels of a 16-bit PNG (pypng) or TIFF (tifffile), imported
    only for such files."""
    if im.format == "PNG":
        import png

        try:
            width, height, rows, info = png.Reader(filename=str(path)).asDirect()
            rows = list(rows)
        except png.Error as exc:
            raise ValueError(str(exc)) from None
        planes = info["planes"]
        return np.vstack([np.asarray(r, np.uint16) for r in rows]).reshape(height, width, planes)
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        pixels = page.asarray()
        if page.planarconfig == tifffile.PLANARCONFIG.SEPARATE:  # (S, H, W): one plane a channel
            pixels = np.moveaxis(pixels, 0, -1)
    if pixels.ndim != 3:
        raise ValueError(f"unsupported TIFF layout {page.axes} {pixels.shape}")
    return pixels[..., :4]


def load_images(paths: list[Path], root: Path, progress: bool = False,
                max_pixels: int = DEFAULT_MAX_PIXELS) -> list[LoadedImage]:
    """Decode every path, naming each image by its path relative to ``root``."""
    from tqdm import tqdm

    return [
        load_image(p, p.relative_to(root).as_posix(), max_pixels)
        for p in tqdm(paths, desc="loading", unit="img", disable=not progress)
    ]
