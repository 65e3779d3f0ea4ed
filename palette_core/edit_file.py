"""Local-edit files: stacked selections with their palettes, saved to be replayed
(``palette-recolor STACK --edits FILE``; docs/formats.md, docs/selections.md).

``edits.json`` holds::

    {"format": "palette-edits/1",
     "stack": {"palette": [[r, g, b], ...], "images": "<sha256 of the image names>"},
     "edits": [{"palette": ["#rrggbb", ...], "rgb": [[r, g, b], ...],
                "mask": "edits.masks/0.png" | "colour": K | "near": "#rrggbb",
                "threshold": 0.5, "distance": 0.1, "feather": 0.0}, ...]}

with the masks beside it in ``edits.masks/`` (one PNG for every image, or a folder of one
per image). ``stack`` names the stack the edits were made for; another stack is refused.
Mask paths are relative to the file's folder and cannot leave it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from .errors import InputError
from .folders import copy_folder, inside
from .json_file import read_json
from .outputs import atomic_outputs, check_outdir, check_writable, publish_folder
from .palette_file import palette_entry, palette_to_hex, parse_palette
from .selection import LocalEdit, Selection, parse_near
from .stack import WeightStack

FORMAT = "palette-edits/1"
_NUMBERS = ("threshold", "distance", "feather")


def masks_folder(path: str | os.PathLike) -> Path:
    """Where the masks of edit file ``path`` live: ``edits.json`` -> ``edits.masks``."""
    path = Path(path)
    return path.with_name(path.stem + ".masks")


def stack_identity(stack: WeightStack) -> dict:
    """What an edit file records of the stack it was made for."""
    names = "\n".join(stack.names).encode()
    return {"palette": np.asarray(stack.palette, np.float64).tolist(),
            "images": hashlib.sha256(names).hexdigest()}


def write_edits(path: str | os.PathLike, stack: WeightStack, edits: list[LocalEdit],
                force: bool = False) -> list[Path]:
    """Write ``edits`` of ``stack`` to ``path`` with copies of their masks in
    ``masks_folder(path)``, published together; returns both paths (the folder only when a
    mask needs it).

    Raises
    ------
    InputError
        If an output exists (without ``force``).
    """
    path = Path(path)
    folder = masks_folder(path)
    masked = check_edits_writable(path, edits, force)
    outputs = [path] + [folder] * masked
    with contextlib.ExitStack() as context:
        stage = context.enter_context(atomic_outputs(force))
        staging = context.enter_context(publish_folder(folder, force)) if masked else None
        entries = [_entry(edit, i, staging, folder.name) for i, edit in enumerate(edits)]
        text = json.dumps({"format": FORMAT, "stack": stack_identity(stack), "edits": entries},
                          indent=1)
        stage(path).write_text(text + "\n")
    return outputs


def check_edits_writable(path: Path, edits: list[LocalEdit], force: bool) -> bool:
    """InputError unless ``write_edits`` may write ``path`` (and its masks folder, when an
    edit has a mask: then True)."""
    check_writable([path], force)
    masked = any(edit.selection.mask is not None for edit in edits)
    if masked:
        check_outdir(masks_folder(path), force)
    return masked


def _entry(edit: LocalEdit, i: int, staging: Path | None, folder: str) -> dict:
    """The JSON of one edit, its mask copied into ``staging`` (published as ``folder``)."""
    selection = edit.selection
    entry = {**palette_entry(edit.palette), **{k: getattr(selection, k) for k in _NUMBERS}}
    if selection.mask is not None:
        source = Path(selection.mask)
        name = f"{i}{source.suffix}" if source.is_file() else str(i)
        if source.is_file():
            shutil.copyfile(source, staging / name)
        else:
            copy_folder(source, staging / name)  # regular files: no link out is followed
        entry["mask"] = f"{folder}/{name}"
    elif selection.colour is not None:
        entry["colour"] = selection.colour
    else:
        entry["near"] = palette_to_hex(np.array([selection.near]))[0]
    return entry


def read_edits(path: str | os.PathLike, stack: WeightStack) -> list[LocalEdit]:
    """The edits of file ``path``, checked against ``stack``.

    Raises
    ------
    InputError
        If the file is missing or malformed, was made for another stack, or a mask path
        leaves its folder or does not exist.
    """
    path = Path(path)
    data = read_json(path, "edit file")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"{path} is not an edit file (format {FORMAT})")
    if not _made_for(data.get("stack"), stack_identity(stack)):
        raise InputError(f"edit file {path} was made for another stack (its palette or its "
                         "images differ)")
    entries = data.get("edits")
    if not isinstance(entries, list) or not entries:
        raise InputError(f"edit file {path} must list its edits")
    return [_edit(entry, path, i, len(stack.palette)) for i, entry in enumerate(entries)]


def _made_for(made_for, ours: dict) -> bool:
    """Whether an edit file's ``stack`` entry (any JSON) names the stack of ``ours``."""
    if not isinstance(made_for, dict) or made_for.get("images") != ours["images"]:
        return False
    try:
        palette = np.asarray(made_for.get("palette"), np.float64)
    except (TypeError, ValueError):  # not a table of numbers
        return False
    return palette.shape == np.shape(ours["palette"]) and np.allclose(palette, ours["palette"],
                                                                      atol=1e-6)


def _edit(entry, path: Path, i: int, k: int) -> LocalEdit:
    where = f"edit file {path}, edit {i}"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: an edit is a table")
    unknown = set(entry) - {"palette", "rgb", "mask", "colour", "near", *_NUMBERS}
    if unknown:
        raise InputError(f"{where}: unknown field {sorted(unknown)[0]!r}")
    palette = parse_palette(entry, where, k)
    numbers = {key: entry[key] for key in _NUMBERS if key in entry}
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool)
               for v in numbers.values()):
        raise InputError(f"{where}: threshold, distance and feather are numbers")
    mask, colour, near = entry.get("mask"), entry.get("colour"), entry.get("near")
    if mask is not None:
        if not isinstance(mask, str):
            raise InputError(f"{where}: mask is a path")
        mask = inside(path.parent, mask)  # cannot leave the file's folder
    if colour is not None and (not isinstance(colour, int) or isinstance(colour, bool)):
        raise InputError(f"{where}: colour is a palette index")
    if near is not None:
        near = parse_near(near if isinstance(near, str) else repr(near))
    try:
        selection = Selection(mask=mask, colour=colour, near=near, **numbers)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    selection.check(k)
    return LocalEdit(selection, palette)
