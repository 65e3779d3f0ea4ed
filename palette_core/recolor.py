"""Recolouring a weight stack: every image (and every video) again, with another palette."""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from .basis import weights_to_rgb
from .errors import InputError
from .outputs import atomic_outputs, check_writable, inside, save_image
from .stack import WeightStack, video_of


def recolor_stack(stack: WeightStack, palette: np.ndarray, folder: str | os.PathLike,
                  force: bool = False, frames: bool = False) -> list[Path]:
    """Write every image of ``stack`` recoloured with ``palette`` (K, 3) under its own name.

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
        If an output exists (without ``force``) or the folder cannot be written.
    """
    videos = {} if frames else stack.meta.get("videos", {})
    targets = [inside(folder, video) for video in videos]
    images = [(i, name) for i, name in enumerate(stack.names) if video_of(name) not in videos]
    targets += [inside(folder, name if video_of(name) is None else f"{name}.png")
                for _, name in images]
    check_writable(targets, force)

    def recoloured(i: int) -> np.ndarray:
        return weights_to_rgb(stack.weights[i], palette, stack.basis, stack.order)

    with atomic_outputs(force) as stage:
        for video, path in zip(videos, targets):
            indices = [i for i, name in enumerate(stack.names) if video_of(name) == video]
            write_video(stage(path), (recoloured(i) for i in indices), videos[video], str(path))
        for (i, _), path in zip(images, targets[len(videos):]):
            save_image(stage(path), recoloured(i))
    return targets


def write_video(path: Path, frames, fps: float, name: str | None = None) -> None:
    """Encode float (H, W, 3) frames in [0, 1] as H.264 (x264 ``veryfast``, CRF 18; MPEG-4
    Part 2 where PyAV lacks x264); odd sizes lose their last row or column (4:2:0).

    Raises
    ------
    InputError
        Naming the video (``name``, else ``path``) if its frames are smaller than 2x2 or
        differ in size, or the encoder fails.
    """
    import av

    name = name or str(path)
    try:
        with av.open(str(path), mode="w") as container:
            codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
            stream = size = None
            for rgb in frames:
                data = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
                if stream is None:
                    size = data.shape[:2]
                    if min(size) < 2:
                        raise InputError(f"video {name}: frames of {size[1]}x{size[0]} pixels "
                                         "cannot be encoded (at least 2x2)")
                    options = {"preset": "veryfast", "crf": "18"} if codec == "libx264" else {}
                    stream = container.add_stream(
                        codec, rate=Fraction(fps).limit_denominator(1001), options=options)
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
