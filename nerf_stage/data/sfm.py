"""Camera poses for a folder of photos: structure from motion with pycolmap on the CPU.

``estimate_poses`` runs COLMAP's phases, each with a progress bar: SIFT features (one
camera for all photos, ``camera_model``), matching (every pair up to ``EXHAUSTIVE_UP_TO``
photos, else each photo with its ``SEQUENTIAL_OVERLAP`` neighbours in name order and those
at power-of-two offsets, as COLMAP's sequential matcher pairs video frames), mapping
(``MAPPERS``: global by default, GLOMAP's rotation averaging and global positioning, which
registers forward-moving street sequences where the incremental mapper finds no initial
pair; incremental, COLMAP's classic, on request), and undistortion where the camera's
distortion moves a pixel by more than ``colmap.MAX_DISTORTION``. A folder that already
holds a COLMAP model is converted without running structure from motion. A capture that
already has its poses (a ``transforms.json``, or a Blender scene's files) keeps them: its
photos, undistorted as ``load_dataset`` reads them, are matched and its points
triangulated from the known cameras (``triangulate_points``, COLMAP's
``point_triangulator``), so that a splat run starts at them, in the frame of its poses.
Every capture is written in nerfstudio's layout (``images/`` and ``transforms.json``,
with its sparse points in ``sparse_pc.ply``, as nerfstudio names them); one made from
photos or a model is in the normalised frame of ``colmap.model_frames``, with the COLMAP
model of its images in ``sparse/0``.
docs/capture.md.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from palette_core.errors import InputError
from palette_core.outputs import check_apart, check_outdir, publish_folder

from .colmap import (
    MAX_DISTORTION,
    cam_from_world,
    check_upright,
    distortion,
    find_model,
    import_pycolmap,
    model_frames,
    model_points,
    read_model,
)
from .dataset import Dataset, load_dataset
from .layouts import LAYOUTS
from .photos import MATCHERS, MIN_PHOTOS, image_pairs, list_photos, upright
from .points import POINTS_FILE, Points, write_points

MIN_REGISTERED = 0.5  # share of the photos that must register
MAPPERS = ("global", "incremental")
SEED = 0  # RANSAC and the mappers: the same photos give the same poses
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_EXTRACT_CHUNK, _MATCH_CHUNK = 8, 256  # photos, pairs a call (a step of the progress bars)


@dataclass
class PosesReport:
    """What ``estimate_poses`` did: the photos that registered and those that did not, the
    model's mean reprojection error (pixels) and 3D points, whether the photos were
    undistorted, and the seconds of each phase."""

    registered: list[str]
    missing: list[str]
    reprojection_error: float
    points: int
    undistorted: bool
    seconds: dict[str, float] = field(default_factory=dict)
    models: list[int] = field(default_factory=list)
    """Photos in each model structure from motion made, largest (the one kept) first: more
    than one when the set split."""
    posed: bool = False
    """The capture came with its poses, which it kept; its points were triangulated."""


def estimate_poses(source: str | os.PathLike, out: str | os.PathLike,
                   camera_model: str = "SIMPLE_RADIAL", matcher: str = "auto",
                   mapper: str = "global", force: bool = False,
                   progress: bool = True) -> PosesReport:
    """Write the capture folder ``out`` for the photos in ``source``, or for the COLMAP model
    that ``source`` holds (``colmap.find_model``; its photos in ``source/images``).

    Raises
    ------
    InputError
        Bad photos (``list_photos``), a model that cannot be read, fewer than
        ``MIN_REGISTERED`` of the photos registered, a posed capture of fewer than
        ``MIN_PHOTOS`` photos or without a point to triangulate, an ``out`` among the photos
        or not empty (without ``force``); nothing is written then.
    """
    if camera_model not in CAMERA_MODELS or matcher not in MATCHERS or mapper not in MAPPERS:
        raise InputError(f"camera model must be one of {', '.join(CAMERA_MODELS)}, matcher one "
                         f"of {', '.join(MATCHERS)} and mapper one of {', '.join(MAPPERS)}")
    source, out = Path(source), Path(out)
    check_apart([out], [source])
    check_outdir(out, force)  # before minutes of work; publish_folder checks again at the end
    pycolmap = import_pycolmap()
    model = find_model(source)
    if model is None and any(reader.holds(source) for name, reader in LAYOUTS.items()
                             if name != "colmap"):
        return _posed_capture(pycolmap, load_dataset(source), out, matcher, force, progress)
    photos = source / "images" if model is not None else source
    names = list_photos(photos)
    if model is not None:
        check_upright(photos, names, f"the COLMAP model in {model}")
    with tempfile.TemporaryDirectory(prefix="nerf-stage-poses-") as work:
        work, seconds = Path(work), {}
        models = None
        if model is None:
            photos, names = upright(photos, names, work / "upright")
            model, models = _structure_from_motion(pycolmap, photos, names, work,
                                                   camera_model, matcher, mapper, progress,
                                                   seconds)
        reconstruction = read_model(model)
        registered = sorted(image.name for image in reconstruction.images.values()
                            if image.has_pose)
        models = models or [len(registered)]
        strangers = sorted(set(registered) - set(names))
        if strangers:
            raise InputError(f"the COLMAP model in {model} names images that are not photos "
                             f"in {photos}: {', '.join(strangers[:3])}")
        missing = sorted(set(names) - set(registered))
        if len(registered) < max(MIN_PHOTOS, MIN_REGISTERED * len(names)):
            split = (f"; they split into {len(models)} models of "
                     f"{', '.join(map(str, models))} photos" if len(models) > 1 else "")
            raise InputError(f"only {len(registered)} of {len(names)} photos registered (at "
                             f"least {max(MIN_PHOTOS, round(MIN_REGISTERED * len(names)))} "
                             f"needed{split}): the photos may overlap too little or lack "
                             "texture")
        undistort = any(distortion(c) > MAX_DISTORTION for c in reconstruction.cameras.values())
        report = PosesReport(registered, missing,
                             float(reconstruction.compute_mean_reprojection_error()),
                             reconstruction.num_points3D(), undistort, seconds, models)
        with publish_folder(out, force) as staging:
            images = staging / "images"
            start = time.perf_counter()
            if undistort:
                model, photos = _undistort(pycolmap, model, photos, registered, work, progress)
                reconstruction = read_model(model)
            images.mkdir()
            for name in tqdm(registered, desc="copy photos", unit="photo", disable=not progress):
                shutil.copyfile(photos / name, images / name)
            seconds["undistort and copy"] = time.perf_counter() - start
            _write_transforms(staging / "transforms.json", reconstruction, str(source))
            write_points(model_points(reconstruction), staging / POINTS_FILE)
            (staging / "sparse" / "0").mkdir(parents=True)
            reconstruction.write(staging / "sparse" / "0")  # binary, for COLMAP's tools
    return report


def _structure_from_motion(pycolmap, photos: Path, names: list[str], work: Path,
                           camera_model: str, matcher: str, mapper: str, progress: bool,
                           seconds: dict) -> tuple[Path, list[int]]:
    """Run features, matching and mapping in ``work``; the folder of the largest model, and
    the photos in each model, largest first.

    Raises
    ------
    InputError
        If no model could be made.
    """
    database = _matched(pycolmap, photos, names, work, pycolmap.CameraMode.SINGLE,
                        camera_model, matcher, progress, seconds)
    start = time.perf_counter()
    with tqdm(total=len(names), desc=f"{mapper} mapping", unit="photo",
              disable=not progress) as bar:
        if mapper == "global":
            options = pycolmap.GlobalPipelineOptions()
            options.random_seed = SEED
            models = pycolmap.global_mapping(database, photos, work / "sparse", options)
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.random_seed = SEED
            models = pycolmap.incremental_mapping(
                database, photos, work / "sparse", options,
                initial_image_pair_callback=lambda: bar.update(2),
                next_image_callback=lambda: bar.update(1))
        bar.n = max((m.num_reg_images() for m in models.values()), default=0)  # the kept one
    seconds["mapping"] = time.perf_counter() - start
    if not models:
        raise InputError(f"structure from motion found no model for the {len(names)} photos in "
                         f"{photos}: they may overlap too little or lack texture")
    largest = max(models, key=lambda k: models[k].num_reg_images())
    sizes = sorted((m.num_reg_images() for m in models.values()), reverse=True)
    return work / "sparse" / str(largest), sizes


def _matched(pycolmap, photos: Path, names: list[str], work: Path, camera_mode,
             camera_model: str, matcher: str, progress: bool, seconds: dict) -> Path:
    """The database in ``work`` of the photos' SIFT features (cameras as ``camera_mode``
    and ``camera_model`` make them) and their matches (``image_pairs``)."""
    database, cpu = work / "database.db", pycolmap.Device.cpu
    pycolmap.set_random_seed(SEED)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    start = time.perf_counter()
    pycolmap.Database.open(database).close()  # created empty
    pycolmap.import_images(database, photos, camera_mode, names, reader)
    with tqdm(total=len(names), desc="features", unit="photo", disable=not progress) as bar:
        for i in range(0, len(names), _EXTRACT_CHUNK):
            chunk = names[i:i + _EXTRACT_CHUNK]
            pycolmap.extract_features(database, photos, chunk, camera_mode, reader, device=cpu)
            bar.update(len(chunk))
    seconds["features"] = time.perf_counter() - start
    start, pairs = time.perf_counter(), image_pairs(names, matcher)
    pairing, pair_file = pycolmap.ImportedPairingOptions(), work / "pairs.txt"
    pairing.match_list_path = pair_file
    with tqdm(total=len(pairs), desc="matching", unit="pair", disable=not progress) as bar:
        for i in range(0, len(pairs), _MATCH_CHUNK):
            chunk = pairs[i:i + _MATCH_CHUNK]
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
            pycolmap.match_image_pairs(database, pairing_options=pairing, device=cpu)
            bar.update(len(chunk))
    seconds["matching"] = time.perf_counter() - start
    return database


def _posed_capture(pycolmap, dataset: Dataset, out: Path, matcher: str, force: bool,
                   progress: bool) -> PosesReport:
    """Write the capture folder ``out`` for ``dataset``, whose poses are known: its images
    as ``load_dataset`` read them (undistorted) in PNGs, its cameras, poses and splits in
    ``transforms.json``, and the points triangulated from them (``triangulate_points``)."""
    ids = list(range(len(dataset.names)))
    with tempfile.TemporaryDirectory(prefix="nerf-stage-poses-") as work:
        work, seconds = Path(work), {}
        names, photos, reconstruction = _triangulated(pycolmap, dataset, ids, work, matcher,
                                                      progress, seconds)
        points = reconstruction.points3D.values()
        report = PosesReport(names, [], float(reconstruction.compute_mean_reprojection_error()),
                             len(points), dataset.lenses is not None, seconds, [len(names)],
                             posed=True)
        with publish_folder(out, force) as staging:
            shutil.move(photos, staging / "images")  # the PNGs written above
            frames = [{"file_path": f"images/{name}",
                       "transform_matrix": dataset.poses[i].tolist(),
                       **_intrinsics(dataset.camera(i))} for i, name in enumerate(names)]
            splits = {split: [f"images/{n}" for n, s in zip(names, dataset.splits) if s == split]
                      for split in ("train", "val", "test")}
            (staging / "transforms.json").write_text(json.dumps({
                "camera_model": "PINHOLE", "ply_file_path": POINTS_FILE, "frames": frames,
                **{f"{split}_filenames": files for split, files in splits.items()}}, indent=1))
            write_points(_points(reconstruction), staging / POINTS_FILE)
    return report


def points_from_poses(dataset: Dataset, ids, progress: bool = True) -> Points:
    """The sparse points triangulated from ``dataset``'s frames ``ids`` at their known poses
    (as ``estimate_poses`` does for a posed capture, without writing one): what a splat run
    of a capture without points starts from.

    Raises
    ------
    InputError
        Without pycolmap (the ``poses`` extra), with fewer than ``MIN_PHOTOS`` frames, or
        when no point triangulates.
    """
    pycolmap = import_pycolmap()
    with tempfile.TemporaryDirectory(prefix="nerf-stage-points-") as work:
        _, _, reconstruction = _triangulated(pycolmap, dataset, list(ids), Path(work), "auto",
                                             progress, {})
        return _points(reconstruction)


def _points(reconstruction) -> Points:
    """A pycolmap reconstruction's 3D points and their colours."""
    points = list(reconstruction.points3D.values())
    return Points(np.array([p.xyz for p in points]).reshape(-1, 3),
                  np.array([p.color for p in points], np.float32).reshape(-1, 3) / 255)


def _triangulated(pycolmap, dataset: Dataset, ids: list[int], work: Path, matcher: str,
                  progress: bool, seconds: dict):
    """The frames ``ids`` of ``dataset`` as it reads them (undistorted) written as PNGs
    (``work / "images"``, named by frame), matched, and the pycolmap reconstruction of their
    points at the frames' poses (``triangulate_points``): names, folder, reconstruction."""
    names = [f"{i:04d}.png" for i in ids]
    if len(names) < MIN_PHOTOS:
        raise InputError(f"{dataset.root} holds {len(names)} photo(s); triangulation needs at "
                         f"least {MIN_PHOTOS}")
    photos = work / "images"
    photos.mkdir()
    for name, i in zip(names, ids):
        image, alpha = dataset.images[i], dataset.alpha[i]
        rgba = np.concatenate([image, alpha[..., None]], -1) if (alpha < 1).any() else image
        Image.fromarray((rgba * 255).round().astype(np.uint8)).save(photos / name)
    database = _matched(pycolmap, photos, names, work, pycolmap.CameraMode.PER_IMAGE,
                        "PINHOLE", matcher, progress, seconds)
    start = time.perf_counter()
    reconstruction = triangulate_points(pycolmap, dataset, ids, photos, names, database, work)
    seconds["triangulation"] = time.perf_counter() - start
    if not reconstruction.points3D:
        raise InputError(f"no point could be triangulated from the {len(names)} photos of "
                         f"{dataset.root} at their poses: they may overlap too little or "
                         "lack texture")
    return names, photos, reconstruction


def _intrinsics(camera) -> dict:
    """A frame's camera in ``transforms.json``'s fields."""
    return {"w": camera.width, "h": camera.height, "fl_x": camera.fx, "fl_y": camera.fy,
            "cx": camera.cx, "cy": camera.cy}


def triangulate_points(pycolmap, dataset: Dataset, ids: list[int], photos: Path,
                       names: list[str], database: Path, work: Path):
    """The pycolmap reconstruction of the cameras and poses of ``dataset``'s frames ``ids``
    (pinhole, their images ``names`` in ``photos`` at the dataset's size) with the points
    that COLMAP's ``point_triangulator`` finds from the matches in ``database``, the poses
    held fixed.
    The model is written as COLMAP's text files with the database's image and camera ids
    (an image a camera, ``CameraMode.PER_IMAGE``)."""
    db = pycolmap.Database.open(database)
    ids_of = {image.name: (image.image_id, image.camera_id) for image in db.read_all_images()}
    db.close()
    model = work / "known"
    model.mkdir()
    cameras, images = [], []
    for i, name in zip(ids, names):
        image_id, camera_id = ids_of[name]
        c = dataset.camera(i)
        cameras.append(f"{camera_id} PINHOLE {c.width} {c.height} "
                       f"{_numbers(c.fx, c.fy, c.cx, c.cy)}\n")
        rotation, translation = cam_from_world(dataset.poses[i])
        images.append(f"{image_id} {_numbers(*_quaternion(rotation), *translation)} {camera_id} "
                      f"{name}\n\n")
    (model / "cameras.txt").write_text("".join(cameras))
    (model / "images.txt").write_text("".join(images))
    (model / "points3D.txt").write_text("")
    (work / "triangulated").mkdir()
    return pycolmap.triangulate_points(pycolmap.Reconstruction(model), database, photos,
                                       work / "triangulated", clear_points=True)


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion of a (3, 3) rotation matrix."""
    from scipy.spatial.transform import Rotation

    return np.roll(Rotation.from_matrix(rotation).as_quat(), 1)


def _numbers(*values) -> str:
    """``values`` for a COLMAP text file, each to float64's full precision."""
    return " ".join(repr(float(v)) for v in values)


def _undistort(pycolmap, model: Path, photos: Path, names: list[str], work: Path,
               progress: bool) -> tuple[Path, Path]:
    """Undistort the registered photos into ``work``; the pinhole model and photo folders."""
    target = work / "undistorted"
    with tqdm(total=len(names), desc="undistort", unit="photo", disable=not progress) as bar:
        for i in range(0, len(names), _EXTRACT_CHUNK):
            chunk = names[i:i + _EXTRACT_CHUNK]
            pycolmap.undistort_images(target, model, photos, chunk)
            bar.update(len(chunk))
    return target / "sparse", target / "images"


def _write_transforms(path: Path, reconstruction, source: str) -> None:
    """``transforms.json`` (nerfstudio layout, a camera per frame, the points'
    ``ply_file_path``) of ``reconstruction``."""
    names, poses, cameras, _ = model_frames(reconstruction, source)  # undistorted: pinhole
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) > 1:
        raise InputError(f"{source}: the model's cameras have different image sizes")
    first = cameras[0]
    frames = []
    for name, pose, camera in zip(names, poses, cameras):
        frame = {"file_path": f"images/{name}", "transform_matrix": pose.tolist()}
        if camera != first:
            frame.update(fl_x=camera.fx, fl_y=camera.fy, cx=camera.cx, cy=camera.cy)
        frames.append(frame)
    path.write_text(json.dumps({
        "camera_model": "PINHOLE", "w": first.width, "h": first.height, "fl_x": first.fx,
        "fl_y": first.fy, "cx": first.cx, "cy": first.cy, "ply_file_path": POINTS_FILE,
        "frames": frames}, indent=1))
