"""PlayCanvas's SOG (a zip, or a folder, of ``meta.json`` and WebP images of the splats'
quantised attributes and codebooks), read through PyPI's ``gsply`` (which decodes the WebP
with ``imagecodecs``) after the bundle is checked here: every entry's declared size
possible for its compressed one, and every image's size, from its header, of the count the
meta declares."""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

from PIL import Image

from palette_core.errors import InputError

from .fields import MAX_RATIO, SplatFields, from_gsdata, gsply_module

#: The images of a SOG and how many pixels each holds a splat (the rest: codebooks).
SPLAT_IMAGES = ("means", "quats", "scales", "sh0")


def read_sog(path: str | os.PathLike) -> SplatFields:
    """The splats of a ``.sog`` bundle, or of a folder holding a SOG's ``meta.json``."""
    path = Path(path)
    entries, size = _entries(path)
    try:
        meta = json.loads(entries("meta.json"))
        count = int(meta["count"] if "count" in meta else meta["means"]["shape"][0])
        images = {name: key for key in SPLAT_IMAGES for name in meta[key]["files"]}
    except (ValueError, KeyError, TypeError, IndexError):
        raise InputError(f"{path}: the SOG's meta.json is not one of splats") from None
    if not 0 < count <= MAX_RATIO * size:
        raise InputError(f"{path}: its meta.json declares {count} splats, which {size} bytes "
                         "cannot hold")
    for name, key in images.items():
        try:
            width, height = Image.open(io.BytesIO(entries(name))).size
        except (OSError, ValueError):
            raise InputError(f"{path}: its {key} image {name} is not a picture") from None
        if not count <= width * height <= count + 4 * (width + height):
            raise InputError(f"{path}: its {key} image {name} is {width} x {height}, not of "
                             f"{count} splats")
    try:
        data = gsply_module("SOG").sogread(path)
    except (ValueError, KeyError, ImportError) as exc:
        raise InputError(f"{path}: {exc}") from None
    return from_gsdata(data)


def _entries(path: Path):
    """A reader of the named entries of the bundle (or folder) ``path``, each refused when
    it declares more than ``MAX_RATIO`` times its stored size, and the bundle's bytes."""
    if path.is_dir():
        def entry(name: str) -> bytes:
            file = path / Path(name).name
            if not file.is_file():
                raise InputError(f"{path}: the SOG has no {name}")
            return file.read_bytes()
        return entry, sum(f.stat().st_size for f in path.iterdir() if f.is_file())
    try:
        bundle = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError):
        raise InputError(f"{path} is not a SOG bundle (a zip)") from None

    def entry(name: str) -> bytes:
        try:
            info = bundle.getinfo(name)
        except KeyError:
            raise InputError(f"{path}: the SOG has no {name}") from None
        if info.file_size > MAX_RATIO * info.compress_size + 4096:
            raise InputError(f"{path}: its entry {name} declares {info.file_size} bytes from "
                             f"{info.compress_size}")
        try:
            return bundle.read(info)
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise InputError(f"{path}: its entry {name} is corrupt ({exc})") from None
    return entry, path.stat().st_size
