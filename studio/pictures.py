"""What the viewport shows: 8-bit pictures, letterboxed to the browser's aspect, and the
browser's camera in our convention."""

from __future__ import annotations

import numpy as np
import viser.transforms as tf

from palette_core.errors import InputError

BACKDROP = np.array([33, 33, 38], np.uint8)  # letterbox bars around a photo
MAX_ASPECT = 8.0  # widest (and tallest) view drawn: a browser's aspect cannot size a render


def to_bytes(image: np.ndarray) -> np.ndarray:
    """Floats in [0, 1] -> uint8, rounded."""
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)


def letterbox(image: np.ndarray, aspect: float) -> np.ndarray:
    """(H, W, 3) uint8 -> padded with ``BACKDROP`` to width / height = ``aspect``, centred."""
    h, w = image.shape[:2]
    width, height = max(w, round(h * aspect)), max(h, round(w / aspect))
    canvas = np.empty((height, width, 3), image.dtype)
    canvas[:] = BACKDROP
    top, left = (height - h) // 2, (width - w) // 2
    canvas[top:top + h, left:left + w] = image
    return canvas


def bounded_aspect(camera) -> float:
    """The browser's width / height, within [1 / MAX_ASPECT, MAX_ASPECT] (1 if not finite)."""
    aspect = float(camera.aspect)
    return float(np.clip(aspect, 1 / MAX_ASPECT, MAX_ASPECT)) if np.isfinite(aspect) else 1.0


def camera_pose(camera) -> np.ndarray:
    """(4, 4) camera-to-world pose in our OpenGL convention from a viser camera (OpenCV
    axes: looks along +z, +y down)."""
    wxyz, position = (np.asarray(v, np.float64) for v in (camera.wxyz, camera.position))
    if wxyz.shape != (4,) or position.shape != (3,) or not (
            np.isfinite(wxyz).all() and np.isfinite(position).all() and wxyz @ wxyz > 0):
        raise InputError("the browser's camera must be a finite position and rotation")
    pose = np.eye(4)
    pose[:3, :3] = tf.SO3(wxyz / np.linalg.norm(wxyz)).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = position
    return pose
