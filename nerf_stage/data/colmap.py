"""COLMAP models as captures: a pycolmap reconstruction's cameras and poses in our conventions.

A COLMAP model (``cameras``, ``images``, ``points3D``, as ``.bin`` or ``.txt``) stores
world-to-camera poses with the camera looking down +z, y down. A capture stores
camera-to-world poses with OpenGL axes (``cameras``) in a normalised frame: centred on the
cameras, the cameras' mean up vector turned to +y, the farthest camera at distance 1
(nerfstudio's "poses" centring and "up" orientation). ``data`` reads a model's folder
directly as a capture, its photos undistorted when read (``distortion``); ``sfm`` writes one
as a nerfstudio folder of pinhole cameras, undistorting photos whose lens moves a pixel by
more than ``MAX_DISTORTION``. docs/capture.md.

pycolmap is an optional dependency (``pip install 'palette-nerf-toolkit[poses]'``).
"""

from __future__ import annotations

import os
import resource
import signal
from pathlib import Path

import numpy as np

from palette_core.errors import InputError, first_line
from palette_core.io import is_turned

from .cameras import Intrinsics, checked_camera
from .distortion import Distortion
from .points import Points

#: What pycolmap's reader may take on a model in a child process (``_check_readable``).
READ_SECONDS = 10
READ_BYTES = 2 << 30
#: Where a model may sit in a folder, in the order looked at (COLMAP's own layout first).
MODEL_FOLDERS = ("sparse/0", "sparse", ".")
#: Pixels that a camera's distortion may move an image corner before ``sfm`` undistorts.
MAX_DISTORTION = 0.1
#: COLMAP's camera axes to OpenGL's: x right, y down, z forward -> x right, y up, z back.
_FLIP = np.diag([1.0, -1.0, -1.0])


def import_pycolmap():
    """The pycolmap module; InputError saying how to install it when it is missing."""
    try:
        import pycolmap
    except ImportError:
        raise InputError("COLMAP models and structure from motion need pycolmap: "
                         "pip install 'palette-nerf-toolkit[poses]'") from None
    pycolmap.logging.minloglevel = 3  # fatal only: we show progress and errors ourselves
    return pycolmap


def find_model(folder: str | os.PathLike) -> Path | None:
    """The folder of the COLMAP model in ``folder`` (``MODEL_FOLDERS``), or None."""
    for name in MODEL_FOLDERS:
        model = Path(folder) / name
        if any((model / f"cameras.{ext}").is_file() and (model / f"images.{ext}").is_file()
               for ext in ("bin", "txt")):
            return model
    return None


def read_model(model: str | os.PathLike):
    """The ``pycolmap.Reconstruction`` in folder ``model``, text or binary.

    Raises
    ------
    InputError
        If it cannot be read or registers no image.
    """
    pycolmap = import_pycolmap()
    _check_readable(pycolmap, Path(model))
    try:
        reconstruction = pycolmap.Reconstruction(Path(model))
    except Exception as exc:  # pycolmap raises its own C++ exceptions
        raise InputError(f"cannot read the COLMAP model in {model}: {first_line(exc)}") from None
    if reconstruction.num_reg_images() == 0:
        raise InputError(f"the COLMAP model in {model} registers no image")
    for camera in reconstruction.cameras.values():
        check_camera(camera, f"the COLMAP model in {model}")
    for image in reconstruction.images.values():
        if image.has_pose and not np.isfinite(image.cam_from_world().matrix()).all():
            raise InputError(f"the COLMAP model in {model}: the pose of image {image.image_id} "
                             "holds NaN or infinity")
    xyz = np.array([p.xyz for p in reconstruction.points3D.values()], np.float64)
    if not np.isfinite(xyz).all():
        raise InputError(f"the COLMAP model in {model}: {int((~np.isfinite(xyz)).any(-1).sum())} "
                         "of its 3D points hold NaN or infinity")
    try:
        [image.name for image in reconstruction.images.values()]
    except UnicodeDecodeError:
        raise InputError(f"the COLMAP model in {model} names an image in bytes that are not "
                         "UTF-8") from None
    return reconstruction


def _check_readable(pycolmap, model: Path) -> None:
    """InputError unless pycolmap reads ``model`` in a child process within
    ``READ_SECONDS`` (plus a second a megabyte) and ``READ_BYTES`` (plus 64 bytes a byte of
    the model) of address space: a crafted count inside a binary model makes its reader loop
    or allocate without end, in C++ code that nothing here can interrupt."""
    size = sum(f.stat().st_size for f in model.iterdir() if f.is_file())
    pid = os.fork()
    if pid == 0:  # the child: read, then leave without Python's teardown
        code = 3
        try:
            signal.signal(signal.SIGALRM, signal.SIG_DFL)
            signal.alarm(READ_SECONDS + size // 2**20)
            hard = resource.getrlimit(resource.RLIMIT_AS)[1]
            limit = _address_space() + READ_BYTES + 64 * size
            limit = limit if hard == resource.RLIM_INFINITY else min(limit, hard)
            resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
            pycolmap.Reconstruction(model)
            code = 0
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    if os.waitstatus_to_exitcode(status) < 0:
        raise InputError(f"cannot read the COLMAP model in {model}: its reader stopped "
                         f"({signal.Signals(-os.waitstatus_to_exitcode(status)).name}); the "
                         "model is damaged or crafted")


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def check_upright(photos: Path, names: list[str], source: str) -> None:
    """InputError naming the photos whose EXIF orientation turns them (``io.is_turned``):
    ``source``'s poses were computed from their stored pixels, every command here reads them
    turned."""
    turned = [name for name in names if is_turned(photos / name)]
    if turned:
        raise InputError(f"{source} was made from the stored pixels of photos that their EXIF "
                         f"orientation turns ({', '.join(turned[:3])}"
                         f"{' ...' if len(turned) > 3 else ''}): pose the photos themselves "
                         "with nerf-stage poses")


def check_camera(camera, source: str) -> None:
    """InputError unless ``camera``'s parameters are finite and its pinhole part a valid
    camera (``cameras.Intrinsics``), naming ``source``."""
    where = f"{source}: camera {camera.camera_id}"
    if not np.isfinite(np.asarray(camera.params, np.float64)).all():
        raise InputError(f"{where}: its parameters hold NaN or infinity")
    checked_camera(where, camera.width, camera.height, float(camera.focal_length_x),
                   float(camera.focal_length_y), float(camera.principal_point_x),
                   float(camera.principal_point_y))


def distortion(camera) -> float:
    """Most pixels by which ``camera``'s distortion moves a point on its image's border."""
    if not camera.extra_params_idxs():
        return 0.0
    w, h = camera.width, camera.height
    border = np.array([[x, y] for x in np.linspace(0, w, 9) for y in np.linspace(0, h, 9)
                       if x in (0, w) or y in (0, h)], np.float64)
    undistorted = camera.cam_from_img(border)  # normalised image coordinates, distortion removed
    fx, fy = camera.focal_length_x, camera.focal_length_y
    pinhole = undistorted * [fx, fy] + [camera.principal_point_x, camera.principal_point_y]
    return float(np.abs(pinhole - border).max())


#: COLMAP camera models we read: name -> (the params' order, our distortion model). f is a
#: shared focal length; k and p name the coefficients of ``distortion.Distortion``.
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), "opencv"),
    "PINHOLE": (("fx", "fy", "cx", "cy"), "opencv"),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k1"), "opencv"),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"), "opencv"),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), "opencv"),
    "FULL_OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4_rational",
                     "k5_rational", "k6_rational"), "opencv"),
    "SIMPLE_RADIAL_FISHEYE": (("f", "cx", "cy", "k1"), "fisheye"),
    "RADIAL_FISHEYE": (("f", "cx", "cy", "k1", "k2"), "fisheye"),
    "OPENCV_FISHEYE": (("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"), "fisheye"),
}


def camera_lens(camera, source: str) -> tuple[Intrinsics, Distortion]:
    """``camera`` as a pinhole camera and its lens's distortion (``CAMERA_MODELS``).

    Raises
    ------
    InputError
        For a model we cannot undistort (FOV, thin-prism fisheyes, FULL_OPENCV's rational
        terms), naming ``source``.
    """
    where = f"{source}: camera {camera.camera_id}"
    if camera.model_name not in CAMERA_MODELS:
        raise InputError(f"{where}: camera model {camera.model_name} is not supported (read: "
                         f"{', '.join(CAMERA_MODELS)}); undistort its photos first, e.g. with "
                         "COLMAP's image_undistorter")
    names, model = CAMERA_MODELS[camera.model_name]
    values = dict(zip(names, map(float, camera.params)))
    if any(values.get(f"k{i}_rational") for i in (4, 5, 6)):
        raise InputError(f"{where}: FULL_OPENCV's rational terms k4, k5, k6 are not supported")
    fx, fy = values.get("fx", values.get("f")), values.get("fy", values.get("f"))
    intrinsics = checked_camera(where, camera.width, camera.height, fx, fy, values["cx"],
                                values["cy"])
    k = tuple(values.get(f"k{i}", 0.0) for i in range(1, 5))
    try:
        return intrinsics, Distortion(model, k, (values.get("p1", 0.0), values.get("p2", 0.0)))
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def model_frames(reconstruction, source: str):
    """The registered images of ``reconstruction`` by name: (N,) names, (N, 4, 4)
    camera-to-world poses (OpenGL axes, normalised frame: ``normalised``), N pinhole
    cameras and their N distortions (``camera_lens``)."""
    images = _registered(reconstruction)
    cameras, lenses = zip(*(camera_lens(image.camera, source) for image in images))
    return ([image.name for image in images], normalised(_world_poses(images)), list(cameras),
            list(lenses))


def model_points(reconstruction) -> Points:
    """The 3D points of ``reconstruction`` in the frame of ``model_frames``' poses."""
    rotation, centre, radius = normalisation(_world_poses(_registered(reconstruction)))
    points = list(reconstruction.points3D.values())
    positions = np.array([p.xyz for p in points], np.float64).reshape(-1, 3)
    colours = np.array([p.color for p in points], np.float32).reshape(-1, 3) / 255.0
    return Points((positions - centre) @ rotation.T / radius, colours)


def _registered(reconstruction) -> list:
    """The images of ``reconstruction`` that have a pose, by name."""
    images = sorted(reconstruction.images.values(), key=lambda image: image.name)
    return [image for image in images if image.has_pose]


def _world_poses(images) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses of pycolmap ``images``, OpenGL axes, COLMAP's frame."""
    poses = []
    for image in images:
        world_to_camera = image.cam_from_world().matrix()  # (3, 4)
        pose = np.eye(4)
        pose[:3, :3] = world_to_camera[:, :3].T @ _FLIP
        pose[:3, 3] = -world_to_camera[:, :3].T @ world_to_camera[:, 3]
        poses.append(pose)
    return np.array(poses)


def cam_from_world(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's world-to-camera (3, 3) rotation and (3,) translation (OpenCV axes) of a
    (4, 4) camera-to-world ``pose`` (OpenGL axes): the inverse of ``_world_poses``."""
    rotation = (pose[:3, :3] @ _FLIP).T
    return rotation, -rotation @ pose[:3, 3]


def normalisation(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The similarity ``normalised`` applies to (N, 4, 4) camera-to-world ``poses``: a point
    x goes to ``rotation @ (x - centre) / radius``. Returns (3, 3) rotation, (3,) centre and
    radius: it turns the poses' mean up vector to +y, centres them on their mean position
    and puts the farthest camera at distance 1."""
    up = poses[:, :3, 1].mean(0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else np.array([0.0, 1.0, 0.0])
    centre = poses[:, :3, 3].mean(0)
    radius = np.linalg.norm(poses[:, :3, 3] - centre, axis=1).max()
    return (_rotation_onto(up, np.array([0.0, 1.0, 0.0])), centre,
            float(radius) if radius > 1e-12 else 1.0)


def normalised(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) camera-to-world ``poses`` moved by their ``normalisation``.

    Examples
    --------
    >>> poses = np.tile(np.eye(4), (2, 1, 1)); poses[:, :3, 3] = [[2, 0, 0], [4, 0, 0]]
    >>> normalised(poses)[:, :3, 3].tolist()
    [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    """
    rotation, centre, radius = normalisation(poses)
    moved = poses.copy()
    moved[:, :3, :3] = rotation @ poses[:, :3, :3]
    moved[:, :3, 3] = (poses[:, :3, 3] - centre) @ rotation.T / radius
    return moved


def _rotation_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    axis, cos = np.cross(a, b), float(a @ b)
    if np.linalg.norm(axis) < 1e-12:
        if cos > 0:
            return np.eye(3)
        perpendicular = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        perpendicular /= np.linalg.norm(perpendicular)
        return 2 * np.outer(perpendicular, perpendicular) - np.eye(3)  # half a turn
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + k + k @ k / (1 + cos)
