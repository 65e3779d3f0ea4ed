"""Sources of a collection: image files and videos, one reader per kind.

``find_sources`` probes each file without decoding it (an image's header; a video's
stream, frame count, rate and key frames), checking declared sizes against
``max_pixels``; ``read_frames`` decodes frames one at a time and turns every decode
error into one line naming the file and frame. Videos are anything PyAV reads
(``VIDEO_SUFFIXES``); their frames are named ``clip.mp4#000123`` in stacks
(``stack.frame_name``).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .io import DEFAULT_MAX_PIXELS, IMAGE_SUFFIXES, find_images, image_size, load_image
from .stack import MAX_FPS, frame_name

#: The video containers read as sources (anything PyAV opens) and written back by
#: ``recolor.write_video``: each suffix with its encoders, best first (H.264 where the
#: container holds it, VP9 for WebM, MPEG-4 Part 2 as the fallback). A new container is
#: one entry here.
VIDEO_CONTAINERS = {
    ".mp4": ("libx264", "mpeg4"), ".m4v": ("libx264", "mpeg4"), ".mov": ("libx264", "mpeg4"),
    ".mkv": ("libx264", "mpeg4"), ".avi": ("mpeg4", "mjpeg"), ".webm": ("libvpx-vp9", "libvpx"),
}
VIDEO_SUFFIXES = tuple(VIDEO_CONTAINERS)


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
        return [frame_name(self.name, i) for i in range(self.frames)] if self.video else [self.name]


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
        width, height = image_size(path, max_pixels)
        return Source(str(path), name, 1, height, width)
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            height, width = stream.codec_context.height, stream.codec_context.width
            if width * height > max_pixels:
                raise InputError(f"video {path} is {width}x{height}, more than {max_pixels} "
                                 "pixels", fixes=[("max_pixels", "to allow more")])
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
