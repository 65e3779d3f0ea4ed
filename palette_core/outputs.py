"""Writing outputs: checked up front, staged beside their place, published by rename.

Every command writes through here, so nothing is half-written: files are staged
as hidden temporaries in their final folder (``atomic_outputs``) and folders are
built beside their final place (``publish_folder``); both are renamed into place
only when everything has been written, and removed on any error.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image

from .errors import InputError


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


@contextlib.contextmanager
def publish_folder(final: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Build a folder beside ``final`` and rename it onto ``final`` when the block succeeds.

    Yields the staging folder. An existing ``final`` is replaced (moved aside,
    then deleted) only with ``force``; on error the staging folder is removed.

    Raises
    ------
    InputError
        If ``final`` exists and ``force`` is not given.
    """
    final = Path(final)
    check_outdir(final, force)
    final.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    try:
        yield staging
        if final.exists():
            trash = Path(tempfile.mkdtemp(prefix=f".{final.name}.old.", dir=final.parent))
            os.replace(final, trash / "old")
            os.replace(staging, final)
            shutil.rmtree(trash)
        else:
            os.replace(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def check_writable(paths: list[Path], force: bool) -> None:
    """Fail early if an output file exists (without ``force``) or its folder cannot be written.

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
        _check_parent(path)


def check_outdir(outdir: str | os.PathLike, force: bool) -> None:
    """Fail early if ``outdir`` is a file, a non-empty folder (without ``force``) or unwritable.

    Raises
    ------
    InputError
        Naming the folder and the reason.
    """
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"output {outdir} exists and is not a folder")
    if outdir.is_dir() and any(outdir.iterdir()) and not force:
        raise InputError(f"output folder {outdir} is not empty (use --force to replace it)")
    _check_parent(outdir)


def _check_parent(path: Path) -> None:
    folder = next(p for p in [path.parent, *path.parent.parents] if p.exists())
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"cannot write output {path}: {folder} is not a writable folder")


def save_image(path: Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3), (H, W, 4) or (H, W) floats in [0, 1] as an 8-bit image (suffix = format)."""
    data = np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
    fmt = Image.registered_extensions().get(Path(path).suffix.lower(), "PNG")
    Image.fromarray(data).save(path, format=fmt, **({"quality": 95} if fmt == "JPEG" else {}))
