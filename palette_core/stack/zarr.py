"""Weight stacks in a Zarr store (docs/formats.md): collections
beyond memory, read lazily frame by frame.

A store is built where nothing of the user's is (``check_store_output``), in a hidden
partial sibling (``partial_store``) that ``--resume`` finds after a kill, and renamed
onto its place when complete (``publish_store``); ``--force`` replaces only a store of
ours. ``read_zarr_stack`` checks every declared shape, chunk and attribute before a
weight is read.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..basis import Basis, check_basis
from ..errors import InputError, OutputExists, first_line
from ..io import DEFAULT_MAX_PIXELS
from ..outputs import check_parent, publish_folder, rename_no_replace
from .base import FORMAT, WeightStack, check_meta, check_names, video_of

_ARRAY_NAME = re.compile(r"^weights_\d{4,}$")


def _exists(path: str) -> bool:
    return "://" not in path and os.path.lexists(path)


def is_stack_store(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a Zarr group of a weight stack (``format`` ``FORMAT``): a store
    that this package wrote, which ``--force`` may replace."""
    import zarr

    try:
        return zarr.open_group(str(path), mode="r").attrs.get("format") == FORMAT
    except Exception:  # noqa: BLE001 - whatever zarr raises, it is not our store
        return False


def check_store_output(path: str | os.PathLike, force: bool) -> None:
    """Fail early unless a store may be written at ``path``: nothing there (or an empty
    folder), or, with ``force``, a weight stack store to replace. Anything else there is the
    user's and is never replaced.

    Raises
    ------
    InputError
        Naming ``path``.
    """
    path = str(path)
    if "://" in path:
        if is_stack_store(path) and not force:
            raise OutputExists(f"output {path} already exists", "to replace it")
        return
    if not os.path.lexists(path) or (os.path.isdir(path) and not os.listdir(path)):
        check_parent(Path(path))
        return
    if not is_stack_store(path):
        raise InputError(f"output {path} exists and is not a weight stack store: it is "
                         "never replaced; choose another output")
    if not force:
        raise OutputExists(f"output {path} already exists", "to replace it")


def partial_store(output: str) -> str:
    """Where the store ``output`` is built until its pass 2 completes: a hidden sibling
    (``.w.zarr.partial``) that ``--resume`` finds after a kill; a URL is built in place."""
    if "://" in output:
        return output
    path = Path(output.rstrip("/"))
    return str(path.with_name(f".{path.name}.partial"))


def publish_store(partial: str, output: str, force: bool) -> None:
    """Rename the finished store onto ``output`` (a store there is replaced only with
    ``force``, after ``check_store_output`` found it to be ours)."""
    if partial == output:
        return
    with contextlib.suppress(OSError):
        os.rmdir(output)  # an empty folder: what check_store_output allowed
    if force and is_stack_store(output):
        trash = tempfile.mkdtemp(prefix=f".{Path(output).name}.old.", dir=Path(output).parent)
        os.replace(output, Path(trash) / "old")
        os.replace(partial, output)
        remove_store(trash)
        return
    try:
        rename_no_replace(Path(partial), Path(output))
    except FileExistsError:
        raise InputError(f"output {output} appeared while writing; it was kept, and the new "
                         f"store waits in {partial}", fixes=[("resume", "to publish it")]
                         ) from None


def remove_store(path: str) -> None:
    """Delete a store (or its trash folder) that this package made."""
    shutil.rmtree(path, ignore_errors=True)


def compressors() -> list:
    """Blosc LZ4 with byte shuffle at level 1: the fastest of Zarr's codecs to write
    weights (docs/formats.md)."""
    from zarr.codecs import BloscCodec

    return [BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")]


def create_store(path: str, stack: WeightStack, sources: list[tuple[str, int | None, tuple]],
                 dtype: str, complete: bool):
    """A new store at ``path`` with ``stack``'s attributes (its weights unused) and one array
    per source: ``(name, frames or None for an image, (H, W, M))``, chunked per frame; the
    ``complete`` marker starts all ``complete``. An existing store there is replaced only if
    it is ours (``is_stack_store``)."""
    import zarr

    store = zarr.open_group(path, mode="w" if is_stack_store(path) else "w-")
    arrays = {}
    for i, (source, frames, shape) in enumerate(sources):
        arrays[source] = name = f"weights_{i:04d}"
        store.create_array(name, shape=shape if frames is None else (frames, *shape),
                           chunks=shape if frames is None else (1, *shape), dtype=dtype,
                           compressors=compressors())
    store.create_array("complete", shape=(len(stack.names),), chunks=(1,), dtype="bool",
                       fill_value=complete)
    store.attrs.update({"format": FORMAT, "palette": np.asarray(stack.palette).tolist(),
                        "basis": str(stack.basis), "order": stack.order,
                        "names": list(stack.names), "method": stack.method,
                        "arrays": arrays, "meta": json.dumps(stack.meta)})
    return store


def write_zarr_stack(stack: WeightStack, path: str | os.PathLike, force: bool = False) -> None:
    """Write any stack as a Zarr store, one frame at a time (the frames of a video into one
    array), built beside ``path`` and published whole (``outputs.publish_folder``)."""
    check_store_output(path, force)
    groups: dict[str, list[int]] = {}
    for i, name in enumerate(stack.names):
        groups.setdefault(video_of(name) or name, []).append(i)
    sources = [(source, len(indices) if video_of(stack.names[indices[0]]) else None,
                stack.weights[indices[0]].shape) for source, indices in groups.items()]
    with publish_folder(path, force) as staging:
        store = create_store(str(staging), stack, sources,
                             str(stack.weights[0].dtype), complete=True)
        for (source, frames, _), indices in zip(sources, groups.values()):
            data = store[store.attrs["arrays"][source]]
            for j, i in enumerate(indices):
                if frames is None:
                    data[...] = stack.weights[i]
                else:
                    data[j] = stack.weights[i]


class LazyWeights(Sequence):
    """The per-frame weights of a Zarr stack, read one frame at a time; a frame that cannot
    be decoded (a damaged chunk) or holds NaN is an InputError naming it."""

    def __init__(self, store, sources: list[tuple[str, int | None]], names: list[str],
                 path: str):
        self.store, self.sources, self.names, self.path = store, sources, names, path

    def __len__(self) -> int:
        return len(self.sources)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        array, frame = self.sources[i]
        try:
            data = self.store[array]
            weights = data[frame] if frame is not None else data[...]
        except Exception as exc:  # noqa: BLE001 - codecs raise many kinds on damaged chunks
            raise InputError(f"{self.path}: weights of {self.names[i]} cannot be read: "
                             f"{first_line(exc)}"
                             ) from None
        if not np.isfinite(weights).all():
            raise InputError(f"{self.path}: weights of {self.names[i]} hold NaN or infinity")
        return weights


def _frames(store, source: str, name: str, path: str, m: int, count: int,
            max_pixels: int) -> list[tuple[str, int | None]]:
    """The frames of array ``name`` (the weights of ``source``): (name, frame index, or None
    for an image), checked: float32 or float16 frames of at most ``max_pixels`` pixels and
    ``m`` channels, at most ``count`` of them, one chunk a frame, every chunk written."""
    try:
        data = store[name]
    except KeyError:
        raise InputError(f"{path}: weights of {source} ({name}) are missing") from None
    except Exception as exc:  # noqa: BLE001 - zarr and json raise many kinds
        raise InputError(f"{path}: weights of {source} ({name}) cannot be read: "
                         f"{first_line(exc)}"
                         ) from None
    video = data.ndim == 4
    shape = data.shape[1:] if video else data.shape
    pixels = shape[0] * shape[1] if len(shape) == 3 else 0
    if (len(shape) != 3 or shape[-1] != m or not 0 < pixels <= max_pixels
            or data.dtype not in (np.float32, np.float16)
            or (video and not 0 < data.shape[0] <= count)
            or data.chunks != ((1, *shape) if video else shape)):
        raise InputError(f"{path}: weights of {source} must be float32/float16 frames of at "
                         f"most {max_pixels} pixels and {m} channels, one chunk a frame, "
                         f"got {data.dtype} {data.shape} in chunks {data.chunks}")
    missing = data.nchunks - data.nchunks_initialized
    if missing:
        raise InputError(f"{path}: weights of {source} miss {missing} of {data.nchunks} "
                         "chunks")
    return [(name, i) for i in range(data.shape[0])] if video else [(name, None)]


def read_zarr_stack(path: str, max_pixels: int = DEFAULT_MAX_PIXELS) -> WeightStack:
    """Read and validate a Zarr weight stack; its weights are read lazily, frame by frame.

    Everything is checked before a weight is read: the attributes' types, array names
    (plain names inside the store), each array's declared shape and chunking against the
    names and ``max_pixels`` a frame, every chunk present, and every frame complete.

    Raises
    ------
    InputError
        If the store is missing, not a ``palette-weights/1`` stack, incomplete, or
        malformed (the message names the key).
    """
    import zarr

    if not _exists(path) and is_stack_store(partial_store(path)):
        raise InputError(f"{path} is incomplete: palette-decompose's resume finishes it")
    try:
        store = zarr.open_group(path, mode="r")
        attrs = dict(store.attrs)
    except Exception as exc:  # noqa: BLE001 - zarr and json raise many kinds
        raise InputError(f"{path} is not a readable Zarr weight stack: "
                         f"{first_line(exc)}"
                         ) from None
    if attrs.get("format") != FORMAT:
        raise InputError(f"{path}: format is {attrs.get('format')!r}, expected {FORMAT!r}")
    try:
        palette = np.asarray(attrs["palette"], np.float64)
        names, arrays = attrs["names"], attrs["arrays"]
        meta = json.loads(attrs["meta"])
        basis = Basis.parse(attrs["basis"])
        order = attrs.get("order", 1)
    except (KeyError, TypeError, ValueError, RecursionError) as exc:
        raise InputError(f"{path}: malformed attributes: {exc}") from None
    if (palette.ndim != 2 or palette.shape[1:] != (3,) or len(palette) == 0
            or not np.all((palette >= 0) & (palette <= 1))):
        raise InputError(f"{path}: palette must have shape (K, 3) with values in [0, 1]")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: names must be a list of strings")
    if not isinstance(arrays, dict) or not all(
            isinstance(a, str) and _ARRAY_NAME.match(a) for a in arrays.values()):
        raise InputError(f"{path}: arrays must map sources to arrays named weights_NNNN")
    check_names(names, path)
    m = check_basis(len(palette), basis, order, path)
    check_meta(meta, names, path)
    try:
        complete = store["complete"]
        done = complete.shape == (len(names),) and bool(complete[...].all())
    except Exception:  # noqa: BLE001 - missing, or not a bool array
        done = False
    if not done:
        raise InputError(f"{path} is incomplete: palette-decompose's resume finishes it")
    frames = [frame for source, name in arrays.items()
              for frame in _frames(store, source, name, path, m, len(names), max_pixels)]
    if len(frames) != len(names):
        raise InputError(f"{path}: {len(names)} names but {len(frames)} weight frames")
    return WeightStack(palette.astype(np.float32), LazyWeights(store, frames, names, path),
                       names, str(attrs.get("method", "mvc")), basis, order, meta=meta)
