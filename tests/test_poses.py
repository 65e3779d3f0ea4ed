"""Structure from motion (``nerf-stage poses``) and COLMAP models read as captures."""

import json
import shutil

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import zoom

pycolmap = pytest.importorskip("pycolmap")

from nerf_stage.cli import main as nerf_stage  # noqa: E402
from nerf_stage.data.cameras import Intrinsics, camera_rays, look_at  # noqa: E402
from nerf_stage.data.dataset import load_dataset  # noqa: E402
from nerf_stage.train.metrics import pose_errors  # noqa: E402
from palette_core.cli import decompose  # noqa: E402

from .nerf_runs import TINY_FLAGS  # noqa: E402

CAMERA = Intrinsics(160, 120, 140.0, 140.0, 80.0, 60.0)


def _texture(rng, n=256) -> np.ndarray:
    """(n, n, 3) noise of three scales, in [0, 1]: texture that SIFT finds features on."""
    texture = sum(zoom(rng.random((s, s, 3)), (n / s, n / s, 1), order=1) / (i + 1)
                  for i, s in enumerate((8, 32, 128)))
    return (texture - texture.min()) / np.ptp(texture)


def _render_corner(pose, textures) -> np.ndarray:
    """(H, W, 3) uint8 view of a room corner (floor y = 0, walls z = -2 and x = -2, each
    4 m square and textured) by ray casting."""
    origins, directions = (a[:, :, 0] for a in camera_rays(pose, CAMERA))
    nearest, rgb = np.full(origins.shape[:2], np.inf), np.zeros(origins.shape)
    for axis, at, texture in zip((1, 2, 0), (0.0, -2.0, -2.0), textures):
        d = directions[..., axis]
        t = (at - origins[..., axis]) / np.where(np.abs(d) < 1e-9, 1e-9, d)
        uv = np.delete(origins + t[..., None] * directions, axis, -1)
        hit = (t > 0) & np.all(np.abs(uv) <= 2, -1) & (t < nearest)
        texel = np.clip(((uv + 2) / 4 * (len(texture) - 1)).astype(int), 0, len(texture) - 1)
        rgb[hit], nearest[hit] = texture[texel[hit, 0], texel[hit, 1]], t[hit]
    return (rgb * 255).astype(np.uint8)


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    """A folder of 10 photos of a textured room corner on a 50-degree arc, and their true
    camera-to-world poses."""
    folder = tmp_path_factory.mktemp("corner") / "photos"
    folder.mkdir()
    rng = np.random.default_rng(0)
    textures = [_texture(rng) for _ in range(3)]
    poses = []
    for i, angle in enumerate(np.radians(np.linspace(-25, 25, 10))):
        eye = [3 * np.sin(angle), 1.5 + 0.2 * np.cos(3 * angle), 3 * np.cos(angle) - 1]
        poses.append(look_at(eye, [-0.5, 0.5, -1.5]))
        Image.fromarray(_render_corner(poses[-1], textures)).save(folder / f"v{i:02d}.png")
    return folder, np.array(poses)


@pytest.fixture(scope="module")
def capture(corner, tmp_path_factory):
    out = tmp_path_factory.mktemp("capture") / "capture"
    assert nerf_stage(["poses", str(corner[0]), "-o", str(out)]) == 0
    return out


def test_pose_errors_undo_a_similarity_and_see_what_it_cannot(rng):
    truth = np.array([look_at(rng.normal(size=3) * 3, [0, 0, 0]) for _ in range(8)])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + np.sin(1.0) * k + (1 - np.cos(1.0)) * k @ k  # one radian about axis
    moved = truth.copy()
    moved[:, :3, :3] = turn @ truth[:, :3, :3]
    moved[:, :3, 3] = 0.3 * truth[:, :3, 3] @ turn.T + [1, 2, 3]
    rotation, centre = pose_errors(moved, truth)
    assert rotation.max() < 1e-6 and centre.max() < 1e-9
    moved[0, :3, :3] = moved[0, :3, :3] @ look_at([0, 0, 1], [0.1, 0, 0])[:3, :3]  # one camera
    rotation, _ = pose_errors(moved, truth)
    assert rotation[0] == pytest.approx(np.degrees(np.arctan(0.1)), abs=1e-6)
    assert rotation[1:].max() < 1e-6


def test_photos_register_into_a_capture_folder(corner, capture):
    frames = json.loads((capture / "transforms.json").read_text())["frames"]
    assert len(frames) == 10 and (capture / "sparse" / "0" / "images.bin").is_file()
    dataset = load_dataset(capture)
    assert dataset.layout == "nerfstudio" and dataset.indices("test").tolist() == [7]
    rotation, centre = pose_errors(dataset.poses, corner[1])
    assert rotation.max() < 3.0 and centre.max() < 0.05  # degrees; the corner is 4 m wide
    centres = dataset.poses[:, :3, 3]  # the normalised frame
    assert np.allclose(centres.mean(0), 0, atol=1e-9)
    assert np.isclose(np.linalg.norm(centres, axis=1).max(), 1.0)
    assert dataset.poses[:, :3, 1].mean(0) @ [0, 1, 0] > 0.9  # the cameras' up is +y



def test_a_capture_has_its_sparse_points_in_the_frame_of_its_poses(capture):
    """``nerf-stage poses`` writes the model's points (``sparse_pc.ply``) where the
    capture's cameras see them: projected into each photo, a point has the photo's colour
    there (a wrong frame would put it on unrelated texture); the COLMAP model read directly
    gives the same points."""
    dataset = load_dataset(capture)
    points = dataset.points
    assert points is not None and len(points) > 100
    errors = []
    for i, (pose, image) in enumerate(zip(dataset.poses, dataset.images)):
        local = (points.positions - pose[:3, 3]) @ pose[:3, :3]  # camera axes, looking down -z
        depth, camera = -local[:, 2], dataset.camera(i)
        front = depth > 1e-3
        x = camera.fx * local[front, 0] / depth[front] + camera.cx
        y = camera.cy - camera.fy * local[front, 1] / depth[front]
        seen = (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        pixels = image[y[seen].astype(int), x[seen].astype(int)]
        errors.append(np.abs(pixels - points.colours[front][seen]).mean(1))
    assert np.median(np.concatenate(errors)) < 0.04
    project = capture.parent / "colmap"
    (project / "sparse").mkdir(parents=True, exist_ok=True)
    shutil.copytree(capture / "sparse" / "0", project / "sparse" / "0", dirs_exist_ok=True)
    shutil.copytree(capture / "images", project / "images", dirs_exist_ok=True)
    direct = load_dataset(project).points
    assert np.allclose(direct.positions, points.positions, atol=1e-6)


def test_a_walk_forward_registers_with_sequential_matching(tmp_path):
    """Eight frames walking towards the corner (forward motion, the parallax a street
    sequence has; weaving, so that the centres fix the similarity of ``pose_errors``):
    every frame registers, each pose within a few degrees."""
    rng, folder = np.random.default_rng(2), tmp_path / "walk"
    folder.mkdir()
    textures = [_texture(rng) for _ in range(3)]
    eyes = [[0.6 + 0.2 * (i % 2), 1.3 + 0.1 * (i % 3), 3.0 - 0.3 * i] for i in range(8)]
    poses = np.array([look_at(eye, [-0.8, 0.9, -2.0]) for eye in eyes])
    for i, pose in enumerate(poses):
        Image.fromarray(_render_corner(pose, textures)).save(folder / f"f{i:02d}.png")
    out = tmp_path / "capture"
    assert nerf_stage(["poses", str(folder), "-o", str(out), "--matcher", "sequential"]) == 0
    dataset = load_dataset(out)
    assert len(dataset.names) == 8
    rotation, centre = pose_errors(dataset.poses, poses)
    assert rotation.max() < 3.0 and centre.max() < 0.1


def _posed_corner(corner, posed):
    """The corner's photos with their true poses (nerfstudio's ``transforms.json``, every
    other photo held out by name), no points."""
    folder, poses = corner
    shutil.copytree(folder, posed / "images")
    names = sorted(p.name for p in folder.iterdir())
    (posed / "transforms.json").write_text(json.dumps({
        "w": CAMERA.width, "h": CAMERA.height, "fl_x": CAMERA.fx, "fl_y": CAMERA.fy,
        "cx": CAMERA.cx, "cy": CAMERA.cy,
        "train_filenames": [f"images/{n}" for n in names[::2]],
        "test_filenames": [f"images/{n}" for n in names[1::2]],
        "frames": [{"file_path": f"images/{n}", "transform_matrix": pose.tolist()}
                   for n, pose in zip(names, poses)]}))
    return posed


def _on_the_corner(points) -> np.ndarray:
    """Each point's distance to the nearest of the room corner's three planes."""
    return np.abs(np.stack([points[:, 1], points[:, 2] + 2, points[:, 0] + 2])).min(0)


def test_a_posed_capture_keeps_its_poses_and_gets_points_on_its_surfaces(corner, tmp_path):
    """A capture with known poses is matched and its points triangulated from those poses:
    they lie on the room corner's floor and walls, in the frame of the poses, which the
    capture keeps."""
    _, poses = corner
    posed = _posed_corner(corner, tmp_path / "posed")
    out = tmp_path / "capture"
    assert nerf_stage(["poses", str(posed), "-o", str(out)]) == 0
    dataset = load_dataset(out)
    assert np.allclose(dataset.poses, poses) and dataset.intrinsics == CAMERA
    assert dataset.indices("test").tolist() == [1, 3, 5, 7, 9]
    points = dataset.points.positions
    assert len(points) > 100
    distance = _on_the_corner(points)  # a pixel is about 2 cm across on the walls
    assert np.median(distance) < 0.02 and np.mean(distance < 0.1) > 0.9


def test_a_splat_run_of_a_posed_capture_without_points_starts_at_triangulated_ones(
        corner, tmp_path, monkeypatch):
    """A capture with poses and no points: a splat run triangulates them from its training
    views (not the held-out ones) as it starts, on the corner's surfaces; with
    ``--no-splats-triangulate`` it starts without them."""
    from nerf_stage.data.sfm import points_from_poses
    from nerf_stage.train import trainer

    posed = _posed_corner(corner, tmp_path / "posed")
    dataset = load_dataset(posed)
    points = points_from_poses(dataset, dataset.indices("train"), progress=False)
    assert len(points) > 50 and np.median(_on_the_corner(points.positions)) < 0.02
    started, choose = [], trainer.choose_scene_box
    monkeypatch.setattr(trainer, "choose_scene_box",
                        lambda config, data, *rest: started.append(data.points)
                        or choose(config, data, *rest))
    assert decompose.main([str(posed / "images"), "-k", "4", "-o",
                           str(posed / "weights.npz")]) == 0
    for flags in ([], ["--no-splats-triangulate"]):
        assert nerf_stage(["train", str(posed), "--backbone", "splats", "-o",
                           str(tmp_path / "run"), "--force", "--pretrain-iters", "2",
                           "--finetune-iters", "2", *flags]) == 0
    # COLMAP's threads match in any order, so each triangulation finds a few points more or less
    assert abs(len(started[0]) - len(points)) <= 0.15 * len(points) and started[1] is None
    assert np.median(_on_the_corner(started[0].positions)) < 0.02


def test_text_and_binary_models_read_the_same(capture, tmp_path):
    model = pycolmap.Reconstruction(capture / "sparse" / "0")
    datasets = []
    for kind in ("bin", "txt"):
        project = tmp_path / kind
        (project / "sparse" / "0").mkdir(parents=True)
        shutil.copytree(capture / "images", project / "images")
        (model.write_binary if kind == "bin" else model.write_text)(project / "sparse" / "0")
        datasets.append(load_dataset(project))
    binary, text = datasets
    assert binary.layout == text.layout == "colmap" and binary.names == text.names
    assert np.allclose(binary.poses, text.poses, atol=1e-6)
    assert binary.intrinsics == text.intrinsics
    ours = load_dataset(capture)
    assert np.allclose(binary.poses, ours.poses, atol=1e-6) and binary.names == ours.names


def test_a_capture_trains(capture, tmp_path):
    stack = tmp_path / "weights.npz"
    assert decompose.main([str(capture / "images"), "-k", "4", "-o", str(stack)]) == 0
    assert nerf_stage(["train", str(capture), "--weights", str(stack), "-o",
                       str(tmp_path / "run"), *TINY_FLAGS]) == 0
    assert (tmp_path / "run" / "checkpoint.pt").is_file()


def test_a_model_whose_images_climb_out_is_refused(capture, tmp_path, capsys):
    model = pycolmap.Reconstruction(capture / "sparse" / "0")
    image = next(iter(model.images.values()))
    image.name = "../../outside.png"
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    model.write_text(tmp_path / "sparse" / "0")
    assert nerf_stage(["train", str(tmp_path), "-o", str(tmp_path / "run")]) == 2
    assert "lies outside" in capsys.readouterr().err


def _photos(folder, sizes, rng) -> None:
    folder.mkdir()
    for i, (w, h) in enumerate(sizes):
        Image.fromarray(rng.integers(0, 255, (h, w, 3), np.uint8)).save(folder / f"{i}.png")


def _posed(folder, n, rng) -> None:
    """A nerfstudio capture of ``n`` noise photos with poses around the origin."""
    _photos(folder / "images", [(96, 72)] * n, rng)
    (folder / "transforms.json").write_text(json.dumps({
        "w": 96, "h": 72, "fl_x": 80.0, "fl_y": 80.0, "cx": 48.0, "cy": 36.0,
        "frames": [{"file_path": f"images/{i}.png", "transform_matrix":
                    look_at([np.sin(i), 0.2, np.cos(i)], [0, 0, 0]).tolist()}
                   for i in range(n)]}))


@pytest.mark.parametrize("case, message", [
    ("one photo", "needs at least 3"),
    ("sizes", "different sizes"),
    ("not photos", "not photos"),
    ("noise", "overlap too little"),
    ("posed, two photos", "needs at least 3"),
    ("posed noise", "no point could be triangulated"),
])
def test_bad_photo_folders_are_one_line(case, message, tmp_path, capsys):
    rng, photos = np.random.default_rng(1), tmp_path / "photos"
    if case.startswith("posed"):
        photos.mkdir()
        _posed(photos, 2 if "two" in case else 4, rng)
    elif case == "one photo":
        _photos(photos, [(64, 48)], rng)
    elif case == "sizes":
        _photos(photos, [(64, 48), (64, 48), (48, 64)], rng)
    elif case == "not photos":
        _photos(photos, [(64, 48)] * 3, rng)
        (photos / "notes.txt").write_text("not a photo")
    else:  # unrelated noise: nothing matches
        _photos(photos, [(96, 72)] * 4, rng)
    out = tmp_path / "capture"
    assert nerf_stage(["poses", str(photos), "-o", str(out)]) == 2
    err = capsys.readouterr().err  # the progress bars of the phases that ran, then the line
    assert message in err.strip().splitlines()[-1] and "Traceback" not in err
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["photos"]


def test_a_capture_is_not_written_over_nor_among_the_photos(corner, capture, capsys):
    assert nerf_stage(["poses", str(corner[0]), "-o", str(capture)]) == 2
    assert "not empty" in capsys.readouterr().err
    assert nerf_stage(["poses", str(corner[0]), "-o", str(corner[0] / "capture")]) == 2
    assert "among the inputs" in capsys.readouterr().err
    assert not (corner[0] / "capture").exists()


def test_turned_photos_pose_decompose_and_train_as_they_show(corner, tmp_path):
    """Photos stored a quarter turn off, with EXIF orientation 6 (as phones take them
    upright): poses register them as they show, and the README's sequence runs."""
    photos = tmp_path / "turned"
    photos.mkdir()
    exif = Image.Exif()
    exif[0x0112] = 6
    for path in sorted(corner[0].iterdir()):
        upright = np.asarray(Image.open(path))
        Image.fromarray(np.ascontiguousarray(np.rot90(upright, 1))).save(
            photos / f"{path.stem}.jpg", quality=95, exif=exif)
    out = tmp_path / "capture"
    assert nerf_stage(["poses", str(photos), "-o", str(out)]) == 0
    dataset = load_dataset(out)
    assert dataset.names[0] == "images/v00.jpg.png"
    assert dataset.images.shape[2] > dataset.images.shape[1]  # landscape, as they show
    rotation, centre = pose_errors(dataset.poses, corner[1][[int(n[8:10]) for n in
                                                             dataset.names]])
    assert rotation.max() < 5.0 and centre.max() < 0.05  # JPEG's; turned, 90 degrees off
    stack = tmp_path / "weights.npz"
    assert decompose.main([str(out / "images"), "-k", "4", "-o", str(stack)]) == 0
    assert nerf_stage(["train", str(out), "--weights", str(stack), "-o", str(tmp_path / "run"),
                       *TINY_FLAGS]) == 0


def test_a_colmap_model_of_turned_photos_is_refused(capture, tmp_path, capsys):
    """COLMAP posed the stored pixels; every command here reads them turned."""
    copy = tmp_path / "model"
    shutil.copytree(capture, copy)
    (copy / "transforms.json").unlink()
    exif = Image.Exif()
    exif[0x0112] = 6
    for path in sorted((copy / "images").iterdir()):  # all of them, as a phone's are
        with Image.open(path) as image:
            image.load()
            image.save(path, exif=exif)
    assert nerf_stage(["poses", str(copy), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "EXIF orientation turns (v00.png, v01.png, v02.png ...)" in err
