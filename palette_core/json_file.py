"""Reading the JSON files people hand to the commands (palettes, local edits, regions): one
clear line for a file that is missing or not JSON."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .errors import InputError

#: Largest JSON file read: a palette, an edit list or a region list is a few kilobytes.
MAX_JSON_BYTES = 16 << 20


def read_json(path: str | os.PathLike, kind: str, hint: str = ""):
    """The parsed contents of the ``kind`` file (``"palette file"``, ...) at ``path``.

    Raises
    ------
    InputError
        If it does not exist (the message ends with ``hint``), is larger than
        ``MAX_JSON_BYTES`` or is not valid JSON.
    """
    try:
        size = Path(path).stat().st_size
        if size > MAX_JSON_BYTES:
            raise InputError(f"{kind} {path} holds {size} bytes, more than the "
                             f"{MAX_JSON_BYTES} a {kind} may")
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(f"{kind} {path} does not exist{hint}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{kind} {path} is not valid JSON: {exc}") from None
