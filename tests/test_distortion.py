"""Lens distortion: undistortion against an independent inversion of the lens, the
undistorted camera's coverage, every camera model from both capture layouts, and models we
cannot undistort refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from palette_core.errors import InputError
from palette_core.stack import WeightStack, write_stack

from .hostile import colmap_capture, nerfstudio_capture

torch = pytest.importorskip("torch")

from nerf_stage.data.cameras import Intrinsics  # noqa: E402
from nerf_stage.data.dataset import join_weights, load_dataset  # noqa: E402
from nerf_stage.data.distortion import Distortion, sources, undistort, undistorted_camera  # noqa: E402

CAMERA = Intrinsics(64, 48, 50.0, 52.0, 31.0, 25.0)
LENSES = [Distortion("opencv", (-0.25, 0.06, 0.0, 0.0), (0.002, -0.003)),
          Distortion("opencv", (0.12, 0.0, 0.0, 0.0)),
          Distortion("fisheye", (0.05, -0.02, 0.004, 0.0))]


def scene(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour for each normalised pinhole direction: (..., 3)."""
    return np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(2 * y),
                     0.5 + 0.3 * np.sin(2 * x + y)], -1)


def inverted(distortion: Distortion, xd: np.ndarray, yd: np.ndarray):
    """Normalised pinhole coordinates that the lens takes to (xd, yd), by Newton's method
    with a numerical Jacobian: an oracle independent of the resampling."""
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        fx, fy = distortion.distort(x, y)
        rx, ry = fx - xd, fy - yd
        h = 1e-6
        ax, ay = distortion.distort(x + h, y)
        bx, by = distortion.distort(x, y + h)
        j11, j21, j12, j22 = (ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h
        det = j11 * j22 - j12 * j21
        x, y = x - (j22 * rx - j12 * ry) / det, y - (j11 * ry - j21 * rx) / det
    return x, y


@pytest.mark.parametrize("distortion", LENSES)
def test_undistortion_undoes_the_lens(distortion):
    """A photo through the lens, made by inverting the lens at each photo pixel, undistorts
    into the pinhole image of the same scene within bilinear interpolation's error."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width] + 0.5
    x, y = inverted(distortion, (u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy)
    photo = scene(x, y)
    target = undistorted_camera(CAMERA, distortion)
    truth = scene((u - target.cx) / target.fx, (v - target.cy) / target.fy)
    error = np.abs(undistort(photo, CAMERA, distortion, target) - truth)
    assert error.max() < 0.02 and error.mean() < 0.002
    naive = np.abs(photo - truth).max()  # the photo taken as a pinhole image
    assert naive > 10 * error.max()


@pytest.mark.parametrize("distortion", LENSES)
def test_the_undistorted_camera_is_covered_by_the_photo_and_no_smaller(distortion):
    target = undistorted_camera(CAMERA, distortion)
    assert (target.width, target.height, target.cx, target.cy) == (64, 48, 31.0, 25.0)
    v, u = np.mgrid[0:49, 0:65].astype(np.float64)  # pixel corners, the border included
    su, sv = sources(CAMERA, distortion, target, u, v)
    assert su.min() >= -1e-6 and sv.min() >= -1e-6 and su.max() <= 64 + 1e-6
    assert sv.max() <= 48 + 1e-6
    wider = Intrinsics(64, 48, target.fx * 0.99, target.fy * 0.99, 31.0, 25.0)
    su, sv = sources(CAMERA, distortion, wider, u, v)
    assert su.min() < 0 or sv.min() < 0 or su.max() > 64 or sv.max() > 48


def test_a_pinhole_lens_changes_nothing():
    image = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    assert undistorted_camera(CAMERA, Distortion()) == CAMERA
    assert np.array_equal(undistort(image, CAMERA, Distortion(), CAMERA), image)
    with pytest.raises(InputError, match="finite"):
        Distortion("opencv", (float("nan"), 0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="model must be one of"):
        Distortion("fov")


# The same lens written by each layout: (COLMAP camera line, nerfstudio keys).
SIZE = (40, 30)
PAIRS = {
    "SIMPLE_RADIAL": ("SIMPLE_RADIAL 40 30 40 20 15 -0.2", {"k1": -0.2}),
    "RADIAL": ("RADIAL 40 30 40 20 15 -0.2 0.05", {"k1": -0.2, "k2": 0.05}),
    "OPENCV": ("OPENCV 40 30 40 40 20 15 -0.2 0.05 0.001 -0.002",
               {"camera_model": "OPENCV", "k1": -0.2, "k2": 0.05, "p1": 0.001, "p2": -0.002}),
    "FULL_OPENCV": ("FULL_OPENCV 40 30 40 40 20 15 -0.2 0.05 0.001 -0.002 0.01 0 0 0",
                    {"k1": -0.2, "k2": 0.05, "p1": 0.001, "p2": -0.002, "k3": 0.01}),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE 40 30 40 40 20 15 0.05 -0.02 0.004 0.001",
                       {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.02,
                        "k3": 0.004, "k4": 0.001}),
    "RADIAL_FISHEYE": ("RADIAL_FISHEYE 40 30 40 20 15 0.05 -0.02",
                       {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.02}),
    "PINHOLE": ("PINHOLE 40 30 40 40 20 15", {"camera_model": "PINHOLE"}),
}


@pytest.mark.parametrize("model", PAIRS)
def test_every_camera_model_reads_the_same_from_both_layouts(tmp_path, model):
    pytest.importorskip("pycolmap")
    line, keys = PAIRS[model]
    colmap = load_dataset(colmap_capture(tmp_path / "colmap", np.random.default_rng(1),
                                         binary=model == "RADIAL", camera=line, size=SIZE))
    nerfstudio = load_dataset(nerfstudio_capture(tmp_path / "ns", np.random.default_rng(1),
                                                 keys, size=SIZE))
    assert colmap.intrinsics == nerfstudio.intrinsics
    assert np.allclose(colmap.images, nerfstudio.images, atol=1e-6)
    if model == "PINHOLE":
        assert colmap.lenses is None and colmap.intrinsics == Intrinsics(40, 30, 40, 40, 20, 15)
    else:
        assert colmap.lenses[0].distortion == nerfstudio.lenses[0].distortion
        assert colmap.intrinsics.fx != 40.0  # undistorted into a scaled pinhole camera


def test_weights_are_undistorted_with_their_frames(tmp_path):
    rng = np.random.default_rng(2)
    capture = nerfstudio_capture(tmp_path / "c", rng, {"k1": -0.2, "k2": 0.05}, size=SIZE)
    weights = [rng.dirichlet(np.ones(4), SIZE[::-1]).astype(np.float32) for _ in range(3)]
    write_stack(WeightStack((np.eye(4, 3) * 0.8 + 0.1).astype(np.float32), weights,
                            [f"images/f{i}.png" for i in range(3)]), tmp_path / "w.npz")
    from palette_core.stack import read_stack

    dataset = load_dataset(capture, downscale=2)
    joined = join_weights(dataset, read_stack(tmp_path / "w.npz"))
    assert joined.shape == (len(dataset.indices("train")), 15, 20, 4)
    assert np.allclose(joined.sum(-1), 1, atol=1e-5) and joined.min() >= 0
    lens = dataset.lenses[0]
    expected = lens.undistort(weights[0])[:30, :40].reshape(15, 2, 20, 2, 4).mean((1, 3))
    assert np.allclose(joined[0], expected, atol=1e-6)


@pytest.mark.parametrize("layout, lens", [
    ("colmap", "FOV 40 30 40 40 20 15 0.5"),
    ("colmap", "FULL_OPENCV 40 30 40 40 20 15 -0.2 0.05 0 0 0 0.1 0 0"),
    ("nerfstudio", {"camera_model": "EQUIRECTANGULAR"}),
    ("nerfstudio", {"camera_model": "OPENCV_FISHEYE", "p1": 0.01}),
])
def test_lenses_we_cannot_undistort_are_one_line(tmp_path, capsys, layout, lens):
    from nerf_stage.cli import main as nerf

    rng = np.random.default_rng(3)
    if layout == "colmap":
        pytest.importorskip("pycolmap")
        capture = colmap_capture(tmp_path / "c", rng, binary=False, camera=lens, size=SIZE)
    else:
        capture = nerfstudio_capture(tmp_path / "c", rng, lens, size=SIZE)
    assert nerf(["train", str(capture), "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "not supported" in err or "tangential" in err
    assert not (tmp_path / "run").exists()


def test_a_transforms_file_with_nan_distortion_is_refused(tmp_path):
    capture = nerfstudio_capture(tmp_path / "c", np.random.default_rng(4), {"k1": 0.0},
                                 size=SIZE)
    text = (capture / "transforms.json").read_text().replace('"k1": 0.0', '"k1": NaN')
    (capture / "transforms.json").write_text(text)
    assert json.loads(text)["k1"] != json.loads(text)["k1"]  # NaN, as Python writes it
    with pytest.raises(InputError, match="finite"):
        load_dataset(capture)
