"""NDC space for forward-facing captures: the map and its inverse, rays that stay straight,
points' depth targets, and a run that trains, saves and renders in it."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage.cli import main as nerf  # noqa: E402
from nerf_stage.data.cameras import Intrinsics, camera_rays, look_at  # noqa: E402
from nerf_stage.data.dataset import load_dataset  # noqa: E402
from nerf_stage.data.points import Points  # noqa: E402
from nerf_stage.render.ndc import (  # noqa: E402
    NDCFrame,
    forward_facing,
    frame_from_dict,
    reference_frame,
)
from nerf_stage.render.scene_box import box_from_dict  # noqa: E402
from nerf_stage.train.config import TrainConfig  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402
from nerf_stage.train.trainer import choose_scene_box  # noqa: E402
from palette_core.cli.decompose import main as decompose  # noqa: E402
from palette_core.errors import InputError  # noqa: E402

from .helpers import expect_error, llff_capture  # noqa: E402
from .nerf_runs import TINY_FLAGS  # noqa: E402


def _frame(rng):
    pose = look_at(rng.normal(size=3) * 0.1, [0.2, -0.1, -3.0])
    return NDCFrame(pose[:3, :3], pose[:3, 3], 0.5, 1.6, 2.1)


def test_ndc_maps_the_frustum_onto_the_cube_and_back(rng):
    frame = _frame(rng)
    depth = np.exp(rng.uniform(np.log(0.5), np.log(1e4), 200))  # from the near plane on
    camera = np.stack([rng.uniform(-1, 1, 200) * depth / frame.sx,
                       rng.uniform(-1, 1, 200) * depth / frame.sy, -depth], 1)
    points = torch.as_tensor(camera @ frame.rotation.T + frame.eye)
    ndc = frame.from_box(points)
    assert torch.all(ndc.abs() <= 1 + 1e-9)  # inside the reference frustum past the near plane
    assert torch.allclose(frame.to_box(ndc), points, rtol=1e-6, atol=1e-6)


def test_rays_start_on_the_near_plane_and_stay_straight_to_infinity(rng):
    frame = _frame(rng)
    origins = torch.as_tensor(frame.eye + rng.normal(size=(50, 3)) * 0.05)
    directions = torch.nn.functional.normalize(
        torch.as_tensor(rng.normal(size=(50, 3)) * 0.2 - frame.rotation[:, 2]), dim=1)
    start, towards = frame.rays(origins, directions)
    assert torch.allclose(start[:, 2], torch.full((50,), -1.0, dtype=torch.float64))
    assert torch.allclose(towards.norm(dim=1), torch.ones(50, dtype=torch.float64))
    for distance in (1.0, 10.0, 1e3):  # world points on a ray lie on its NDC line, in order
        ndc = frame.from_box(origins + distance * directions)
        offset = ndc - start
        along = (offset * towards).sum(1)
        assert torch.allclose(offset, along[:, None] * towards, atol=1e-6)
        assert torch.all(along >= 0)
    backwards = frame.rays(origins[:1], -directions[:1])[0]
    assert backwards[0, 2] > 1  # a ray away from the frustum starts outside the cube


def test_a_checkpoint_frame_that_lies_is_one_line(rng):
    data = _frame(rng).to_dict()
    assert np.allclose(frame_from_dict(data, "c").rotation, data["rotation"])
    for change in ({"near": -1.0}, {"sx": float("nan")}, {"rotation": [[2, 0, 0]] * 3},
                   {"eye": "here"}):
        with pytest.raises(InputError, match="NDC frame"):
            frame_from_dict(data | change, "c")
    box = {"centre": [0, 0, 0], "half": [1, 1, 1], "ndc": data | {"near": 0.0}}
    with pytest.raises(InputError, match="NDC frame"):
        box_from_dict(box, "c")


def test_the_reference_frame_is_the_mean_camera_and_holds_every_view(rng):
    poses = np.array([look_at([x, 0.0, 0.0], [x, 0.0, -4.0]) for x in (-0.2, 0.0, 0.2)])
    camera = Intrinsics(40, 30, 50.0, 50.0, 20.0, 15.0)
    frame = reference_frame(poses, [camera] * 3, 2.0, np.array([0.0, 0.0, -2.0]), 2.0)
    np.testing.assert_allclose(frame.rotation, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(frame.eye, [0.0, 0.0, 1.0])  # normalised by the box
    assert frame.near == pytest.approx(0.75)
    # the side cameras' rays reach the cube's sides on the near plane, none beyond
    origins, directions = camera_rays(poses[0], camera)
    start, towards = frame.rays(torch.as_tensor((origins.reshape(-1, 3) - [0, 0, -2]) / 2),
                                torch.as_tensor(directions.reshape(-1, 3)))
    assert start[:, :2].abs().max() <= 1 + 1e-9 and start[:, 0].min() < -0.95
    assert frame.sx < 2 * camera.fx / camera.width  # wider than one camera's view
    with pytest.raises(InputError, match="depth bounds"):
        reference_frame(poses, [camera] * 3, None, np.zeros(3), 1.0)


def test_cameras_around_an_object_do_not_face_one_way():
    ahead = np.array([look_at([0.3 * x, 0.0, 4.0], [0.0, 0.0, 0.0]) for x in (-1, 0, 1)])
    around = np.array([look_at([4 * np.cos(a), 0.0, 4 * np.sin(a)], [0.0, 0.0, 0.0])
                       for a in np.linspace(0, np.pi, 5)])
    assert forward_facing(ahead) and not forward_facing(around)


@pytest.fixture
def llff(tmp_path, rng):
    llff_capture(tmp_path, rng)
    assert decompose([str(tmp_path / "images_2"), "-k", "4", "-o",
                      str(tmp_path / "weights.npz")]) == 0
    return tmp_path


def test_an_ndc_run_trains_saves_and_renders(llff):
    assert nerf(["train", str(llff), "-o", str(llff / "run"), "--space", "ndc",
                 *TINY_FLAGS]) == 0
    run = load_run(llff / "run")
    assert run.box.ndc is not None and run.occupancy.ndc is not None
    assert run.config.backbone == "grid" and not run.box.unbounded and run.box.sky
    data = load_dataset(llff)
    values, opacity = run.render(data.poses[data.indices("test")][:1])
    assert np.isfinite(values).all() and np.all((opacity >= 0) & (opacity <= 1 + 1e-6))
    assert np.allclose(values.sum(-1), opacity, atol=1e-4)  # additive weights sum to opacity
    box = run.box
    assert np.all(np.abs(run.bounds() - box.centre) <= box.half + 1e-9)  # the studio's orbit


def test_the_splats_refuse_ndc_in_one_line(llff, capsys):
    expect_error(nerf, ["train", str(llff), "-o", str(llff / "run"), "--space", "ndc",
                        "--backbone", "splats"], "--space ndc", capsys)


@pytest.mark.parametrize("backbone, ndc", [("grid", True), ("mlp", True), ("splats", False)])
def test_auto_puts_the_fields_of_an_llff_capture_in_ndc(llff, backbone, ndc):
    data = load_dataset(llff)
    box = choose_scene_box(TrainConfig(backbone=backbone), data, None, data.indices("train"),
                           None, "cpu", False)
    assert (box.ndc is not None) == ndc and box.sky


def test_auto_keeps_a_capture_without_depth_bounds_out_of_ndc(llff):
    data = load_dataset(llff)
    data.bounds = None  # as a forward-facing COLMAP capture
    box = choose_scene_box(TrainConfig(backbone="grid"), data, None, data.indices("train"),
                           None, "cpu", False)
    assert box.ndc is None and box.unbounded


def test_without_bounds_the_near_plane_comes_from_the_points(llff, rng):
    data = load_dataset(llff)
    data.bounds = None
    train = data.indices("train")
    assert data.nearest_depth(train) is None
    poses = data.poses[train]
    axis = -poses[:, :3, 2].mean(0) / np.linalg.norm(poses[:, :3, 2].mean(0))
    depths = rng.uniform(2.0, 6.0, 500)
    positions = poses[:, :3, 3].mean(0) + depths[:, None] * axis
    data.points = Points(np.concatenate([positions, [positions[0] - 9 * axis]]),
                         np.zeros((501, 3), np.float32))  # one point behind the cameras
    assert data.nearest_depth(train) == pytest.approx(np.percentile(depths, 1))
