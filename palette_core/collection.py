"""Collections beyond memory: two streaming passes into a chunked Zarr weight stack.

Pass 1 reads the images and video frames (``sources``) one at a time and merges
their exact colour counts (``colour_counts``); the palette comes from the merged
counts, as for ``decompose``. Pass 2 computes the weights of every distinct colour
once and writes each frame's weights into its own chunk of the store
(``stack.zarr``, docs/formats.md). Memory holds one frame and the distinct colours,
never the collection.

Both passes run on a dask.distributed cluster when one is given (``client``):
pass 1 as a tree reduction of the per-task counts, pass 2 as one task per group
of frames, each writing its own chunks of the store; the palette is the same to
the bit. A store records the frames it holds (``complete``), so a pass 2 that
was killed resumes where it stopped.
"""

from __future__ import annotations

import itertools
import json
import os
import time
from dataclasses import dataclass

import numpy as np

from .basis import Basis
from .colour_counts import ColourCounter, ColourIndex, decode_codes, merge_counts
from .errors import InputError
from .io import DEFAULT_MAX_PIXELS
from .outputs import atomic_outputs, check_apart, check_writable
from .palette_file import palette_paths, write_palette_json
from .palettes import PALETTE_METHODS, check_palette_size, palette_polytope
from .polytope import Polytope
from .registry import check_options
from .sources import Source, find_sources, read_frames
from .stack import WeightStack, check_dtype, stored_weights
from .stack.zarr import (
    check_store_output,
    create_store,
    is_stack_store,
    partial_store,
    publish_store,
    remove_store,
)
from .swatch import palette_swatch
from .version import __version__
from .weights import check_weight_method, colour_weights

#: Megapixels of one task: a whole image, or a run of frames of one video.
TASK_MEGAPIXELS = 8.0


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


def count_task(task: Task, max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """Pass 1 of one task: its sparse colour counts (``ColourCounter.result``)."""
    counter = ColourCounter()
    for pixels, opaque in read_frames(task.source, task.start, task.stop, max_pixels):
        counter.add(pixels, opaque)
    return counter.result()


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
                         progress: bool = True, method: str = "mvc",
                         method_options: dict | None = None,
                         palette_options: dict | None = None) -> Collection:
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
    method, method_options : str, dict
        A per-colour weight method (``weights.WEIGHT_METHODS``) and its options.
    palette_options : dict
        Options of ``palette_method``.

    Raises
    ------
    InputError
        On unreadable inputs, invalid options, or an existing store (without ``force`` or
        ``resume``).
    """
    k = check_palette_size(k, max_error)
    method_options, palette_options = method_options or {}, palette_options or {}
    check_options(PALETTE_METHODS, palette_method, "palette method", palette_options)
    check_weight_method(method, method_options, stream=True)
    check_dtype(dtype)
    swatch, palette_json = palette_paths(output)
    check_apart([output, swatch, palette_json], inputs)
    check_writable([swatch, palette_json], force or resume)
    check_store_output(output, force)
    partial = partial_store(output)
    unfinished = is_stack_store(partial)
    if resume and not unfinished:
        raise InputError(f"{output} has no unfinished store to finish", "resume")
    if unfinished and not (resume or force):
        raise InputError(f"output {output} has an unfinished store",
                         fixes=[("resume", "to finish it"), ("force", "to start afresh")])
    if not resume and os.path.lexists(partial):
        if not unfinished:
            raise InputError(f"{partial} is in the way of the output and is not a weight "
                             "stack store: move it away")
        remove_store(partial)  # our own unfinished store: --force starts afresh
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
    poly = palette_polytope(decode_codes(codes), counts, k, max_error, palette_method,
                            **palette_options)
    timings["palette"] = time.perf_counter() - start
    collection = Collection(sources, codes, counts, poly, timings)
    start = time.perf_counter()
    store = _open_store(partial, collection, method, dtype, resume, {
        "k": k, "max_error": max_error, "palette_method": palette_method,
        "palette_options": palette_options, "method_options": method_options})
    weights = colour_weights(decode_codes(codes), poly, method,
                             **method_options).astype(np.float32)
    todo = [t for t in tasks if not _complete(store, t)]
    _pass2(todo, partial, codes, weights, dtype, max_pixels, client, progress)
    timings["pass2"] = time.perf_counter() - start
    store.attrs["meta"] = json.dumps({**json.loads(store.attrs["meta"]), "timings": timings})
    publish_store(partial, output, force)
    with atomic_outputs(force or resume) as stage:
        palette_swatch(poly.vertices).save(stage(swatch), format="PNG")
        with open(stage(palette_json), "w") as f:
            write_palette_json(f, poly.vertices)
    return collection


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


def _array_name(source: Source, store) -> str:
    return store.attrs["arrays"][source.name]


def _open_store(output, collection: Collection, method: str, dtype: str, resume: bool,
                settings: dict):
    """The Zarr group of the stack: created, or reopened to resume."""
    import zarr

    palette = collection.palette.vertices.astype(np.float32)
    if resume:
        store = zarr.open_group(output, mode="r+")
        if (store.attrs.get("names") != collection.names
                or not np.array_equal(np.asarray(store.attrs["palette"], np.float32), palette)):
            raise InputError(f"{output} holds another collection or palette", "resume",
                             [("force", "to start afresh")])
        return store
    meta = {"version": __version__, **settings, "dtype": dtype,
            "videos": {s.name: s.fps for s in collection.sources if s.video},
            "n_pixels": int(collection.counts.sum()), "n_colours": len(collection.codes)}
    header = WeightStack(palette, [], collection.names, method, Basis.ADDITIVE, 1, meta=meta)
    sources = [(s.name, s.frames if s.video else None, (s.height, s.width, len(palette)))
               for s in collection.sources]
    return create_store(output, header, sources, dtype, complete=False)


def _complete(store, task: Task) -> bool:
    return bool(store["complete"][task.first:task.first + task.stop - task.start].all())
