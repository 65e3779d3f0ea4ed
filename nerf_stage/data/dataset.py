"""Multi-view datasets: Blender and nerfstudio ``transforms`` files, COLMAP models, and
weight stacks.

Three layouts are read (``LAYOUTS``, in the order a folder is looked at):

- Blender synthetic scenes: ``transforms_{train,val,test}.json`` with
  ``camera_angle_x`` and ``frames[]`` (``file_path`` without or with suffix,
  ``transform_matrix`` camera-to-world, OpenGL axes), as ``nerf-stage simulate``
  writes them.
- nerfstudio: one ``transforms.json`` with ``fl_x``, ``fl_y``, ``cx``, ``cy``,
  ``w``, ``h``, a lens (``camera_model`` OPENCV or OPENCV_FISHEYE with ``k1``-``k4``,
  ``p1``, ``p2``) and ``frames[]``, where a frame may carry its own camera and lens (of one
  image size); splits come
  from ``train_filenames``, ``val_filenames`` and ``test_filenames`` where the file lists
  them, else every eighth frame is held out for testing (the LLFF convention) and there
  is no validation split.
- COLMAP: a model (``sparse/0``, text or binary; ``colmap``) with its photos in ``images/``,
  read as a nerfstudio capture in a normalised frame (every eighth photo held out likewise).

Photos taken through a distorting lens are undistorted once, when they are read, into
pinhole images (``distortion``); a lens model we cannot undistort is refused.

A frame with ``"off_ring": true`` (Blender or nerfstudio) is a test view away from the
training cameras (``nerf-stage simulate --off-ring``), scored apart (``Dataset.off_ring``).

Images are read as RGBA and composited on a chosen background; ``downscale`` N averages
each N x N block of pixels (premultiplied by alpha), for captures larger than the training
resolution (nerfstudio's ``--downscale-factor``): each photo is read as 8-bit and made small
before the next is read, so a capture of full-size photos needs the memory of its small
images only.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import astuple, dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from palette_core.errors import InputError
from palette_core.io import image_size, load_image
from palette_core.stack import WeightStack

from .cameras import Intrinsics, checked_camera, focal_length
from .colmap import check_upright, find_model, model_frames, model_points, read_model
from .distortion import Distortion, undistort, undistorted_camera
from .points import Points, read_points

SPLITS = ("train", "val", "test")
NERFSTUDIO_HOLDOUT = 8  # every eighth nerfstudio frame is a test view
MAX_DOWNSCALE = 64
#: What a nerfstudio frame may set for itself (else the file's top level says it).
_CAMERA_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_model", "k1", "k2", "k3", "k4",
                "p1", "p2")
#: nerfstudio's camera models -> our distortion models (``distortion.MODELS``).
NERFSTUDIO_MODELS = {"OPENCV": "opencv", "PINHOLE": "opencv", "SIMPLE_PINHOLE": "opencv",
                     "OPENCV_FISHEYE": "fisheye"}


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
                   off_ring, lenses, points if points is not None and len(points) else None)


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
                         + _listing(unmatched))
    missing = [f for f in frames if f not in by_name]
    if missing:
        raise InputError(f"{split} frames without weights in the stack: {_listing(missing)}")
    size = (dataset.intrinsics.height, dataset.intrinsics.width)
    weights = [_frame_weights(dataset, i, np.asarray(stack.weights[by_name[f]], np.float32))
               for i, f in zip(dataset.indices(split), frames)]
    wrong = [f for f, w in zip(frames, weights) if w.shape[:2] != size]
    if wrong:
        raise InputError(f"weights of {_listing(wrong)} are not {size[1]}x{size[0]} "
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


def _listing(names: list[str], most: int = 5) -> str:
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError(f"{path}: expected an object with a 'frames' list")
    return data


def _field(data: dict, key: str, path: Path, kind=float):
    value = data.get(key)
    if (not isinstance(value, (int, float)) or isinstance(value, bool)
            or not math.isfinite(value) or value <= 0):
        raise InputError(f"{path}: field {key!r} must be a positive number, got {value!r}")
    return kind(value)


def _frames(data: dict, path: Path, default_suffix: str,
            frames_outside: bool) -> tuple[list[str], list, list[bool]]:
    """Image names (relative to root, with suffix), poses and off-ring flags of a ``frames``
    list."""
    names, poses, off_ring = [], [], []
    for i, frame in enumerate(data["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(f"{where}: missing 'file_path'")
        name = frame["file_path"]
        if not PurePosixPath(name).suffix:  # Blender's file_path leaves out ".png"
            name += default_suffix
        pose = np.asarray(frame.get("transform_matrix"), dtype=object)
        if pose.shape not in ((4, 4), (3, 4)):
            raise InputError(f"{where}: 'transform_matrix' must be 4x4, got shape {pose.shape}")
        try:
            pose = pose.astype(np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}: 'transform_matrix' must hold numbers") from None
        if not np.isfinite(pose).all():
            raise InputError(f"{where}: 'transform_matrix' holds NaN or infinity")
        if not isinstance(frame.get("off_ring", False), bool):
            raise InputError(f"{where}: 'off_ring' must be true or false")
        names.append(_frame_path(name, where, path.parent, frames_outside))
        poses.append(np.vstack([pose[:3], [0.0, 0.0, 0.0, 1.0]]))
        off_ring.append(frame.get("off_ring", False))
    return names, poses, off_ring


def _frame_path(name: str, where: str, root: Path, frames_outside: bool) -> str:
    """A frame's image ``name`` normalised, InputError if it lies outside ``root``, by its
    name or through a link (unless ``frames_outside``): a file from elsewhere cannot make us
    read what it does not hold."""
    path = PurePosixPath(os.path.normpath(name))
    if not frames_outside and (path.is_absolute() or path.parts[:1] == ("..",)
                               or not (root / path).resolve().is_relative_to(root.resolve())):
        raise InputError(f"{where}: file_path {name!r} lies outside {root}",
                         fixes=[("frames_outside", "to read it")])
    return path.as_posix()


@dataclass(frozen=True)
class Frames:
    """What a layout's reader finds in a dataset folder (``Dataset``'s fields of the same
    names): frame paths, splits, (N, 4, 4) poses, the cameras (one for all frames, or one a
    frame) and their distortions, (N,) off-ring marks (or None) and sparse points (or
    None)."""

    names: list[str]
    splits: list[str]
    poses: np.ndarray
    cameras: list[Intrinsics]
    distortions: list[Distortion]
    off_ring: np.ndarray | None = None
    points: Points | None = None


@dataclass(frozen=True)
class Layout:
    """A dataset layout: the file that marks it (``marker``), whether a folder holds it
    (``holds(root)``), and its reader (``read(root, frames_outside) -> Frames``)."""

    marker: str
    holds: Callable[[Path], bool]
    read: Callable[[Path, bool], Frames]


def _read_blender(root: Path, frames_outside: bool) -> Frames:
    """NeRF's synthetic layout: ``transforms_{train,val,test}.json``, one camera."""
    names, splits, poses, angle, off_ring = [], [], [], None, []
    for split in SPLITS:
        path = root / f"transforms_{split}.json"
        if not path.is_file():
            continue
        data = _load_json(path)
        split_angle = _field(data, "camera_angle_x", path)
        if angle is not None and abs(split_angle - angle) > 1e-9:
            raise InputError(f"{path}: camera_angle_x {split_angle} differs from the train split's")
        angle = split_angle
        split_names, split_poses, split_off = _frames(data, path, ".png", frames_outside)
        names += split_names
        poses += split_poses
        off_ring += split_off
        splits += [split] * len(split_names)
    if not names:
        raise InputError(f"{root}: the transforms files list no frames")
    width, height = image_size(root / names[0])
    focal = focal_length(width, angle)
    camera = checked_camera(str(root / "transforms_train.json"), width, height, focal, focal,
                            width / 2, height / 2)
    return Frames(names, splits, np.array(poses), [camera], [Distortion()], np.array(off_ring))


def _read_colmap(root: Path, frames_outside: bool) -> Frames:
    """A COLMAP model (``sparse/0``, text or binary) with its photos in ``images/``."""
    model = find_model(root)
    reconstruction = read_model(model)
    names, poses, cameras, distortions = model_frames(reconstruction, str(root))
    names = [_frame_path(f"images/{name}", f"{model}: image", root, frames_outside)
             for name in names]
    check_upright(root, names, f"the COLMAP model in {model}")
    return Frames(names, _holdout(len(names)), poses, cameras, distortions,
                  points=model_points(reconstruction))


def _read_nerfstudio(root: Path, frames_outside: bool) -> Frames:
    """nerfstudio's layout: ``transforms.json``, a camera (and lens) per frame or for all."""
    path = root / "transforms.json"
    data = _load_json(path)
    names, poses, off_ring = _frames(data, path, "", frames_outside)
    if not names:
        raise InputError(f"{path} lists no frames")
    cameras, lenses = [], []
    for i, frame in enumerate(data["frames"]):
        own = {key: frame[key] for key in _CAMERA_KEYS if key in frame}
        fields, where = {**data, **own}, f"{path}: frames[{i}]" if own else path
        cameras.append(checked_camera(
            str(where), _field(fields, "w", where, int), _field(fields, "h", where, int),
            _field(fields, "fl_x", where), _field(fields, "fl_y", where),
            _field(fields, "cx", where), _field(fields, "cy", where)))
        lenses.append(_nerfstudio_lens(fields, where))
    sizes = {(camera.width, camera.height) for camera in cameras}
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
        raise InputError(f"{path}: frames of different image sizes ({listed}) are not supported")
    points = None
    if "ply_file_path" in data:
        if not isinstance(data["ply_file_path"], str):
            raise InputError(f"{path}: ply_file_path must be a file name")
        points = read_points(root / _frame_path(data["ply_file_path"], f"{path}: ply_file_path",
                                                root, frames_outside))
    return Frames(names, _nerfstudio_splits(data, names, path), np.array(poses), cameras,
                  lenses, np.array(off_ring), points)


#: Dataset layouts, looked for in this order; a new layout is a reader and an entry here.
LAYOUTS = {
    "blender": Layout("transforms_train.json", lambda root: (root / "transforms_train.json")
                      .is_file(), _read_blender),
    "nerfstudio": Layout("transforms.json", lambda root: (root / "transforms.json").is_file(),
                         _read_nerfstudio),
    "colmap": Layout("a COLMAP model (sparse/0)", lambda root: find_model(root) is not None,
                     _read_colmap),
}


def _nerfstudio_lens(fields: dict, where) -> Distortion:
    """The distortion of a nerfstudio camera (``camera_model``, ``k1``-``k4``, ``p1``,
    ``p2``; OPENCV when no model is named, as nerfstudio reads it)."""
    name = fields.get("camera_model", "OPENCV")
    if not isinstance(name, str) or name not in NERFSTUDIO_MODELS:
        raise InputError(f"{where}: camera_model {name!r} is not supported (read: "
                         f"{', '.join(NERFSTUDIO_MODELS)}); undistort the photos first")
    coefficients = {key: fields.get(key, 0.0) for key in ("k1", "k2", "k3", "k4", "p1", "p2")}
    try:
        return Distortion(NERFSTUDIO_MODELS[name],
                          tuple(coefficients[f"k{i}"] for i in range(1, 5)),
                          (coefficients["p1"], coefficients["p2"]))
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _nerfstudio_splits(data: dict, names: list[str], path: Path) -> list[str]:
    """The split of each frame: from nerfstudio's ``train_filenames``, ``val_filenames`` and
    ``test_filenames`` lists where the file has any, else every eighth frame held out
    (``_holdout``). A frame is in one list, or in ``val`` and ``test`` both (nerfstudio
    holds out its val views while training and its test views in ``ns-eval``; a capture
    made for both names the same held-out frames twice): then a test view."""
    lists = {split: data[f"{split}_filenames"] for split in SPLITS
             if f"{split}_filenames" in data}
    if not lists:
        return _holdout(len(names))
    listed = {}
    for split, files in lists.items():
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            raise InputError(f"{path}: '{split}_filenames' must be a list of file paths")
        for name in files:
            name = PurePosixPath(os.path.normpath(name)).as_posix()
            before = listed.setdefault(name, split)
            if {before, split} == {"val", "test"}:
                listed[name] = "test"
            elif before != split:
                raise InputError(f"{path}: {name} is listed in two splits")
    unlisted = [name for name in names if name not in listed]
    if unlisted:
        raise InputError(f"{path}: frames in no split list: {_listing(unlisted)}")
    return [listed[name] for name in names]


def _holdout(n: int) -> list[str]:
    """Splits of n frames of a capture: every eighth a test view (one frame: training)."""
    return ["test" if i % NERFSTUDIO_HOLDOUT == NERFSTUDIO_HOLDOUT - 1 and n > 1 else "train"
            for i in range(n)]


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
        raise InputError(f"{root}: images {_listing(wrong)} are not "
                         f"{camera.width}x{camera.height} as the cameras say")
    return np.stack(frames)
