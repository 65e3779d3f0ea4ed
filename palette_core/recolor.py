"""Recolouring a weight stack: every image (and every video) again, with another palette."""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from .basis import weights_to_rgb
from .outputs import atomic_outputs, check_writable, inside, save_image
from .stack import WeightStack


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
    images = [(i, name) for i, name in enumerate(stack.names)
              if name.split("#")[0] not in videos]
    targets += [inside(folder, name if "#" not in name else f"{name}.png") for _, name in images]
    check_writable(targets, force)

    def recoloured(i: int) -> np.ndarray:
        return weights_to_rgb(stack.weights[i], palette, stack.basis, stack.order)

    with atomic_outputs(force) as stage:
        for video, path in zip(videos, targets):
            indices = [i for i, name in enumerate(stack.names) if name.split("#")[0] == video]
            write_video(stage(path), (recoloured(i) for i in indices), videos[video])
        for (i, _), path in zip(images, targets[len(videos):]):
            save_image(stage(path), recoloured(i))
    return targets


def write_video(path: Path, frames, fps: float) -> None:
    """Encode float (H, W, 3) frames in [0, 1] as H.264 (x264 ``veryfast``, CRF 18; MPEG-4
    Part 2 where PyAV lacks x264)."""
    import av

    with av.open(str(path), mode="w") as container:
        codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
        stream = None
        for rgb in frames:
            data = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
            if stream is None:
                options = {"preset": "veryfast", "crf": "18"} if codec == "libx264" else {}
                stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001),
                                              options=options)
                stream.height, stream.width = data.shape[0] // 2 * 2, data.shape[1] // 2 * 2
                stream.pix_fmt = "yuv420p"
            frame = av.VideoFrame.from_ndarray(data[: stream.height, : stream.width],
                                               format="rgb24")
            container.mux(stream.encode(frame))
        if stream is not None:
            container.mux(stream.encode())
