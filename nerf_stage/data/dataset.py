"""Multi-view datasets and the weight stacks joined to them.

A dataset folder is read in any of the layouts of ``layouts.LAYOUTS`` (Blender, nerfstudio,
COLMAP, LLFF; one module each), which give its frames, splits, poses, cameras and lenses,
sparse points and depth bounds where they have them (``layouts.Frames``).

Photos taken through a distorting lens are undistorted once, when they are read, into
pinhole images (``distortion``); a lens model we cannot undistort is refused.

A frame with ``"off_ring": true`` (Blender or nerfstudio) is a test view away from the
training cameras (``nerf-stage simulate --off-ring``), scored apart (``Dataset.off_ring``).

Images are read as RGBA and composited on a chosen background; ``downscale`` N averages
each N x N block of pixels (premultiplied by alpha), for captures larger than the training
resolution (nerfstudio's ``--downscale-factor``): each photo is read
(``palette_core.io.load_image``, as every command reads it) and made small before the next
is read, so a capture of full-size photos needs the memory of its small images only.
"""

from __future__ import annotations

import os
from dataclasses import astuple, dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from palette_core.errors import InputError
from palette_core.io import load_image
from palette_core.stack import WeightStack

from .cameras import Intrinsics
from .distortion import Distortion, undistort, undistorted_camera
from .layouts import LAYOUTS
from .layouts.common import listing
from .points import Points

MAX_DOWNSCALE = 64


@dataclass(frozen=True)
class Lens:
    """A frame's ``camera`` through ``distortion``, undistorted into pinhole ``target`` (all
    at the files' size; ``distortion``)."""

    camera: Intrinsics
    distortion: Distortion
    target: Intrinsics

    def undistort(self, image: np.ndarray) -> np.ndarray:
        """(H, W, C) image or weights of the file -> float32, of ``target``."""
        return undistort(image, self.camera, self.distortion, self.target)


@dataclass
class Dataset:
    """Frames of one scene.

    Attributes
    ----------
    root : Path
    names : list of str
        Image paths relative to ``root``, with suffix and forward slashes.
    splits : list of str
        ``"train"``, ``"val"`` or ``"test"`` per frame.
    poses : (N, 4, 4) float64
        Camera-to-world matrices, OpenGL axes.
    intrinsics : Intrinsics
        The first frame's camera; every frame's has its image size.
    images : (N, H, W, 3) float32
        Colours composited on ``background``.
    alpha : (N, H, W) float32
    background : (3,) float64
    layout : str
        The key in ``LAYOUTS`` of the files it was read from.
    frames_outside : bool
        Frames were allowed outside ``root`` (``load_dataset``).
    downscale : int
        The images are this many times smaller than the files (``load_dataset``).
    frame_intrinsics : list of Intrinsics or None
        Each frame's camera, where they differ (``camera``).
    off_ring : (N,) bool
        Test frames away from the cameras that training saw (a frame's ``"off_ring":
        true``, which ``nerf-stage simulate --off-ring`` writes): scored apart.
    lenses : list of Lens or None
        Each frame's lens at the files' size, where a lens distorts: the images (and a
        stack's weights, ``join_weights``) are undistorted through it.
    points : Points or None
        The capture's sparse points, in the poses' frame, where it has them
        (``points``: a nerfstudio ``ply_file_path``, a COLMAP model's ``points3D``).
    bounds : (N, 2) float64 or None
        Near and far depths of the scene in each frame, where the layout has them (LLFF's
        ``poses_bounds.npy``), in the poses' units.
    """

    root: Path
    names: list[str]
    splits: list[str]
    poses: np.ndarray
    intrinsics: Intrinsics
    images: np.ndarray
    alpha: np.ndarray
    background: np.ndarray
    layout: str = "blender"
    frames_outside: bool = False
    downscale: int = 1
    frame_intrinsics: list[Intrinsics] | None = None
    off_ring: np.ndarray | None = None
    lenses: list[Lens] | None = None
    points: Points | None = None
    bounds: np.ndarray | None = None

    def __post_init__(self):
        if self.off_ring is None:
            self.off_ring = np.zeros(len(self.names), bool)

    def camera(self, i: int) -> Intrinsics:
        """Frame ``i``'s camera."""
        return self.intrinsics if self.frame_intrinsics is None else self.frame_intrinsics[i]

    def cameras(self, ids) -> list[Intrinsics]:
        """The cameras of the frames ``ids``."""
        return [self.camera(i) for i in ids]

    def indices(self, split: str, off_ring: bool | None = None) -> np.ndarray:
        """Frame indices of one split: all of them, or those off the ring or on it."""
        return np.array([i for i, s in enumerate(self.splits) if s == split
                         and (off_ring is None or self.off_ring[i] == off_ring)], np.int64)

    def scene_depth(self, ids) -> float | None:
        """How far in front of the cameras of frames ``ids`` the scene lies, where the
        capture says: twice the median near bound of an LLFF capture, else the median depth
        of its sparse points (``point_depths``; ``scene_box.scene_box``'s ``depth``); None
        without either."""
        if self.bounds is not None:
            return 2.0 * float(np.median(self.bounds[ids, 0]))
        depths = self.point_depths(ids)
        return None if depths is None else float(np.median(depths))

    def nearest_depth(self, ids) -> float | None:
        """The nearest depth the capture gives in front of the cameras of frames ``ids``
        (where NDC space puts its near plane: ``ndc.reference_frame``): an LLFF capture's
        least near bound, else the 1st percentile of its sparse points' depths in front of
        them; None without either."""
        if self.bounds is not None:
            return float(self.bounds[ids, 0].min())
        depths = self.point_depths(ids)
        ahead = None if depths is None else depths[depths > 0]
        return None if ahead is None or not len(ahead) else float(np.percentile(ahead, 1))

    def point_depths(self, ids) -> np.ndarray | None:
        """(P,) the depths of the sparse points along the mean optical axis of the cameras
        of frames ``ids``, from their mean position; None without points."""
        if self.points is None or not len(self.points):
            return None
        poses = self.poses[ids]
        axis = -poses[:, :3, 2].mean(0)
        axis /= max(np.linalg.norm(axis), 1e-12)
        return (self.points.positions - poses[:, :3, 3].mean(0)) @ axis


def load_dataset(root: str | os.PathLike, background=(1.0, 1.0, 1.0),
                 frames_outside: bool = False, downscale: int = 1) -> Dataset:
    """Read a dataset folder in any of the ``LAYOUTS``, its images ``downscale`` times
    smaller.

    A frame's ``file_path`` must lie inside ``root`` (neither absolute nor climbing out
    with ``..``) unless ``frames_outside``: a transforms file from elsewhere cannot make
    training read files it does not name in its own folder.

    Raises
    ------
    InputError
        If the folder holds neither layout, a file is malformed (the message
        names the file and the field), a frame lies outside the folder, an image is
        missing or unreadable, or the images differ in size.
    """
    root = Path(root)
    background = np.asarray(background, np.float64).reshape(3)
    check_downscale(downscale)
    layout = next((name for name, reader in LAYOUTS.items() if reader.holds(root)), None)
    if layout is None:
        held = ", ".join(f"{reader.marker} ({name} layout)" for name, reader in LAYOUTS.items())
        raise InputError(f"{root} holds none of {held}: make one from photos with nerf-stage "
                         "poses or from a scene with nerf-stage simulate")
    frames = LAYOUTS[layout].read(root, frames_outside)
    names, splits, poses, points = frames.names, frames.splits, frames.poses, frames.points
    frame_intrinsics, distortions, off_ring = frames.cameras, frames.distortions, frames.off_ring
    lenses = _lenses(frame_intrinsics, distortions, len(names), root)
    frame_intrinsics = [lens.target for lens in lenses] if lenses else frame_intrinsics
    intrinsics = frame_intrinsics[0]
    if all(camera == intrinsics for camera in frame_intrinsics):
        frame_intrinsics = None  # one camera for all frames
    if min(intrinsics.width, intrinsics.height) < downscale:
        raise InputError(f"{root}: images of {intrinsics.width}x{intrinsics.height} cannot be "
                         f"downscaled {downscale} times")
    rgba = _read_frames(root, names, intrinsics, downscale, lenses)
    intrinsics = intrinsics.downscaled(downscale)
    if frame_intrinsics is not None:
        frame_intrinsics = [camera.downscaled(downscale) for camera in frame_intrinsics]
    alpha = rgba[..., 3]
    images = rgba[..., :3] * alpha[..., None] + (1 - alpha[..., None]) * background
    return Dataset(root, names, splits, poses, intrinsics, images.astype(np.float32),
                   alpha, background, layout, frames_outside, downscale, frame_intrinsics,
                   off_ring, lenses, points if points is not None and len(points) else None,
                   frames.bounds)


def _lenses(cameras: list[Intrinsics], distortions: list[Distortion], n: int,
            root: Path) -> list[Lens] | None:
    """Each frame's ``Lens`` (one camera and distortion may stand for all), or None when
    no lens distorts."""
    if all(d.none for d in distortions):
        return None
    cameras = cameras * n if len(cameras) == 1 else cameras
    distortions = distortions * n if len(distortions) == 1 else distortions
    made: dict[tuple, Lens] = {}
    lenses = []
    for camera, distortion in zip(cameras, distortions):
        key = (astuple(camera), distortion)
        if key not in made:
            try:
                made[key] = Lens(camera, distortion, undistorted_camera(camera, distortion))
            except InputError as exc:
                raise InputError(f"{root}: {exc}") from None
        lenses.append(made[key])
    return lenses


def check_downscale(factor) -> int:
    """``factor``, checked: a whole number from 1 to ``MAX_DOWNSCALE``.

    Raises
    ------
    InputError
    """
    if isinstance(factor, bool) or not isinstance(factor, int) or not 1 <= factor <= MAX_DOWNSCALE:
        raise InputError(f"downscale must be a whole number from 1 to {MAX_DOWNSCALE}, got "
                         f"{factor!r}")
    return factor


def block_mean(image: np.ndarray, factor: int, rgba: bool = False) -> np.ndarray:
    """(H, W, C) -> (H // factor, W // factor, C): the mean of each factor x factor block
    (the rows and columns past the last whole block are dropped). The colour of an ``rgba``
    image is averaged premultiplied by alpha, so that compositing commutes with
    downscaling; weights, linear in the colour, average as they are."""
    if factor == 1:
        return image
    h, w = image.shape[0] // factor, image.shape[1] // factor
    blocks = image[:h * factor, :w * factor].reshape(h, factor, w, factor, -1)
    if not rgba:
        return blocks.mean((1, 3)).astype(image.dtype)
    alpha = blocks[..., 3:].mean((1, 3))
    colour = (blocks[..., :3] * blocks[..., 3:]).mean((1, 3)) / np.maximum(alpha, 1e-12)
    return np.concatenate([colour, alpha], -1).astype(image.dtype)


def join_weights(dataset: Dataset, stack: WeightStack, split: str = "train") -> np.ndarray:
    """(n, H, W, M) weights of the frames of ``split``, matched to the stack by image name.

    A stack name matches a frame when it equals the frame's path relative to the
    dataset root or is a trailing part of it (``r_000.png`` for a stack
    decomposed from ``train/`` alone). Weights of the image files' size are downscaled like
    the images (``block_mean``).

    Raises
    ------
    InputError
        Naming frames of the split that have no weights, stack images that match
        no frame of the dataset, names that match several frames, or weights whose
        size differs from the images.
    """
    frames = [dataset.names[i] for i in dataset.indices(split)]
    by_name: dict[str, int] = {}
    unmatched = []
    for j, name in enumerate(stack.names):
        matches = [f for f in frames if _same_image(f, name)]
        if len(matches) > 1:
            raise InputError(f"weight stack image {name!r} matches several {split} frames: "
                             f"{', '.join(matches[:3])}")
        if matches:
            by_name[matches[0]] = j
        elif not any(_same_image(f, name) for f in dataset.names):
            unmatched.append(name)
    if unmatched:
        raise InputError(f"weight stack has images that are not frames of {dataset.root}: "
                         + listing(unmatched))
    missing = [f for f in frames if f not in by_name]
    if missing:
        raise InputError(f"{split} frames without weights in the stack: {listing(missing)}")
    size = (dataset.intrinsics.height, dataset.intrinsics.width)
    weights = [_frame_weights(dataset, i, np.asarray(stack.weights[by_name[f]], np.float32))
               for i, f in zip(dataset.indices(split), frames)]
    wrong = [f for f, w in zip(frames, weights) if w.shape[:2] != size]
    if wrong:
        raise InputError(f"weights of {listing(wrong)} are not {size[1]}x{size[0]} "
                         "like the images")
    return np.stack(weights).astype(np.float32)


def _frame_weights(dataset: Dataset, i: int, weights: np.ndarray) -> np.ndarray:
    """(h, w, M) weights of frame ``i``'s image file, undistorted through its lens and
    downscaled like the image; weights of another size as they are (``join_weights``
    names them)."""
    camera = dataset.camera(i)
    if weights.shape[:2] == (camera.height, camera.width):
        return weights  # made from the frames as the dataset has them
    if dataset.lenses is not None and weights.shape[:2] == (dataset.lenses[i].camera.height,
                                                            dataset.lenses[i].camera.width):
        weights = dataset.lenses[i].undistort(weights)
    return block_mean(weights, dataset.downscale)


def _same_image(frame: str, name: str) -> bool:
    frame_parts, name_parts = PurePosixPath(frame).parts, PurePosixPath(name).parts
    return frame_parts[len(frame_parts) - len(name_parts):] == name_parts


def _read_frames(root: Path, names: list[str], camera: Intrinsics, downscale: int,
                 lenses: list[Lens] | None) -> np.ndarray:
    """(N, H / n, W / n, 4) float32 RGBA in [0, 1] of the frames, undistorted through their
    ``lenses`` and ``downscale`` n times smaller (``block_mean``; images without alpha are
    opaque), read by ``palette_core.io.load_image`` as every command reads them. Each frame is
    made small before the next is read, so full-size photos never sit in memory together as
    floats.

    Raises
    ------
    InputError
        If a frame cannot be read or is not the camera's size (all such frames named).
    """
    frames, wrong = [], []
    for i, name in enumerate(names):
        image = load_image(root / name)  # the pixels palette-decompose reads
        if image.pixels.shape[:2] != (camera.height, camera.width):
            wrong.append(name)
        elif not wrong:
            alpha = np.ones(image.opaque.shape, np.float32) if image.alpha is None else image.alpha
            rgb = image.pixels / np.float32(np.iinfo(image.pixels.dtype).max)
            rgba = np.concatenate([rgb, alpha[..., None]], -1)
            if lenses is not None:
                rgba = lenses[i].undistort(rgba)
            frames.append(block_mean(rgba, downscale, rgba=True))
    if wrong:
        raise InputError(f"{root}: images {listing(wrong)} are not "
                         f"{camera.width}x{camera.height} as the cameras say")
    return np.stack(frames)
