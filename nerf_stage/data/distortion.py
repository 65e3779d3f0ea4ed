"""Lens distortion as captures have it, removed once when a capture is read.

Two models, in normalised image coordinates (x, y) of a pinhole camera, r^2 = x^2 + y^2:

- ``opencv``, radial-tangential (OpenCV; COLMAP's ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``;
  nerfstudio's ``OPENCV``, whose ``k4`` is the r^8 term)::

      d = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8
      x' = x d + 2 p1 x y + p2 (r^2 + 2 x^2),   y' = y d + p1 (r^2 + 2 y^2) + 2 p2 x y

- ``fisheye`` (OpenCV's fisheye; COLMAP's ``OPENCV_FISHEYE``, ``SIMPLE_RADIAL_FISHEYE``,
  ``RADIAL_FISHEYE``; nerfstudio's ``OPENCV_FISHEYE``)::

      theta = atan(r),   theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
      (x', y') = (x, y) theta_d / r

A photo taken through such a lens is resampled (bilinearly) into the pinhole image of the
same size and principal point whose focal lengths are the photo's scaled by the least
factor at which every pixel's source lies inside the photo: no pixel lacks data, and
barrel distortion loses its stretched corners (COLMAP's undistorter does the same with
``max_scale``). The photo's weights are resampled with the same map, which keeps them on
their simplex (a bilinear sample is a convex combination). docs/capture.md.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass
from functools import lru_cache

import numpy as np

from palette_core.errors import InputError

from .cameras import Intrinsics

MODELS = ("opencv", "fisheye")
#: Pixels that a lens may move a border pixel before its photos are resampled: below, the
#: camera is taken as a pinhole (resampling would blur for nothing).
MIN_SHIFT = 0.05
#: The focal scales searched for the undistorted camera.
SCALE_RANGE = (1 / 16, 16.0)
#: Radii and grid cells on which a lens is checked to be one to one (``check_invertible``).
FOLD_SAMPLES, FOLD_GRID = 4096, 64


@dataclass(frozen=True)
class Distortion:
    """A lens's distortion: ``model`` (``MODELS``), radial ``k`` (k1..k4), tangential ``p``
    (p1, p2; the opencv model only).

    Raises
    ------
    InputError
        For an unknown model or coefficients that are not finite.
    """

    model: str = "opencv"
    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    p: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        if self.model not in MODELS:
            raise InputError(f"distortion model must be one of {', '.join(MODELS)}, "
                             f"got {self.model!r}")
        values = (*self.k, *self.p)
        if len(self.k) != 4 or len(self.p) != 2 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in values):
            raise InputError(f"distortion coefficients must be 4 + 2 finite numbers, got "
                             f"k {self.k}, p {self.p}")
        if self.model == "fisheye" and any(self.p):
            raise InputError("a fisheye lens has no tangential coefficients p1, p2")

    @property
    def none(self) -> bool:
        """A pinhole lens (all coefficients zero): nothing to undistort."""
        return self.model == "opencv" and not any((*self.k, *self.p))

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised pinhole coordinates (any shape) -> where the lens puts them."""
        k1, k2, k3, k4 = self.k
        r2 = x * x + y * y
        if self.model == "fisheye":
            r = np.sqrt(r2)
            theta = np.arctan(r)
            t2 = theta * theta
            theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            scale = np.divide(theta_d, r, out=np.ones_like(r), where=r > 1e-12)
            return x * scale, y * scale
        p1, p2 = self.p
        d = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        return (x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * d + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def sources(camera: Intrinsics, distortion: Distortion, target: Intrinsics,
            u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v) of ``target`` (the pinhole camera; pixel centres at + 0.5)
    -> where they lie in the photo of ``camera`` through ``distortion``."""
    x, y = distortion.distort((u - target.cx) / target.fx, (v - target.cy) / target.fy)
    return x * camera.fx + camera.cx, y * camera.fy + camera.cy


def _border(camera: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The pixel corners along the image's border (pixel coordinates)."""
    w, h = camera.width, camera.height
    across, down = np.arange(w + 1.0), np.arange(h + 1.0)
    u = np.concatenate([across, across, np.zeros_like(down), np.full_like(down, w)])
    v = np.concatenate([np.zeros_like(across), np.full_like(across, h), down, down])
    return u, v


def _scaled(camera: Intrinsics, scale: float) -> Intrinsics:
    return Intrinsics(camera.width, camera.height, camera.fx * scale, camera.fy * scale,
                      camera.cx, camera.cy)


def undistorted_camera(camera: Intrinsics, distortion: Distortion) -> Intrinsics:
    """The pinhole camera that ``undistort`` makes the photos of ``camera`` into (module
    docstring); ``camera`` itself when the lens moves no border pixel by ``MIN_SHIFT``.

    Raises
    ------
    InputError
        If no focal scale in ``SCALE_RANGE`` keeps every pixel's source inside the photo
        (a lens whose model folds back within the image).
    """
    if distortion.none:
        return camera
    u, v = _border(camera)
    with np.errstate(all="ignore"):  # a lens from elsewhere may overflow: not inside, then
        su, sv = sources(camera, distortion, camera, u, v)
        if np.abs(np.hypot(su - u, sv - v)).max() < MIN_SHIFT:
            return camera

    def inside(log_scale: float) -> bool:
        with np.errstate(all="ignore"):
            su, sv = sources(camera, distortion, _scaled(camera, math.exp(log_scale)), u, v)
            return bool(np.all(np.isfinite(su) & np.isfinite(sv) & (su >= -1e-6)
                               & (su <= camera.width + 1e-6) & (sv >= -1e-6)
                               & (sv <= camera.height + 1e-6)))

    low, high = (math.log(s) for s in SCALE_RANGE)
    if not inside(high):
        raise InputError(f"a {distortion.model} lens with k {distortion.k}, p {distortion.p} "
                         f"cannot be undistorted into a {camera.width}x{camera.height} "
                         "pinhole image that its photo covers")
    for _ in range(40):  # bisection on the log of the scale
        middle = (low + high) / 2
        low, high = (low, middle) if inside(middle) else (middle, high)
    target = _scaled(camera, math.exp(high))
    check_invertible(camera, distortion, target)
    return target


def check_invertible(camera: Intrinsics, distortion: Distortion, target: Intrinsics) -> None:
    """InputError unless the lens maps ``target``'s image into ``camera``'s one to one: its
    radial profile rises over every radius the image reaches (``FOLD_SAMPLES`` of them), and
    the whole map (tangential terms too) keeps its orientation on a ``FOLD_GRID`` grid. A
    lens that folds over itself (``k1 = -10``) would give some photo pixels twice."""
    corners = np.array([[0.0, 0.0], [target.width, 0.0], [0.0, target.height],
                        [target.width, target.height]])
    reach = float(np.hypot((corners[:, 0] - target.cx) / target.fx,
                           (corners[:, 1] - target.cy) / target.fy).max())
    r = np.linspace(0.0, reach, FOLD_SAMPLES)
    with np.errstate(all="ignore"):
        radial, _ = distortion.distort(r, np.zeros_like(r))
        v, u = np.mgrid[0:FOLD_GRID + 1, 0:FOLD_GRID + 1] / FOLD_GRID
        u, v = u * target.width, v * target.height
        h = 0.25
        du = [np.stack(sources(camera, distortion, target, u + s, v)) for s in (h, -h)]
        dv = [np.stack(sources(camera, distortion, target, u, v + s)) for s in (h, -h)]
        (a, c), (b, d) = du[0] - du[1], dv[0] - dv[1]
        orientation = a * d - b * c
    if not (np.all(np.diff(radial) > 0) and np.all(orientation > 0)):
        raise InputError(f"a {distortion.model} lens with k {distortion.k}, p {distortion.p} "
                         f"folds over itself within a {camera.width}x{camera.height} image "
                         "(its distortion is not one to one there): it cannot be undistorted")


def undistort(image: np.ndarray, camera: Intrinsics, distortion: Distortion,
              target: Intrinsics) -> np.ndarray:
    """(H, W, C) ``image`` of ``camera`` through ``distortion`` -> the (H, W, C) float32
    image of pinhole ``target`` (``undistorted_camera``), sampled bilinearly."""
    image = image.astype(np.float32, copy=False)
    if target == camera:
        return image
    y0, x0, fy, fx = (a[..., None] if a.dtype == np.float32 else a
                      for a in _bilinear(astuple(camera), distortion, astuple(target)))
    y1 = np.minimum(y0 + 1, camera.height - 1)
    x1 = np.minimum(x0 + 1, camera.width - 1)
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


@lru_cache(maxsize=2)
def _bilinear(camera: tuple, distortion: Distortion, target: tuple) -> tuple:
    """Each pixel of ``target``: the row and column of its source's top-left neighbour in
    the photo, and its offsets from it (a capture's frames mostly share one camera, so the
    map is made once)."""
    camera, target = Intrinsics(*camera), Intrinsics(*target)
    v, u = np.mgrid[0:target.height, 0:target.width] + 0.5
    su, sv = sources(camera, distortion, target, u, v)
    x = np.clip(su - 0.5, 0, camera.width - 1)  # array coordinates, clamped at the edge
    y = np.clip(sv - 0.5, 0, camera.height - 1)
    x0, y0 = np.floor(x).astype(np.int32), np.floor(y).astype(np.int32)
    return y0, x0, (y - y0).astype(np.float32), (x - x0).astype(np.float32)
