"""Folders from elsewhere, read without following links out of them.

A folder we read (photos, a mask folder of an edit file, a capture's ``images/``) may hold
symbolic links; one that leads outside the folder would make us read, and in a copy
publish, a file its owner never put there (a private file, ``/etc/hostname``, a whole
disk). Every walk here is ``os.walk`` without ``followlinks`` and every entry must resolve
inside the folder; copies copy the regular files so found.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from .errors import InputError


def inside(folder: str | os.PathLike, name: str) -> Path:
    """``folder / name``, checked to lie inside ``folder`` (names come from files we read).

    Raises
    ------
    InputError
        If ``name`` is empty, absolute, holds a NUL or ``..``, or resolves outside.
    """
    folder = Path(folder)
    path = folder / name
    if (not name or "\0" in name or Path(name).is_absolute()
            or ".." in Path(name).parts
            or not path.resolve().is_relative_to(folder.resolve())):
        raise InputError(f"refusing {name!r}: it would lie outside {folder}")
    return path


def check_within(folder: str | os.PathLike, path: str | os.PathLike) -> Path:
    """``path``, an entry of ``folder``, checked not to be a link that leads out of it.

    Raises
    ------
    InputError
        Naming the link and where it leads.
    """
    path = Path(path)
    if path.is_symlink() and not path.resolve().is_relative_to(Path(folder).resolve()):
        raise InputError(f"{path} is a link out of {folder} (to {path.resolve()}): a "
                         "folder's links out are not followed; name the file itself, or "
                         "copy it in")
    return path


def files_in(folder: str | os.PathLike, recursive: bool = True,
             suffixes: tuple[str, ...] | None = None) -> list[Path]:
    """The files under ``folder`` (only directly in it unless ``recursive``; only those with
    ``suffixes``, compared in lower case, when given), sorted, hidden names included; links
    to folders are not descended.

    Raises
    ------
    InputError
        If one of those files is a link that leads out of ``folder`` (``check_within``).
    """
    found = []
    for top, _, files in os.walk(folder):  # followlinks=False
        found += [Path(top) / name for name in files
                  if suffixes is None or Path(name).suffix.lower() in suffixes]
        if not recursive:
            break
    return sorted(check_within(folder, path) for path in found if path.is_file())


def copy_folder(source: str | os.PathLike, target: str | os.PathLike) -> None:
    """Copy the regular files under ``source`` to ``target`` (``files_in``; links inside
    ``source`` are copied as the files they lead to).

    Raises
    ------
    InputError
        If an entry of ``source`` is a link that leads out of it.
    """
    source, target = Path(source), Path(target)
    target.mkdir()
    for file in files_in(source):
        copy = target / file.relative_to(source)
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(file, copy)
