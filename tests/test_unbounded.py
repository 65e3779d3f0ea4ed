"""Unbounded scenes: the contraction of space beyond the box, marching in it, the choice of
space from the images, and a run that trains, saves and renders in it."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage.data.cameras import look_at, rig_poses  # noqa: E402
from nerf_stage.data.dataset import load_dataset  # noqa: E402
from nerf_stage.fields.base import RaySampling  # noqa: E402
from nerf_stage.render.contraction import FAR, contract, ray_interval, ray_points  # noqa: E402
from nerf_stage.render.march import march_rays, scale_near_gradients  # noqa: E402
from nerf_stage.render.occupancy import OccupancyGrid  # noqa: E402
from nerf_stage.render.scene_box import CAMERA_REACH, scene_box  # noqa: E402
from nerf_stage.splats.baking import bake_run  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402
from palette_core.errors import InputError  # noqa: E402

from .nerf_runs import tiny_config, trained  # noqa: E402


def test_contraction_keeps_the_box_and_maps_infinity_into_the_shell(rng):
    inside = torch.as_tensor(rng.uniform(-1, 1, (100, 3)))
    assert torch.equal(contract(inside), inside)
    far = torch.nn.functional.normalize(torch.as_tensor(rng.normal(size=(100, 3))), dim=-1)
    for distance in (2.0, 10.0, 1e6):
        norm = contract(far * distance * 3).abs().amax(-1)
        assert torch.all((norm > 1) & (norm < 2))
    assert torch.allclose(contract(far * 1e12).abs().amax(-1), torch.full((100,), 2.0,
                                                                          dtype=torch.float64))


def test_marching_is_linear_in_the_box_then_in_disparity():
    origins, directions = torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]])
    near, far, bend = ray_interval(torch.tensor([1.0]))
    assert near.item() == 0 and bend.item() == 1 and far.item() == pytest.approx(2 - 1 / FAR)
    u = torch.tensor([[0.5, 1.0, 1.5, 1.75]])
    points = ray_points(origins, directions, u, bend[:, None])
    # t = 0.5, 1, 2, 4: contracted to 0.5, 1, 1.5, 1.75 (a step in u is a step in the shell)
    assert torch.allclose(points[0, :, 0], torch.tensor([0.5, 1.0, 1.5, 1.75]))


class _Fog:
    """A field of density ``sigma`` everywhere; its features are the positions."""

    def __init__(self, sigma=1.0):
        self.sigma = sigma

    def density(self, x):
        return torch.full((len(x),), self.sigma), x


@pytest.mark.parametrize("grad", [False, True])
def test_rays_that_meet_nothing_end_in_the_sky_which_only_their_direction_places(grad):
    grid = OccupancyGrid(torch.full((3,), 2.0), 16**3, contracted=True)
    origins = torch.tensor([[0.9, 0.0, 0.0], [-0.5, 0.3, 0.2], [0.0, 0.0, 0.0]])
    directions = torch.nn.functional.normalize(torch.tensor([[0.2, 1.0, 0.1]] * 3), dim=-1)
    with torch.set_grad_enabled(grad):
        samples = march_rays(_Fog(0.0), grid, origins, directions,
                             RaySampling(step=0.05, sky=True))
    assert torch.equal(samples.opacity, torch.ones(3))
    assert torch.all(samples.ray[1:] >= samples.ray[:-1])  # packed by ray, sky last
    last = torch.tensor([int(torch.nonzero(samples.ray == r)[-1]) for r in range(3)])
    assert torch.equal(samples.weight[last], torch.ones(3))
    sky = samples.h[last]
    assert torch.allclose(sky, sky[:1].expand(3, 3), atol=0.01)
    assert torch.allclose(sky.abs().amax(-1), torch.full((3,), 2.0), atol=0.01)
    dense = march_rays(_Fog(1e3), grid, origins, directions, RaySampling(step=0.05, sky=True))
    assert dense.h.abs().amax(-1).max() < 1.99  # no light left for the sky
    open_sky = march_rays(_Fog(0.0), grid, origins, directions, RaySampling(step=0.05))
    assert torch.equal(open_sky.opacity, torch.zeros(3))  # the background shows


def test_near_gradients_are_scaled_by_the_squared_distance():
    values = torch.ones(4, 2, requires_grad=True)
    t = torch.tensor([0.0, 0.25, 0.5, 2.0])
    scaled = scale_near_gradients(values, t, 0.5)
    assert torch.equal(scaled, values)
    scaled.sum().backward()
    assert torch.allclose(values.grad[:, 0], torch.tensor([0.0, 0.25, 1.0, 1.0]))


def test_a_contracted_grid_skips_empty_space_only_inside_the_box():
    grid = OccupancyGrid(torch.full((3,), 2.0), 16**3, contracted=True)
    grid.occupied.zero_()
    grid.occupied[0, 8, 8] = True  # far out on -x: in the shell
    origins, directions = torch.tensor([[0.9, 0.0, 0.0]]), torch.tensor([[-1.0, 0.0, 0.0]])
    near, far, bend = ray_interval(torch.tensor([1.9]))
    moved = grid.skip_empty(origins, directions, near, far, 0.05, bend)
    assert 0 < moved.item() <= bend.item()  # across the empty box, not into the shell
    field = _Fog()
    samples = march_rays(field, grid, origins, directions, RaySampling(step=0.05))
    assert len(samples.ray) > 0  # the occupied shell cell is still reached


def test_opaque_images_make_an_unbounded_scene_and_transparent_ones_a_box(still_life):
    data = load_dataset(still_life)
    train = data.indices("train")
    poses, intrinsics, alpha = data.poses[train], data.cameras(train), data.alpha[train]
    assert alpha.min() < 1
    assert not scene_box(poses, intrinsics, alpha).unbounded
    box = scene_box(poses, intrinsics, np.ones_like(alpha))
    assert box.unbounded and box.sky and np.allclose(box.half, box.half[0])
    assert np.allclose(box.field_extent, 2)
    assert not scene_box(poses, intrinsics, np.ones_like(alpha), "box").unbounded
    forced = scene_box(poses, intrinsics, alpha, "unbounded")
    assert forced.unbounded and not forced.sky  # transparent pixels show the background
    ring = rig_poses("orbit", 8, [0, 0, 0], 4.0, (10, 10), 360)
    assert scene_box(ring, intrinsics[:1] * 8, np.ones((8, 2, 2))).unbounded


def test_an_unbounded_box_reaches_every_camera_of_a_walk_down_a_street():
    # parallel optical axes meet nowhere: the point nearest to them can sit beside one camera
    poses = np.stack([look_at([0.0, 0.0, -z], [0.0, 0.0, -z - 10.0]) for z in range(8)])
    box = scene_box(poses, None, np.ones((8, 2, 2)))
    reach = np.abs(poses[:, :3, 3] - box.centre).max(1) / box.scale
    assert box.unbounded and reach.max() <= CAMERA_REACH + 1e-9


def test_an_unbounded_run_trains_saves_and_renders(still_life, tmp_path):
    run = trained(still_life, tiny_config(space="unbounded"), tmp_path / "run")
    assert run.box.unbounded and run.occupancy.contracted
    loaded = load_run(tmp_path / "run")
    assert loaded.box.unbounded and loaded.occupancy.contracted
    data = load_dataset(still_life)
    values, opacity = loaded.render(data.poses[data.indices("test")][:1], progress=False)
    assert np.isfinite(values).all() and np.all((opacity >= 0) & (opacity <= 1 + 1e-6))
    assert np.allclose(values.sum(-1), opacity, atol=1e-4)  # additive weights sum to opacity
    assert len(bake_run(tmp_path / "run", refine_steps=1, progress=False).centres)


def test_distortion_loss_is_the_pairwise_sum_and_prefers_compact_rays(rng):
    from nerf_stage.train.losses import distortion_loss

    ray = torch.as_tensor(np.sort(rng.integers(0, 4, 40)))
    t = torch.cat([torch.sort(torch.as_tensor(rng.uniform(0, 3, int((ray == r).sum()))))[0]
                   for r in range(4)])
    w = torch.as_tensor(rng.uniform(0, 0.2, 40))
    brute = sum((w[ray == r][:, None] * w[ray == r][None] * (t[ray == r][:, None]
                 - t[ray == r][None]).abs()).sum() + (w[ray == r] ** 2).sum() * 0.1 / 3
                for r in range(4)) / 4
    assert torch.isclose(distortion_loss(ray, t, w, 0.1, 4), brute)
    one = torch.zeros(10, dtype=torch.long)
    steps = torch.linspace(0, 1, 10)
    compact = torch.tensor([0, 0, 0, 0, 0.5, 0.5, 0, 0, 0, 0])
    spread = torch.tensor([0.5, 0, 0, 0, 0, 0, 0, 0, 0, 0.5])
    assert distortion_loss(one, steps, compact, 0.1, 1) < distortion_loss(one, steps, spread,
                                                                           0.1, 1)


@pytest.mark.parametrize("gain, unbounded", [(5.0, False), (7.0, True)])
def test_auto_keeps_the_box_for_transparent_images_unless_a_probe_fits_far_better(
        still_life, tmp_path, monkeypatch, gain, unbounded):
    from nerf_stage.train import trainer

    probed = []

    def probe(config, box, *args):
        probed.append((box.unbounded, config.strategy, config.total_iters))
        return 20.0 + gain * box.unbounded

    monkeypatch.setattr(trainer, "_probe", probe)
    run = trained(still_life, tiny_config(), tmp_path / "run")
    assert run.box.unbounded == unbounded and not run.box.sky
    assert [p[0] for p in probed] == [False, True] and all(p[1:] == ("rgb", 4) for p in probed)
    assert load_run(tmp_path / "run").box.unbounded == unbounded
    probed.clear()
    trained(still_life, tiny_config(space="box"), tmp_path / "box")
    assert not probed  # a chosen space is not probed


def test_cameras_that_all_stand_at_one_point_are_refused():
    poses = np.stack([look_at([0.0, 0.0, 0.0], [np.cos(a), 0.0, np.sin(a)])
                      for a in np.linspace(0, 6, 8)])
    with pytest.raises(InputError, match="one point"):
        scene_box(poses, None, np.ones((8, 2, 2)))
