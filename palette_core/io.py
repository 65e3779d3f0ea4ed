"""Image input, stitching into one colour set, and atomic output files.

Images are read with Pillow (PNG, JPEG, TIFF, BMP, WebP and whatever else it
knows); 16-bit RGB(A) PNG and TIFF, which Pillow reduces to 8 bits, are read with
pypng and tifffile instead. EXIF orientation is applied, greyscale becomes RGB,
and fully transparent pixels are marked so the palette can leave them out.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import png
import tifffile
from PIL import Image, UnidentifiedImageError

from .errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")

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
    """

    name: str
    pixels: np.ndarray
    opaque: np.ndarray

    @property
    def rgb(self) -> np.ndarray:
        """(H, W, 3) float64 colours in [0, 1]."""
        return self.pixels / float(np.iinfo(self.pixels.dtype).max)


def find_images(inputs: list[str | os.PathLike]) -> tuple[Path, list[Path]]:
    """Expand files and folders (recursively, sorted) into image paths.

    Returns the input root (the deepest folder holding every input) and the paths.

    Raises
    ------
    InputError
        If a path does not exist or a folder holds no image.
    """
    if not inputs:
        raise InputError("no input given: name image files or folders")
    paths: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = sorted(
                p for p in item.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
            )
            if not found:
                raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) found in folder {item}")
            paths.extend(found)
        elif item.is_file():
            paths.append(item)
        else:
            raise InputError(f"input path does not exist: {item}")
    paths = list(dict.fromkeys(p.resolve() for p in paths))
    root = Path(os.path.commonpath([p.parent for p in paths]))
    return root, paths


def load_image(path: str | os.PathLike, name: str | None = None) -> LoadedImage:
    """Decode one image file (see the module docstring for what is supported).

    Raises
    ------
    InputError
        If the file cannot be decoded as an image (the message names it).
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            orientation = im.getexif().get(0x0112, 1)
            pixels = _read_16bit_rgb(path, im) if _is_16bit_rgb(path, im) else None
            if pixels is None:
                pixels = _pil_to_array(im)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, png.Error) as exc:
        raise InputError(f"cannot read {path} as an image: {exc}") from None
    if pixels.shape[-1] == 4:
        opaque = pixels[..., 3] > 0
        pixels = pixels[..., :3]
    else:
        opaque = np.ones(pixels.shape[:2], bool)
    if orientation in _ORIENT:
        pixels, opaque = _ORIENT[orientation](pixels), _ORIENT[orientation](opaque)
    if pixels.size == 0:
        raise InputError(f"image {path} has no pixels")
    return LoadedImage(
        name or path.name, np.ascontiguousarray(pixels), np.ascontiguousarray(opaque)
    )


def _pil_to_array(im: Image.Image) -> np.ndarray:
    """(H, W, 3 or 4) uint8 or uint16 array of a Pillow image."""
    if im.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        grey = np.clip(np.asarray(im), 0, 65535).astype(np.uint16)
        return np.repeat(grey[..., None], 3, axis=-1)
    if im.mode == "F":
        grey = np.round(np.clip(np.asarray(im), 0.0, 1.0) * 65535).astype(np.uint16)
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
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            return page.dtype == np.uint16 and page.samplesperpixel in (3, 4)
    return False


def _read_16bit_rgb(path: Path, im: Image.Image) -> np.ndarray:
    if im.format == "PNG":
        width, height, rows, info = png.Reader(filename=str(path)).asDirect()
        planes = info["planes"]
        return np.vstack([np.asarray(r, np.uint16) for r in rows]).reshape(height, width, planes)
    return tifffile.imread(path, key=0)[..., :4]


def load_images(paths: list[Path], root: Path, progress: bool = False) -> list[LoadedImage]:
    """Decode every path, naming each image by its path relative to ``root``."""
    from tqdm import tqdm

    return [
        load_image(p, p.relative_to(root).as_posix())
        for p in tqdm(paths, desc="loading", unit="img", disable=not progress)
    ]


@dataclass
class ColourSet:
    """All pixels of all images stitched together and deduplicated exactly.

    Attributes
    ----------
    colours : (U, 3) float64
        The distinct colours in [0, 1], sorted by packed integer value.
    counts : (U,) int64
        How many opaque pixels have each colour (0 for colours seen only in
        fully transparent pixels: they get weights but do not shape the palette).
    inverse : (N,) int64
        Index into ``colours`` of every stitched pixel.
    offsets : (n_images + 1,) int64
        Image ``i`` owns ``inverse[offsets[i]:offsets[i + 1]]``.
    """

    colours: np.ndarray
    counts: np.ndarray
    inverse: np.ndarray
    offsets: np.ndarray

    @classmethod
    def from_images(cls, images: list[LoadedImage]) -> ColourSet:
        sixteen = any(im.pixels.dtype == np.uint16 for im in images)
        bits = 16 if sixteen else 8
        codes = np.concatenate([_pack(im.pixels, bits) for im in images])
        opaque = np.concatenate([im.opaque.ravel() for im in images])
        offsets = np.cumsum([0] + [im.opaque.size for im in images])
        unique, inverse = _unique_codes(codes, bits)
        counts = np.bincount(inverse[opaque], minlength=len(unique)).astype(np.int64)
        mask = (1 << bits) - 1
        channels = np.stack([unique >> (2 * bits), (unique >> bits) & mask, unique & mask], -1)
        return cls(channels / float(mask), counts, inverse, offsets)

    def image_indices(self, i: int) -> np.ndarray:
        """Indices into ``colours`` of image ``i``'s pixels, in raster order."""
        return self.inverse[self.offsets[i] : self.offsets[i + 1]]


def _pack(pixels: np.ndarray, bits: int) -> np.ndarray:
    """(H, W, 3) integer pixels -> (H*W,) int64 codes; 8-bit values are widened to 16."""
    p = pixels.reshape(-1, 3).astype(np.int64)
    if bits == 16 and pixels.dtype == np.uint8:
        p *= 257
    return (p[:, 0] << (2 * bits)) | (p[:, 1] << bits) | p[:, 2]


def _unique_codes(codes: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique codes and the inverse index; O(N) through a table for 8-bit data."""
    if bits == 8 and len(codes) > (1 << 20):
        present = np.bincount(codes, minlength=1 << 24) > 0
        unique = np.flatnonzero(present)
        table = np.empty(1 << 24, np.int64)
        table[unique] = np.arange(len(unique))
        return unique, table[codes]
    return np.unique(codes, return_inverse=True)


@contextlib.contextmanager
def atomic_outputs():
    """Stage output files and publish them together, or not at all.

    Yields a function ``stage(final_path) -> temp_path``: write to the temporary
    path it returns. When the block ends without error every staged file is
    renamed onto its final path; on error every temporary file is removed.
    """
    staged: list[tuple[Path, Path]] = []

    def stage(final: str | os.PathLike) -> Path:
        final = Path(final)
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{final.stem}.", suffix=".tmp" + final.suffix, dir=final.parent
        )
        os.close(fd)
        staged.append((Path(tmp), final))
        return Path(tmp)

    try:
        yield stage
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        raise
    for tmp, final in staged:
        os.replace(tmp, final)


def check_writable(paths: list[Path], force: bool) -> None:
    """Fail early if an output exists (without ``force``) or its folder cannot be written.

    Raises
    ------
    InputError
        Naming the first offending path.
    """
    for path in map(Path, paths):
        if path.exists() and not force:
            raise InputError(f"output {path} already exists (use --force to overwrite)")
        if path.is_dir():
            raise InputError(f"output {path} is a folder, expected a file path")
        folder = next(p for p in [path.parent, *path.parent.parents] if p.exists())
        if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
            raise InputError(f"cannot write output {path}: {folder} is not a writable folder")


def save_image(path: Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3), (H, W, 4) or (H, W) floats in [0, 1] as an 8-bit image (suffix = format)."""
    data = np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
    fmt = Image.registered_extensions().get(path.suffix.lower(), "PNG")
    Image.fromarray(data).save(path, format=fmt, **({"quality": 95} if fmt == "JPEG" else {}))
