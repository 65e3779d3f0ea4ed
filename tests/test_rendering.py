"""Scene box, occupancy grid and volume rendering: compositing of M channels, the visual
hull, empty-space skipping, early termination, deferred shading, orbits."""


import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage.data.cameras import orbit_poses, rig_poses  # noqa: E402
from nerf_stage.data.dataset import load_dataset  # noqa: E402
from nerf_stage.fields.base import RaySampling  # noqa: E402
from nerf_stage.render import march as rendering  # noqa: E402
from nerf_stage.render import occupancy as occupancy_module  # noqa: E402
from nerf_stage.render.march import composite, render_rays  # noqa: E402
from nerf_stage.render.occupancy import OccupancyGrid  # noqa: E402
from nerf_stage.render.scene_box import scene_box, visual_hull  # noqa: E402


def test_m_channel_compositing_equals_rgb_compositing_for_one_hot_weights(rng):
    sigma = torch.as_tensor(rng.uniform(0, 3, (5, 7)))
    deltas = torch.as_tensor(rng.uniform(0.05, 0.3, (5, 7)))
    palette = torch.as_tensor(rng.uniform(0, 1, (4, 3)))
    one_hot = torch.nn.functional.one_hot(torch.as_tensor(rng.integers(0, 4, (5, 7))), 4)
    weights, _ = composite(sigma, deltas)
    composited_weights = (weights[..., None] * one_hot).sum(1)
    composited_rgb = (weights[..., None] * (one_hot.double() @ palette)).sum(1)
    assert torch.allclose(composited_weights.double() @ palette, composited_rgb)
    assert torch.all(weights.sum(1) <= 1)


def test_visual_hull_keeps_the_objects(still_life):
    data = load_dataset(still_life)
    train_ids = data.indices("train")
    box = scene_box(data.poses[train_ids], data.cameras(train_ids), data.alpha[train_ids])
    hull = visual_hull(box, np.array([16, 16, 16]), data.poses[train_ids], data.cameras(train_ids),
                       data.alpha[train_ids])
    for centre in ([0.7, 0.5, -0.4], [-0.7, 0.4, -0.5], [1.1, 0.25, 0.7]):  # globe, box, ball
        cell = np.floor((np.array(centre) - box.centre + box.half) / (2 * box.half) * 16)
        assert hull[tuple(cell.astype(int))]
    assert 0 < hull.mean() < 1


def test_occupancy_bounds_frame_the_occupied_cells():
    grid = OccupancyGrid(torch.tensor([1.0, 0.5, 1.0]), 8 * 4 * 8)
    assert np.allclose(grid.bounds(), [[-1, -0.5, -1], [1, 0.5, 1]])  # all occupied
    grid.occupied.zero_()
    grid.occupied[2, 1, 7] = True
    assert np.allclose(grid.bounds(), [[-0.5, -0.25, 0.75], [-0.25, 0.0, 1.0]])


def test_orbit_sweeps_the_front_arc_and_looks_at_the_centre():
    poses = rig_poses("front-arc", 10, [0, 1, 0], 4.0, (0, 10), 60)
    orbit = orbit_poses(poses, 12, [0, 1, 0])
    eyes = orbit[:, :3, 3] - [0, 1, 0]
    azimuth = np.degrees(np.arctan2(eyes[:, 0], eyes[:, 2]))
    assert azimuth.min() >= -27.5 and azimuth.max() <= 27.5 and np.ptp(azimuth) > 50
    assert np.allclose(np.linalg.norm(eyes, axis=1), 4.0)
    assert np.allclose(np.einsum("ni,ni->n", -orbit[:, :3, 2], -eyes / 4.0), 1)


class _Sphere:
    """An opaque ball of radius 0.5 that shows its positions as colours."""

    deferred = False

    def __init__(self, radius: float = 0.5, density: float = 1e3):
        self.radius, self.sigma = radius, density
        self.shaded = 0  # points the colour part ran at

    def density(self, x):
        return self.sigma * (x.norm(dim=-1) < self.radius).float(), x

    def colour(self, h, d):
        self.shaded += len(h)
        return h


def test_deferred_shading_runs_the_colour_part_once_a_ray():
    """A linear colour part shades alike per sample and deferred, also through fog that
    leaves rays part transparent; deferred shading runs it once a ray."""
    occupancy = OccupancyGrid(torch.ones(3), 8**3)
    origins = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.3, 0.1], [-3.0, 0.9, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    per_sample, deferred = _Sphere(0.6, 0.5), _Sphere(0.6, 0.5)
    deferred.deferred = True
    with torch.no_grad():
        expected, samples = render_rays(per_sample, occupancy, origins, directions,
                                        RaySampling(step=0.01))
        values, _ = render_rays(deferred, occupancy, origins, directions, RaySampling(step=0.01))
    assert 0.1 < samples.opacity[0] < 0.9 and samples.opacity[2] == 0
    assert torch.allclose(values, expected, atol=1e-5)
    assert deferred.shaded == 3 and per_sample.shaded > 100


def test_rendering_stops_rays_at_surfaces_and_keeps_their_values():
    occupancy = OccupancyGrid(torch.ones(3), 8**3)
    origins = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.2, 0.1], [-3.0, 0.9, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    sampling = RaySampling(step=0.01)
    with torch.no_grad():
        values, samples = render_rays(_Sphere(), occupancy, origins, directions, sampling)
    unstopped, all_samples = render_rays(_Sphere(), occupancy, origins, directions, sampling)
    assert torch.allclose(values, unstopped, atol=1e-4)
    assert torch.allclose(samples.opacity, torch.tensor([1.0, 1.0, 0.0]), atol=1e-4)
    marched, unstopped_marched = (torch.bincount(s.ray, minlength=3).tolist()
                                  for s in (samples, all_samples))
    assert unstopped_marched == [200] * 3  # 2 units of box at steps of 0.01
    assert marched[0] < 100 and marched[1] < 100 and marched[2] == 200


def test_empty_space_is_skipped_in_whole_steps_and_renders_stay_the_same(monkeypatch, rng):
    occupancy = OccupancyGrid(torch.ones(3), 16**3)
    centres = -1 + (torch.nonzero(torch.ones(16, 16, 16)) + 0.5) / 8
    occupancy.occupied = (centres.norm(dim=-1) < 0.6).reshape(16, 16, 16)
    ahead = torch.as_tensor(rng.normal(size=(64, 3)), dtype=torch.float32)
    origins = -3 * ahead / ahead.norm(dim=-1, keepdim=True)
    targets = torch.as_tensor(rng.uniform(-0.8, 0.8, (64, 3)), dtype=torch.float32)
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far = rendering.box_intersection(origins, directions, occupancy.extent)
    moved = occupancy.skip_empty(origins, directions, near, far, 0.01)
    steps = ((moved - near) / 0.01)[moved < far]  # the others get no samples at all
    assert torch.allclose(steps, steps.round(), atol=1e-3) and (steps >= 0).all()
    t = torch.arange(0, 5, 1e-3)
    inside = torch.stack([occupancy.lookup(o + t[:, None] * d)
                          for o, d in zip(origins, directions)])
    meets = inside.any(1)  # rays that cross an occupied cell, and where they first do
    first = t[inside.int().argmax(1)]
    assert meets.any() and (~meets).any()
    assert (moved[meets] <= first[meets]).all()
    stop = origins + torch.minimum(moved, far - 1e-4)[:, None] * directions
    u = ((stop + 1) * 8).long().clamp(0, 15)
    beside = occupancy.free_distance()[u[:, 0], u[:, 1], u[:, 2]] <= 1
    assert ((moved == far) | beside).all()  # rays stop skipping only beside an occupied cell
    corner, x = torch.tensor([[-3.0, 0.95, 0.95]]), torch.tensor([[1.0, 0.0, 0.0]])
    entry, exit_ = rendering.box_intersection(corner, x, occupancy.extent)
    assert occupancy.skip_empty(corner, x, entry, exit_, 0.01) == exit_  # far from every cell
    with torch.no_grad():
        skipped = render_rays(_Sphere(), occupancy, origins, directions, RaySampling(step=0.01))
        monkeypatch.setattr(occupancy_module, "MAX_SKIPS", 0)
        marched = render_rays(_Sphere(), occupancy, origins, directions, RaySampling(step=0.01))
    assert torch.allclose(skipped[0], marched[0], atol=1e-4)
    assert torch.allclose(skipped[1].opacity, marched[1].opacity, atol=1e-4)


def test_the_free_distance_follows_the_occupied_cells():
    occupancy = OccupancyGrid(torch.ones(3), 8**3)
    occupancy.occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    assert (occupancy.free_distance() > 8 * 3**0.5).all()  # nothing occupied: rays skip the box
    occupancy.occupied[0, 0, 0] = True
    assert occupancy.free_distance()[7, 7, 7] == 7 and occupancy.free_distance()[0, 0, 0] == 0


def test_each_view_renders_with_its_own_camera(scene_run):
    from dataclasses import replace

    from nerf_stage.train.loading import load_run

    run = load_run(scene_run)
    poses = orbit_poses(rig_poses("orbit", 4, [0, 0.4, 0], 4.5, (20, 30)), 2, [0, 0.4, 0])
    wide = replace(run.intrinsics, fx=run.intrinsics.fx / 2, fy=run.intrinsics.fy / 2)
    both, _ = run.render(poses, intrinsics=[run.intrinsics, wide])
    first, _ = run.render(poses[:1])
    second, _ = run.render(poses[1:], intrinsics=wide)
    assert np.array_equal(both[0], first[0]) and np.array_equal(both[1], second[0])
    assert not np.array_equal(run.render(poses[1:])[0][0], second[0])
