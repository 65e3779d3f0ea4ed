"""Pinhole cameras in the Blender / NeRF convention: intrinsics, rays, poses on rigs.

Poses are camera-to-world (4, 4) matrices with OpenGL axes: the camera looks down
its -z axis, +y is up in the image, +x to the right. World +y is up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from palette_core.errors import InputError

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0  # low-discrepancy step for elevations
SPLIT_PHASES = {"train": 0.0, "val": 1.0 / 3.0, "test": 2.0 / 3.0}  # views of splits interleave


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) camera-to-world pose of a camera at ``eye`` looking at ``target``.

    Examples
    --------
    >>> (look_at([4.0, 0, 0], [0.0, 0, 0]).round(6) + 0.0).tolist()  # + 0.0 clears -0.0
    [[0.0, 0.0, 1.0, 4.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-12:  # looking straight up or down: any right will do
        right = np.cross(forward, [0.0, 0.0, -1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :4] = np.stack([right, np.cross(right, forward), -forward, eye], axis=1)
    return pose


#: Most pixels of one camera's image: a file from elsewhere cannot size a render beyond it.
MAX_CAMERA_PIXELS = 1 << 26


@dataclass
class Intrinsics:
    """Pinhole camera shared by all frames: focal lengths and principal point in pixels.

    Raises
    ------
    InputError
        Unless the sizes are whole, positive and at most ``MAX_CAMERA_PIXELS`` in all, the
        focal lengths finite and positive, and the principal point finite and within one
        image size of the image (cameras come from files we did not write).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        w, h, fx, fy, cx, cy = (self.width, self.height, self.fx, self.fy, self.cx, self.cy)
        sizes = all(isinstance(v, (int, np.integer)) and v >= 1 for v in (w, h))
        numbers = all(isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
                      and math.isfinite(v) for v in (fx, fy, cx, cy))
        if not (sizes and numbers and w * h <= MAX_CAMERA_PIXELS and fx > 0 and fy > 0
                and -w <= cx <= 2 * w and -h <= cy <= 2 * h):
            raise InputError(f"a camera of {w!r}x{h!r} pixels, focal lengths {fx!r}, {fy!r} and "
                             f"principal point ({cx!r}, {cy!r}): sizes must be whole and "
                             f"positive (at most {MAX_CAMERA_PIXELS} pixels), focal lengths "
                             "finite and positive, the principal point finite and near the "
                             "image")
        # plain numbers: a camera is written into JSON and checkpoints read as data
        self.width, self.height = int(w), int(h)
        self.fx, self.fy, self.cx, self.cy = float(fx), float(fy), float(cx), float(cy)

    def downscaled(self, factor: int) -> Intrinsics:
        """The camera of images ``factor`` times smaller (whole pixels, as ``data`` crops
        them): focal lengths and principal point scale with the pixels."""
        return Intrinsics(self.width // factor, self.height // factor, self.fx / factor,
                          self.fy / factor, self.cx / factor, self.cy / factor)

    def upscaled(self, factor: int) -> Intrinsics:
        """The camera of images ``factor`` times larger, from the same viewpoint."""
        return Intrinsics(self.width * factor, self.height * factor, self.fx * factor,
                          self.fy * factor, self.cx * factor, self.cy * factor)

    @classmethod
    def from_dict(cls, data, source: str) -> Intrinsics:
        """The camera of a checkpoint's ``intrinsics`` (checked like any camera).

        Raises
        ------
        InputError
            Naming ``source``.
        """
        names = ("width", "height", "fx", "fy", "cx", "cy")
        if not isinstance(data, dict) or set(data) != set(names):
            raise InputError(f"{source}: intrinsics must hold {', '.join(names)}")
        return checked_camera(source, *(data[n] for n in names))


def checked_camera(source: str, *values) -> Intrinsics:
    """``Intrinsics(*values)``, its InputError naming ``source``."""
    try:
        return Intrinsics(*values)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None


def focal_length(width: int, fov_x: float) -> float:
    """Focal length in pixels for a horizontal field of view ``fov_x`` in radians."""
    return 0.5 * width / math.tan(0.5 * fov_x)


def focal_from_fov(width: int, fov_x_degrees: float) -> float:
    """Focal length in pixels for a horizontal field of view in degrees."""
    return focal_length(width, math.radians(fov_x_degrees))


def project(points: np.ndarray, pose: np.ndarray,
            intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P,) pixel coordinates x, y and depth (along the view's axis) of the (P, 3) world
    ``points`` in the view of camera-to-world ``pose``; x and y are meaningless where the
    depth is not positive (behind the camera)."""
    local = (points - pose[:3, 3]) @ pose[:3, :3]
    depth = -local[:, 2]
    safe = np.where(depth > 0, depth, 1.0)
    return (intrinsics.cx + intrinsics.fx * local[:, 0] / safe,
            intrinsics.cy - intrinsics.fy * local[:, 1] / safe, depth)


def camera_rays(pose: np.ndarray, intrinsics: Intrinsics,
                supersampling: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World rays of one camera (OpenGL axes: looks along -z) through the centres of an
    n x n grid of sub-pixels in every pixel (n = ``supersampling``; 1: the pixel centres).

    Returns
    -------
    origins, directions : (H, W, n^2, 3) float64
        Directions are unit vectors; sub-pixels in row-major order.
    """
    sub = (np.arange(supersampling) + 0.5) / supersampling
    j = np.arange(intrinsics.height)[:, None, None, None] + sub[:, None]  # (H, 1, n, 1)
    i = np.arange(intrinsics.width)[None, :, None, None] + sub             # (1, W, 1, n)
    j, i = (a.reshape(intrinsics.height, intrinsics.width, -1) for a in np.broadcast_arrays(j, i))
    local = np.stack([(i - intrinsics.cx) / intrinsics.fx, -(j - intrinsics.cy) / intrinsics.fy,
                      -np.ones_like(i)], axis=-1)
    directions = local @ pose[:3, :3].T
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    return np.broadcast_to(pose[:3, 3], directions.shape).copy(), directions


def rig_poses(rig: str, n: int, target, radius: float, elevation: tuple[float, float],
              arc: float = 360.0, phase: float = 0.0) -> np.ndarray:
    """(n, 4, 4) poses on a rig, all looking at ``target`` from distance ``radius``.

    Parameters
    ----------
    rig : {"orbit", "hemisphere", "front-arc"}
        ``orbit``: azimuths evenly around 360 degrees; ``front-arc``: evenly over
        ``arc`` degrees centred on +z; elevations spread over ``elevation`` (low,
        high) degrees by a golden-ratio sequence. ``hemisphere``: a Fibonacci
        spiral, uniform in area between the low elevation and the pole.
    phase : float in [0, 1)
        Shift of the sequence in steps, so that splits get distinct views.
    """
    low, high = np.radians(elevation)
    k = np.arange(n) + phase
    if rig == "hemisphere":
        azimuth = 2 * np.pi * ((k * GOLDEN) % 1.0)
        elev = np.arcsin(np.sin(low) + (1 - np.sin(low)) * (k + 0.5) / (n + 1))
    else:
        if rig == "orbit":
            azimuth = 2 * np.pi * k / n
        else:
            azimuth = np.radians(arc) * ((k + 0.5) / n - 0.5)
        elev = low + (high - low) * ((k * GOLDEN + 0.5 * phase) % 1.0)
    offsets = radius * np.stack([np.cos(elev) * np.sin(azimuth), np.sin(elev),
                                 np.cos(elev) * np.cos(azimuth)], axis=-1)
    target = np.asarray(target, np.float64)
    return np.array([look_at(target + o, target) for o in offsets]).reshape(n, 4, 4)


def off_ring_poses(rig: str, n: int, target, radius: float, elevation: tuple[float, float],
                   arc: float = 360.0) -> np.ndarray:
    """(n, 4, 4) poses away from the rig's cameras, looking at ``target``: in turn from above
    its highest elevation (20 degrees higher, at most 85; below its lowest for a hemisphere,
    which reaches the pole), from closer (0.6 ``radius``) and from farther (1.5 ``radius``),
    at azimuths within the rig's (golden-ratio steps). They test what training never had to
    explain: floaters that the training views see against the background, holes.
    """
    low, high = np.radians(elevation)
    k = np.arange(n)
    kind = k % 3
    middle = (low + high) / 2
    above = max(low - np.radians(20), np.radians(-85)) if rig == "hemisphere" else min(
        high + np.radians(20), np.radians(85))
    elev = np.where(kind == 0, above, middle)
    distance = radius * np.choose(kind, [1.0, 0.6, 1.5])
    steps = (k * GOLDEN + 0.25) % 1.0
    azimuth = 2 * np.pi * steps if rig != "front-arc" else np.radians(arc) * (steps - 0.5)
    offsets = distance[:, None] * np.stack([np.cos(elev) * np.sin(azimuth), np.sin(elev),
                                            np.cos(elev) * np.cos(azimuth)], axis=-1)
    target = np.asarray(target, np.float64)
    return np.array([look_at(target + o, target) for o in offsets]).reshape(n, 4, 4)


def blender_transforms(poses: np.ndarray, file_paths: list[str], fov_x_degrees: float,
                       off_ring: list[bool] | None = None) -> dict:
    """A ``transforms_<split>.json`` dictionary (Blender synthetic-dataset layout); frames
    flagged in ``off_ring`` carry ``"off_ring": true``."""
    return {"camera_angle_x": math.radians(fov_x_degrees),
            "frames": _frames(poses, file_paths, off_ring)}


def nerfstudio_transforms(poses: np.ndarray, file_paths: list[str], width: int, height: int,
                          fov_x_degrees: float, off_ring: list[bool] | None = None) -> dict:
    """A ``transforms.json`` dictionary (nerfstudio layout: pinhole intrinsics in pixels)."""
    focal = focal_from_fov(width, fov_x_degrees)
    return {
        "camera_model": "OPENCV", "fl_x": focal, "fl_y": focal, "cx": width / 2,
        "cy": height / 2, "w": width, "h": height,
        "frames": _frames(poses, file_paths, off_ring),
    }


def _frames(poses: np.ndarray, file_paths: list[str], off_ring: list[bool] | None) -> list:
    """The ``frames`` list of a transforms file."""
    frames = [{"file_path": path, "transform_matrix": pose.tolist()}
              for path, pose in zip(file_paths, poses)]
    for frame, away in zip(frames, off_ring or ()):
        if away:
            frame["off_ring"] = True
    return frames


def orbit_poses(poses: np.ndarray, n: int, centre) -> np.ndarray:
    """(n, 4, 4) turntable around ``centre`` at the cameras' mean distance and elevation.

    Up is the cameras' mean up vector. When the cameras surround the scene (no
    azimuth gap over 60 degrees) the turntable goes once around; otherwise it
    sweeps their azimuth range forth and back, so the GIF loops smoothly.
    """
    centre = np.asarray(centre, np.float64)
    up = poses[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    offsets = poses[:, :3, 3] - centre
    distance = np.linalg.norm(offsets, axis=1)
    elevation = np.arcsin(np.clip(offsets @ up / distance, -1, 1)).mean()
    flat = offsets - np.outer(offsets @ up, up)
    e1 = flat.mean(0) if np.linalg.norm(flat.mean(0)) > 1e-9 else flat[0]
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    azimuth = np.sort(np.arctan2(flat @ e2, flat @ e1))
    gaps = np.diff(np.append(azimuth, azimuth[0] + 2 * np.pi))
    widest = int(np.argmax(gaps))
    k = np.arange(n) / n
    if gaps[widest] < np.radians(60):
        sweep = azimuth[0] + 2 * np.pi * k
    else:
        start = azimuth[(widest + 1) % len(azimuth)]
        sweep = start + (2 * np.pi - gaps[widest]) * (1 - np.cos(2 * np.pi * k)) / 2
    radius = distance.mean()
    eyes = centre + radius * (np.cos(elevation) * (np.cos(sweep)[:, None] * e1
                                                   + np.sin(sweep)[:, None] * e2)
                              + np.sin(elevation) * up)
    return np.array([look_at(eye, centre, up) for eye in eyes]).reshape(n, 4, 4)


def turntable_poses(pose: np.ndarray, centre, n: int) -> np.ndarray:
    """(n, 4, 4) ``pose`` turned about the vertical (world +y) axis through ``centre`` in n
    even steps, starting from ``pose`` itself."""
    centre = np.asarray(centre, np.float64)
    poses = []
    for angle in 2 * np.pi * np.arange(n) / n:
        c, s = np.cos(angle), np.sin(angle)
        turn = np.eye(4)
        turn[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        turn[:3, 3] = centre - turn[:3, :3] @ centre
        poses.append(turn @ pose)
    return np.array(poses).reshape(n, 4, 4)
