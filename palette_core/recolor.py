"""Recolouring a weight stack: every image (and every video) again, with another palette."""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from .basis import weights_to_rgb
from .errors import InputError
from .folders import inside
from .outputs import atomic_outputs, check_writable, save_image
from .selection import LocalEdit, recolor_local
from .sources import VIDEO_CONTAINERS
from .stack import WeightStack, video_of


def recolor_stack(stack: WeightStack, palette: np.ndarray, folder: str | os.PathLike,
                  force: bool = False, frames: bool = False,
                  edits: list[LocalEdit] = ()) -> list[Path]:
    """Write every image of ``stack`` recoloured with ``palette`` (K, 3) under its own name,
    and with each of ``edits``' palettes inside its selection (``selection.recolor_local``).

    The frames of a video (names ``clip.mp4#000123``, ``stack.meta["videos"]`` giving
    its frame rate) become ``folder/clip.mp4`` at the source frame rate, or, with
    ``frames``, one PNG each (``clip.mp4#000123.png``). Frames are read and written
    one at a time.

    Returns
    -------
    list of Path
        The files written, all published together (``outputs.atomic_outputs``).

    Raises
    ------
    InputError
        If an output exists (without ``force``), the folder cannot be written, or the
        selection does not fit the stack (a mask of another size, a missing mask, a
        palette colour the stack does not have).
    """
    videos = {} if frames else stack.meta.get("videos", {})
    targets = [inside(folder, video) for video in videos]
    images = [(i, name) for i, name in enumerate(stack.names) if video_of(name) not in videos]
    targets += [inside(folder, name if video_of(name) is None else f"{name}.png")
                for _, name in images]
    check_writable(targets, force)
    for path in targets[:len(videos)]:
        video_codec(path)  # before anything is written

    longest = max(max(stack.weights[i].shape[:2]) for i in range(len(stack.names)))
    for edit in edits:
        edit.selection.check(len(stack.palette), longest)

    def recoloured(i: int) -> np.ndarray:
        weights = np.asarray(stack.weights[i])
        if not edits:
            return weights_to_rgb(weights, palette, stack.basis, stack.order)
        return recolor_local(weights, palette, edits, stack.names[i], stack.basis, stack.order)

    with atomic_outputs(force) as stage:
        for video, path in zip(videos, targets):
            indices = [i for i, name in enumerate(stack.names) if video_of(name) == video]
            write_video(stage(path), (recoloured(i) for i in indices), videos[video], str(path))
        for (i, _), path in zip(images, targets[len(videos):]):
            save_image(stage(path), recoloured(i))
    return targets


#: Options of the encoders in ``sources.VIDEO_CONTAINERS`` (x264 ``veryfast``, CRF 18).
_CODEC_OPTIONS = {"libx264": {"preset": "veryfast", "crf": "18"},
                  "libvpx-vp9": {"crf": "18", "b": "0", "deadline": "realtime"}}


def video_codec(path: str | os.PathLike) -> str:
    """The encoder ``write_video`` uses for ``path``'s container (its suffix).

    Raises
    ------
    InputError
        For a container without an encoder in this PyAV.
    """
    import av

    suffix = Path(path).suffix.lower()
    codec = next((c for c in VIDEO_CONTAINERS.get(suffix, ()) if c in av.codecs_available), None)
    if codec is None:
        raise InputError(f"cannot write video {path}: no encoder for {suffix or 'it'} "
                         f"(containers: {', '.join(VIDEO_CONTAINERS)})")
    return codec


def write_video(path: Path, frames, fps: float, name: str | None = None) -> None:
    """Encode float (H, W, 3) frames in [0, 1] into the container that ``name``'s suffix
    names, with its encoder (``video_codec``); odd sizes lose their last row or column
    (4:2:0).

    Raises
    ------
    InputError
        Naming the video (``name``, else ``path``) if its container has no encoder, its
        frames are smaller than 2x2 or differ in size, or the encoder fails.
    """
    import av

    name = name or str(path)
    codec = video_codec(name)
    try:
        with av.open(str(path), mode="w") as container:  # staged with the same suffix
            stream = size = None
            for rgb in frames:
                data = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
                if stream is None:
                    size = data.shape[:2]
                    if min(size) < 2:
                        raise InputError(f"video {name}: frames of {size[1]}x{size[0]} pixels "
                                         "cannot be encoded (at least 2x2)")
                    stream = container.add_stream(
                        codec, rate=Fraction(fps).limit_denominator(1001),
                        options=_CODEC_OPTIONS.get(codec, {}))
                    stream.height, stream.width = size[0] // 2 * 2, size[1] // 2 * 2
                    stream.pix_fmt = "yuv420p"
                if data.shape[:2] != size:
                    raise InputError(f"video {name}: frames differ in size")
                frame = av.VideoFrame.from_ndarray(data[: stream.height, : stream.width],
                                                   format="rgb24")
                container.mux(stream.encode(frame))
            if stream is not None:
                container.mux(stream.encode())
    except (av.FFmpegError, ValueError) as exc:
        raise InputError(f"cannot encode video {name}: {exc}") from None
