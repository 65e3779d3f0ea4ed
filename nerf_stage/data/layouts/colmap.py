"""A COLMAP model (``sparse/0``, text or binary; ``data.colmap``) with its photos in
``images/``, read in a normalised frame, every eighth photo held out.
"""

from __future__ import annotations

from pathlib import Path

from ..colmap import check_upright, find_model, model_frames, model_points, read_model
from .common import Frames, Layout, frame_path, holdout


def read(root: Path, frames_outside: bool) -> Frames:
    """A COLMAP model (``sparse/0``, text or binary) with its photos in ``images/``."""
    model = find_model(root)
    reconstruction = read_model(model)
    names, poses, cameras, distortions = model_frames(reconstruction, str(root))
    names = [frame_path(f"images/{name}", f"{model}: image", root, frames_outside)
             for name in names]
    check_upright(root, names, f"the COLMAP model in {model}")
    return Frames(names, holdout(len(names)), poses, cameras, distortions,
                  points=model_points(reconstruction))


LAYOUT = Layout("a COLMAP model (sparse/0)", lambda root: find_model(root) is not None, read)
