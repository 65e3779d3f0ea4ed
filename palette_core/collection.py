"""Collections beyond memory: two streaming passes into a chunked Zarr weight stack.

Pass 1 reads the images and video frames one at a time and merges their exact
colour counts (colours packed at 16 bits per channel, sparse: sorted codes and
counts); the palette comes from the merged counts, as for ``decompose``. Pass 2
computes the mean value coordinates of every distinct colour once and writes
each frame's weights into its own chunk of ``weights.zarr`` (docs/formats.md).
Memory holds one frame and the distinct colours, never the collection.

Both passes run on a dask.distributed cluster when one is given (``client``):
pass 1 as a tree reduction of the per-task counts, pass 2 as one task per group
of frames, each writing its own chunks of the store; the palette is the same to
the bit. A store records the frames it holds (``complete``), so a pass 2 that
was killed resumes where it stopped.

Videos are anything PyAV reads (``VIDEO_SUFFIXES``); their frames are named
``clip.mp4#000123`` and stored as one (F, H, W, K) array chunked per frame.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from .basis import Basis, n_terms
from .colour_set import pack_codes
from .decompose import stored_weights
from .errors import InputError, OutputExists
from .io import DEFAULT_MAX_PIXELS, IMAGE_SUFFIXES, find_images, load_image
from .mvc import rgb_to_mvc_weights
from .outputs import atomic_outputs, check_apart, check_parent, check_writable, rename_no_replace
from .palette_file import write_palette_json
from .palettes import PALETTE_METHODS, check_palette_size, palette_polytope
from .polytope import Polytope
from .registry import validate_method
from .render import palette_swatch
from .stack import FORMAT, MAX_FPS, WeightStack, check_basis, check_dtype, check_meta, check_names

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")
#: Megapixels of one task: a whole image, or a run of frames of one video.
TASK_MEGAPIXELS = 8.0
_MASK = (1 << 16) - 1


@dataclass(frozen=True)
class Source:
    """One image file or one video of a collection.

    Attributes
    ----------
    path : str
    name : str
        Path relative to the collection's root.
    frames : int
        1 for an image.
    height, width : int
    fps : float or None
        Frames per second of a video.
    keyframes : tuple of int
        Frames of a video where decoding can start (its key frames), ascending.
    """

    path: str
    name: str
    frames: int
    height: int
    width: int
    fps: float | None = None
    keyframes: tuple[int, ...] = (0,)

    @property
    def video(self) -> bool:
        return self.fps is not None

    def frame_names(self) -> list[str]:
        return [f"{self.name}#{i:06d}" for i in range(self.frames)] if self.video else [self.name]


def is_video(path: str | os.PathLike) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def find_sources(inputs: list, max_pixels: int = DEFAULT_MAX_PIXELS) -> list[Source]:
    """Images and videos under ``inputs`` (files and folders, recursively, sorted), probed.

    Raises
    ------
    InputError
        For a missing path, an empty folder, an unreadable file, or a frame larger than
        ``max_pixels``.
    """
    root, paths = find_images(inputs, IMAGE_SUFFIXES + VIDEO_SUFFIXES)
    return [_probe(p, p.relative_to(root).as_posix(), max_pixels) for p in paths]


def _probe(path: Path, name: str, max_pixels: int) -> Source:
    if not is_video(path):
        from .io import open_image

        with open_image(path, max_pixels) as im:
            return Source(str(path), name, 1, im.height, im.width)
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            height, width = stream.codec_context.height, stream.codec_context.width
            if width * height > max_pixels:
                raise InputError(f"video {path} is {width}x{height}, more than --max-pixels "
                                 f"{max_pixels} allows")
            if width * height == 0:
                raise InputError(f"video {path} declares frames of {width}x{height} pixels")
            frames = stream.frames or sum(1 for _ in container.decode(video=0))
            fps = float(stream.average_rate or stream.guessed_rate or 25)
            keyframes = _keyframes(container, stream)
    except (av.FFmpegError, IndexError, OSError, ValueError, ZeroDivisionError) as exc:
        raise InputError(f"cannot read video {path}: {exc}") from None
    if frames < 1:
        raise InputError(f"video {path} has no frames")
    if not 0 < fps <= MAX_FPS:
        raise InputError(f"video {path} declares {fps} frames a second")
    return Source(str(path), name, frames, height, width, fps, keyframes)


def _keyframes(container, stream) -> tuple[int, ...]:
    """Frame indices of a video's key frames, from its packets (nothing is decoded)."""
    rate, base, origin = stream.average_rate, stream.time_base, stream.start_time or 0
    container.seek(origin, stream=stream, backward=True)
    found = {0}
    if rate and base:
        found |= {round(float((packet.pts - origin) * base * rate))
                  for packet in container.demux(stream)
                  if packet.is_keyframe and packet.pts is not None}
    return tuple(sorted(found))


def read_frames(source: Source, start: int = 0, stop: int | None = None,
                max_pixels: int = DEFAULT_MAX_PIXELS) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(H, W, 3) uint8/uint16 pixels and (H, W) opaque mask of frames ``start:stop``."""
    stop = source.frames if stop is None else stop
    if not source.video:
        image = load_image(source.path, source.name, max_pixels)
        if (image.pixels.shape[0], image.pixels.shape[1]) != (source.height, source.width):
            raise InputError(f"{source.path} changed while it was read")
        yield image.pixels, image.opaque
        return
    import av

    index, read = start, 0
    try:
        with av.open(source.path) as container:
            stream = container.streams.video[0]
            for index, frame in _indexed_frames(container, stream, start):
                if index >= stop:
                    break
                if (frame.height, frame.width) != (source.height, source.width):
                    raise InputError(f"video {source.path}: frame {index} is {frame.width}x"
                                     f"{frame.height}, not {source.width}x{source.height} "
                                     "like the video")
                if index >= start:
                    pixels = frame.to_ndarray(format="rgb24")
                    read += 1
                    yield pixels, np.ones(pixels.shape[:2], bool)
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise InputError(f"cannot decode video {source.path} at frame {start + read}: "
                         f"{exc}") from None
    if read < stop - start:
        raise InputError(f"video {source.path} ends after frame {start + read - 1}, before "
                         f"the {source.frames} frames it declared")


def _indexed_frames(container, stream, start: int):
    """(index, frame) of a video from the key frame at or before frame ``start``, so that a
    task in the middle of a video does not decode it from the beginning. Indices come
    from the timestamps at the average frame rate; where a seek cannot be placed that
    way, decoding starts at frame 0."""
    rate, base, origin = stream.average_rate, stream.time_base, stream.start_time or 0
    if start > 0 and rate and base:
        container.seek(int(origin + start / rate / base), stream=stream, backward=True)
        frames = container.decode(stream)
        first = next(frames, None)
        if first is not None and first.pts is not None:
            index = round(float((first.pts - origin) * base * rate))
            if index <= start:
                yield index, first
                yield from enumerate(frames, index + 1)
                return
        container.seek(origin, stream=stream, backward=True)
    yield from enumerate(container.decode(stream))


def _decode(codes: np.ndarray) -> np.ndarray:
    """(D,) codes -> (D, 3) float64 colours in [0, 1]."""
    return np.stack([codes >> 32, (codes >> 16) & _MASK, codes & _MASK], axis=-1) / float(_MASK)


@dataclass(frozen=True)
class Task:
    """Frames ``start:stop`` of one source, and where they go in the stack's frame list."""

    source: Source
    start: int
    stop: int
    first: int  # index of frame ``start`` among all frames of the collection


def plan_tasks(sources: list[Source]) -> list[Task]:
    """Split the collection into tasks of about ``TASK_MEGAPIXELS`` each; a video's tasks
    start at key frames, so that no task decodes frames of another."""
    tasks, first = [], 0
    for source in sources:
        per_task = max(1, int(TASK_MEGAPIXELS * 1e6 // (source.height * source.width)))
        starts = [k for k in source.keyframes if k < source.frames]
        bounds = [0]
        for k in starts[1:]:
            if k - bounds[-1] >= per_task:
                bounds.append(k)
        for start, stop in zip(bounds, bounds[1:] + [source.frames]):
            tasks.append(Task(source, start, stop, first + start))
        first += source.frames
    return tasks


class ColourCounter:
    """Exact colour counts of frames added one at a time.

    8-bit frames go into a dense table of all 2^24 colours (128 MiB), which costs a
    ``bincount`` per frame; 16-bit frames into sparse sorted tables. ``result`` gives
    one sparse table: sorted codes (16 bits per channel) and opaque pixel counts, with
    count 0 for colours seen only in transparent pixels.
    """

    def __init__(self):
        self.dense = self.seen = None
        self.sparse = (np.zeros(0, np.int64), np.zeros(0, np.int64))

    def add(self, pixels: np.ndarray, opaque: np.ndarray) -> None:
        opaque = opaque.ravel()
        if pixels.dtype == np.uint8:
            codes = pack_codes(pixels, 8)
            if self.dense is None:
                self.dense = np.zeros(1 << 24, np.int64)
                self.seen = np.zeros(1 << 24, bool)
            self.dense += np.bincount(codes[opaque], minlength=1 << 24)
            self.seen[codes[~opaque]] = True
            return
        codes = pack_codes(pixels, 16)
        seen, counts = np.unique(codes[opaque], return_counts=True)
        hidden = np.unique(codes[~opaque])
        self.sparse = merge_counts(self.sparse, merge_counts(
            (seen, counts), (hidden, np.zeros(len(hidden), np.int64))))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        if self.dense is None:
            return self.sparse
        present = np.flatnonzero((self.dense > 0) | self.seen)
        widened = ((present >> 16) * 257 << 32) | (((present >> 8) & 255) * 257 << 16) \
            | ((present & 255) * 257)
        return merge_counts(self.sparse, (widened.astype(np.int64), self.dense[present]))


def count_task(task: Task, max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """Pass 1 of one task: its sparse colour counts (``ColourCounter.result``)."""
    counter = ColourCounter()
    for pixels, opaque in read_frames(task.source, task.start, task.stop, max_pixels):
        counter.add(pixels, opaque)
    return counter.result()


def merge_counts(a: tuple[np.ndarray, np.ndarray],
                 b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Sum of two sparse count tables (sorted codes, counts)."""
    if len(a[0]) == 0:
        return b
    if len(b[0]) == 0:
        return a
    codes, inverse = np.unique(np.concatenate([a[0], b[0]]), return_inverse=True)
    return codes, np.bincount(inverse, np.concatenate([a[1], b[1]]), len(codes)).astype(np.int64)


class ColourIndex:
    """Index of each pixel's colour among the sorted distinct codes of pass 1: a lookup table
    of all 2^24 8-bit colours (64 MiB, one gather per frame), binary search for 16-bit."""

    def __init__(self, codes: np.ndarray):
        self.codes = codes
        channels = np.stack([codes >> 32, (codes >> 16) & _MASK, codes & _MASK], -1)
        eight = np.all(channels % 257 == 0, axis=1)
        small = channels[eight] // 257
        self.table = np.full(1 << 24, -1, np.int32)
        self.table[(small[:, 0] << 16) | (small[:, 1] << 8) | small[:, 2]] = \
            np.flatnonzero(eight).astype(np.int32)

    _built: ClassVar[dict[int, ColourIndex]] = {}

    @classmethod
    def of(cls, codes: np.ndarray) -> ColourIndex:
        """The index of ``codes``, built once per process for the same array (a dask worker
        gets the scattered codes once and runs many tasks on them)."""
        index = cls._built.get(id(codes))
        if index is None or index.codes is not codes:
            cls._built.clear()  # one collection at a time: the 64 MiB table of the last
            index = cls._built[id(codes)] = cls(codes)
        return index

    def __call__(self, pixels: np.ndarray, source: Source) -> np.ndarray:
        if pixels.dtype == np.uint8:
            index = self.table[pack_codes(pixels, 8)]
            if (index < 0).any():
                raise InputError(f"{source.path} changed between the two passes")
            return index
        frame_codes = pack_codes(pixels, 16)
        index = np.minimum(np.searchsorted(self.codes, frame_codes), len(self.codes) - 1)
        if not np.array_equal(self.codes[index], frame_codes):
            raise InputError(f"{source.path} changed between the two passes")
        return index


@dataclass
class Collection:
    """What pass 1 found: the sources, the distinct colours, the palette."""

    sources: list[Source]
    codes: np.ndarray  # (D,) sorted distinct codes
    counts: np.ndarray  # (D,) opaque pixels per colour
    palette: Polytope
    timings: dict[str, float]

    @property
    def names(self) -> list[str]:
        return [name for source in self.sources for name in source.frame_names()]


def decompose_collection(inputs: list, output: str, k: int | None = None,
                         max_error: float | None = None, palette_method: str = "refined",
                         dtype: str = "float32", max_pixels: int = DEFAULT_MAX_PIXELS,
                         client=None, resume: bool = False, force: bool = False,
                         progress: bool = True) -> Collection:
    """Decompose images and videos into a Zarr weight stack ``output`` in two streaming passes.

    Parameters
    ----------
    client : dask.distributed.Client, optional
        Run both passes on its cluster; ``output`` must be a path or fsspec URL that
        every worker can write.
    resume : bool
        Continue a store whose pass 2 was stopped (same inputs and palette settings).
    force : bool
        Replace an existing store.

    Raises
    ------
    InputError
        On unreadable inputs, invalid options, or an existing store (without ``force`` or
        ``resume``).
    """
    k = check_palette_size(k, max_error)
    validate_method(palette_method, PALETTE_METHODS, "palette method")
    check_dtype(dtype)
    swatch, palette_json = palette_paths(output)
    check_apart([output, swatch, palette_json], inputs)
    check_writable([swatch, palette_json], force or resume)
    check_store_output(output, force)
    partial = partial_store(output)
    unfinished = is_stack_store(partial)
    if resume and not unfinished:
        raise InputError(f"--resume: {output} has no unfinished store to finish")
    if unfinished and not (resume or force):
        raise OutputExists(f"output {output} has an unfinished store (use --resume to finish "
                           "it or --force to start afresh)")
    if not resume and _exists(partial):
        if not unfinished:
            raise InputError(f"{partial} is in the way of the output and is not a weight "
                             "stack store: move it away")
        _remove_store(partial)  # our own unfinished store: --force starts afresh
    timings = {}
    start = time.perf_counter()
    sources = find_sources(inputs, max_pixels)
    tasks = plan_tasks(sources)
    codes, counts = _pass1(tasks, max_pixels, client, progress)
    if not counts.any():
        raise InputError("every pixel of every image is fully transparent: there are no colours "
                         "to take a palette from")
    timings["pass1"] = time.perf_counter() - start
    start = time.perf_counter()
    poly = palette_polytope(_decode(codes), counts, k, max_error, palette_method)
    timings["palette"] = time.perf_counter() - start
    collection = Collection(sources, codes, counts, poly, timings)
    start = time.perf_counter()
    store = _open_store(partial, collection, k, max_error, palette_method, dtype, resume)
    weights = rgb_to_mvc_weights(_decode(codes), poly).astype(np.float32)
    todo = [t for t in tasks if not _complete(store, t)]
    _pass2(todo, partial, codes, weights, dtype, max_pixels, client, progress)
    timings["pass2"] = time.perf_counter() - start
    store.attrs["meta"] = json.dumps({**json.loads(store.attrs["meta"]), "timings": timings})
    _publish_store(partial, output, force)
    with atomic_outputs(force or resume) as stage:
        palette_swatch(poly.vertices).save(stage(swatch), format="PNG")
        with open(stage(palette_json), "w") as f:
            write_palette_json(f, poly.vertices)
    return collection


def palette_paths(output: str) -> tuple[Path, Path]:
    """The palette swatch and JSON beside a store, named after it (``w.zarr``:
    ``w.palette.png``, ``w.palette.json``)."""
    stem = str(output).rstrip("/")
    stem = stem[: -len(".zarr")] if stem.endswith(".zarr") else stem
    return Path(stem + ".palette.png"), Path(stem + ".palette.json")


def _pass1(tasks, max_pixels, client, progress):
    with _bar("pass 1 (colours)", tasks, progress) as bar:
        if client is None:
            counter = ColourCounter()
            for _, frames in _frames_in_order(tasks, max_pixels):
                for pixels, opaque in _counted(frames, bar):
                    counter.add(pixels, opaque)
            return counter.result()
        return _tree_sum(client, client.map(count_task, tasks, max_pixels=max_pixels,
                                            pure=False), tasks, bar)


def _tree_sum(client, counts: list, tasks: list[Task], bar):
    """Merge the tasks' count tables pairwise as they arrive; no table is held longer than
    its merge needs it."""
    finished = _progress(counts, tasks, bar)
    while len(counts) > 1:
        pairs = [counts[i:i + 2] for i in range(0, len(counts), 2)]
        counts = [client.submit(merge_counts, *pair, pure=False) if len(pair) == 2 else pair[0]
                  for pair in pairs]
    for _ in finished:
        pass
    return counts[0].result()


def _pass2(tasks, output, codes, weights, dtype, max_pixels, client, progress):
    with _bar("pass 2 (weights)", tasks, progress) as bar:
        if client is None:
            index = ColourIndex(codes)
            for task, frames in _frames_in_order(tasks, max_pixels):
                write_task(task, output, index, weights, dtype, max_pixels,
                           _counted(frames, bar))
            return
        shared_codes, shared_weights = client.scatter([codes, weights], broadcast=True)
        written = client.map(write_task, tasks, output=output, index=shared_codes,
                             weights=shared_weights, dtype=dtype, max_pixels=max_pixels,
                             pure=False)
        for _ in _progress(written, tasks, bar):
            pass


def _counted(frames, bar):
    """The frames, advancing ``bar`` by each one's pixels."""
    for pixels, opaque in frames:
        yield pixels, opaque
        bar.update(pixels.shape[0] * pixels.shape[1])


def _progress(futures: list, tasks: list[Task], bar):
    """An iterator over the tasks' futures as they finish, advancing ``bar`` and raising
    the first error; it holds each future only until it has finished."""
    from distributed import as_completed

    pixels = {future.key: _pixels(task) for future, task in zip(futures, tasks)}

    def finish(future) -> None:
        future.result()  # raises the task's error here
        bar.update(pixels[future.key])

    return (finish(future) for future in as_completed(futures))


def write_task(task: Task, output: str, index, weights: np.ndarray, dtype: str,
               max_pixels: int = DEFAULT_MAX_PIXELS, frames=None) -> int:
    """Pass 2 of one task: each frame's weights into its chunk, then mark it complete.

    ``index`` is a ``ColourIndex``, or the sorted distinct codes to build one from (on a
    dask worker, once per worker: ``ColourIndex.of``); ``frames`` the task's frames when
    the caller is already reading them (``_frames_in_order``).
    """
    import zarr

    if not isinstance(index, ColourIndex):
        index = ColourIndex.of(index)
    store = zarr.open_group(output, mode="r+")
    array = store[_array_name(task.source, store)]
    complete = store["complete"]
    if frames is None:
        frames = read_frames(task.source, task.start, task.stop, max_pixels)
    gathered = None  # one buffer for the frames of a task: no fresh pages per frame
    for offset, (pixels, _) in enumerate(frames):
        codes = index(pixels, task.source)
        if gathered is None or len(gathered) != codes.size:
            gathered = np.empty((codes.size, weights.shape[1]), weights.dtype)
        frame = stored_weights(np.take(weights, codes.ravel(), axis=0, out=gathered), dtype)
        frame = frame.reshape(*pixels.shape[:2], -1)
        if task.source.video:
            array[task.start + offset] = frame
        else:
            array[...] = frame
        complete[task.first + offset] = True
    return task.stop - task.start


def _frames_in_order(tasks: list[Task], max_pixels: int):
    """(task, its frames) for tasks in order; a video whose tasks follow each other is
    decoded once, not again from its first frame for every task."""
    source = position = frames = None
    for task in tasks:
        if task.source != source or task.start != position:
            frames = read_frames(task.source, task.start, None, max_pixels)
        source, position = task.source, task.stop
        yield task, itertools.islice(frames, task.stop - task.start)


def _pixels(task: Task) -> int:
    return (task.stop - task.start) * task.source.height * task.source.width


def _bar(label: str, tasks: list[Task], progress: bool):
    """A progress bar over the tasks' pixels (shown as Mpx, Mpx/s)."""
    from tqdm import tqdm

    return tqdm(total=sum(map(_pixels, tasks)), desc=label, unit="px", unit_scale=True,
                disable=not progress)


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
            raise OutputExists(f"output {path} already exists (use --force to replace it)")
        return
    if not os.path.lexists(path) or (os.path.isdir(path) and not os.listdir(path)):
        check_parent(Path(path))
        return
    if not is_stack_store(path):
        raise InputError(f"output {path} exists and is not a weight stack store: refusing to "
                         "replace it, even with --force (choose another -o)")
    if not force:
        raise OutputExists(f"output {path} already exists (use --force to replace it)")


def partial_store(output: str) -> str:
    """Where the store ``output`` is built until its pass 2 completes: a hidden sibling
    (``.w.zarr.partial``) that ``--resume`` finds after a kill; a URL is built in place."""
    if "://" in output:
        return output
    path = Path(output.rstrip("/"))
    return str(path.with_name(f".{path.name}.partial"))


def _publish_store(partial: str, output: str, force: bool) -> None:
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
        _remove_store(trash)
        return
    try:
        rename_no_replace(Path(partial), Path(output))
    except FileExistsError:
        raise OutputExists(f"output {output} appeared while writing; it was kept, and the new "
                           f"store waits in {partial} (--resume publishes it)") from None


def _remove_store(path: str) -> None:
    """Delete a store (or its trash folder) that this package made."""
    shutil.rmtree(path, ignore_errors=True)


def _array_name(source: Source, store) -> str:
    return store.attrs["arrays"][source.name]


def _open_store(output, collection: Collection, k, max_error, palette_method, dtype, resume):
    """The Zarr group of the stack: created (replacing one), or reopened to resume."""
    import zarr

    from . import __version__

    palette = collection.palette.vertices.astype(np.float32)
    if resume:
        store = zarr.open_group(output, mode="r+")
        if (store.attrs.get("names") != collection.names
                or not np.array_equal(np.asarray(store.attrs["palette"], np.float32), palette)):
            raise InputError(f"--resume: {output} holds another collection or palette; start "
                             "afresh with --force")
        return store
    store = zarr.open_group(output, mode="w" if is_stack_store(output) else "w-")
    m = n_terms(len(palette), Basis.ADDITIVE)
    arrays = {}
    for i, source in enumerate(collection.sources):
        name = f"weights_{i:04d}"
        shape = (source.height, source.width, m)
        if source.video:
            store.create_array(name, shape=(source.frames, *shape), chunks=(1, *shape),
                               dtype=dtype, compressors=_compressors())
        else:
            store.create_array(name, shape=shape, chunks=shape, dtype=dtype,
                               compressors=_compressors())
        arrays[source.name] = name
    store.create_array("complete", shape=(len(collection.names),), chunks=(1,), dtype="bool",
                       fill_value=False)
    videos = {s.name: s.fps for s in collection.sources if s.video}
    meta = {"version": __version__, "k": k, "max_error": max_error,
            "palette_method": palette_method, "dtype": dtype, "videos": videos,
            "n_pixels": int(collection.counts.sum()), "n_colours": len(collection.codes)}
    store.attrs.update({"format": FORMAT, "palette": palette.tolist(), "basis": "additive",
                        "order": 1, "names": collection.names, "method": "mvc",
                        "arrays": arrays, "meta": json.dumps(meta)})
    return store


def _compressors() -> list:
    """Blosc LZ4 with byte shuffle at level 1: measured at 0.2 s to write a 2 MP frame of
    6 float32 channels, where Zarr's default Zstandard took 0.56 s."""
    from zarr.codecs import BloscCodec

    return [BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")]


def _complete(store, task: Task) -> bool:
    return bool(store["complete"][task.first:task.first + task.stop - task.start].all())


def write_zarr_stack(stack: WeightStack, path: str | os.PathLike, force: bool = False) -> None:
    """Write any stack as a Zarr store, one frame at a time (frames ``NAME#i`` of a video
    into one array), built beside ``path`` and published whole (``outputs.publish_folder``).
    """
    import zarr

    from .outputs import publish_folder

    check_store_output(path, force)
    groups: dict[str, list[int]] = {}
    for i, name in enumerate(stack.names):
        groups.setdefault(name.split("#")[0] if "#" in name else name, []).append(i)
    with publish_folder(path, force) as staging:
        store = zarr.open_group(str(staging), mode="w")
        arrays = {}
        for n, (source, indices) in enumerate(groups.items()):
            first = stack.weights[indices[0]]
            array = f"weights_{n:04d}"
            video = "#" in stack.names[indices[0]]
            shape = (len(indices), *first.shape) if video else first.shape
            data = store.create_array(array, shape=shape, chunks=(1, *first.shape) if video
                                      else first.shape, dtype=first.dtype,
                                      compressors=_compressors())
            for j, i in enumerate(indices):
                if video:
                    data[j] = stack.weights[i]
                else:
                    data[...] = stack.weights[i]
            arrays[source] = array
        store.create_array("complete", shape=(len(stack.names),), chunks=(1,), dtype="bool",
                           fill_value=True)
        store.attrs.update({"format": FORMAT, "palette": np.asarray(stack.palette).tolist(),
                            "basis": str(stack.basis), "order": stack.order,
                            "names": list(stack.names), "method": stack.method,
                            "arrays": arrays, "meta": json.dumps(stack.meta)})


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
                             f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                             ) from None
        if not np.isfinite(weights).all():
            raise InputError(f"{self.path}: weights of {self.names[i]} hold NaN or infinity")
        return weights


_ARRAY_NAME = re.compile(r"^weights_\d{4,}$")


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
        raise InputError(f"{path} is incomplete: finish it with palette-decompose ... --resume")
    try:
        store = zarr.open_group(path, mode="r")
        attrs = dict(store.attrs)
    except Exception as exc:  # noqa: BLE001 - zarr and json raise many kinds
        raise InputError(f"{path} is not a readable Zarr weight stack: "
                         f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
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
        raise InputError(f"{path} is incomplete: finish it with palette-decompose ... --resume")
    frames = []
    for source, name in arrays.items():
        try:
            data = store[name]
        except KeyError:
            raise InputError(f"{path}: weights of {source} ({name}) are missing") from None
        video = data.ndim == 4
        shape = data.shape[1:] if video else data.shape
        pixels = shape[0] * shape[1] if len(shape) == 3 else 0
        if (len(shape) != 3 or shape[-1] != m or not 0 < pixels <= max_pixels
                or data.dtype not in (np.float32, np.float16)
                or (video and not 0 < data.shape[0] <= len(names))
                or data.chunks != ((1, *shape) if video else shape)):
            raise InputError(f"{path}: weights of {source} must be float32/float16 frames of at "
                             f"most {max_pixels} pixels and {m} channels, one chunk a frame, "
                             f"got {data.dtype} {data.shape} in chunks {data.chunks}")
        missing = data.nchunks - data.nchunks_initialized
        if missing:
            raise InputError(f"{path}: weights of {source} miss {missing} of {data.nchunks} "
                             "chunks")
        frames += [(name, i) for i in range(data.shape[0])] if video else [(name, None)]
    if len(frames) != len(names):
        raise InputError(f"{path}: {len(names)} names but {len(frames)} weight frames")
    return WeightStack(palette.astype(np.float32), LazyWeights(store, frames, names, path),
                       names, str(attrs.get("method", "mvc")), basis, order, meta=meta)
