"""Where splats start (``splats/start.py``): at sparse points, where the views look, where
the views see no point, and never wider than the reach allows."""

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage.data.cameras import look_at  # noqa: E402
from nerf_stage.splats import start  # noqa: E402
from nerf_stage.splats.sh import SH_C0  # noqa: E402

from .splat_cases import CAMERA  # noqa: E402


def _views_of(box, alpha=None):
    """Two views of ``box`` (CAMERA), right halves blue, left halves black."""
    from nerf_stage.splats.start import SeenViews

    poses = np.stack([look_at(box.centre + np.array([0.0, -0.75, 0.25]) * box.scale,
                              box.centre, up=(0, 0, 1)),
                      look_at(box.centre + np.array([0.6, 0.1, 0.1]) * box.scale, box.centre,
                              up=(0, 0, 1))])
    images = np.zeros((2, CAMERA.height, CAMERA.width, 3), np.float32)
    images[:, :, CAMERA.width // 2:] = (0.2, 0.4, 0.9)
    alpha = np.ones(images.shape[:3], np.float32) if alpha is None else alpha
    return SeenViews(poses, [CAMERA, CAMERA], images, alpha)

@pytest.mark.parametrize("unbounded", [False, True])
def test_scenes_without_points_start_their_splats_where_the_views_look(unbounded):
    """Each starting splat lies on the ray through a point of an opaque pixel of a training
    view, in that pixel's colour, within the box (or, unbounded, about half of them beyond
    it, within ten times the distance at which its ray leaves the box)."""
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.splats.start import initial_splats

    box = SceneBox(np.array([0.0, 0.0, 1.0]), np.array([8.0, 8.0, 4.0]), unbounded=unbounded)
    alpha = np.ones((2, CAMERA.height, CAMERA.width), np.float32)
    alpha[1, :, :CAMERA.width // 2] = 0  # the second view's black half is transparent
    views = _views_of(box, alpha)
    start = initial_splats(box, 400, 0, torch.Generator().manual_seed(0), views)
    world = start["means"].numpy() * box.scale + box.centre
    colours = SH_C0 * start["colours"].numpy() + 0.5
    seen = np.zeros((2, len(world)), bool)
    for i, pose in enumerate(views.poses):  # on a pixel of its colour, opaque
        local = (world - pose[:3, 3]) @ pose[:3, :3]
        x = CAMERA.cx + CAMERA.fx * local[:, 0] / -local[:, 2]
        y = CAMERA.cy - CAMERA.fy * local[:, 1] / -local[:, 2]
        inside = (-local[:, 2] > 0) & (x >= 0) & (x < CAMERA.width) & (y >= 0) & (
            y < CAMERA.height)
        right = x >= CAMERA.width // 2
        colour = np.where(right[:, None], (0.2, 0.4, 0.9), 0.0)
        seen[i] = inside & np.isclose(colours, colour, atol=1e-5).all(1) & (right | (i == 0))
    assert seen.any(0).mean() > 0.95 and len(world) == 400
    reach = np.abs(start["means"].numpy()).max(1)
    if unbounded:
        assert 0.3 < (reach > 1).mean() < 0.7 and reach.max() <= 10 * (0.8 + np.sqrt(3))
    else:
        assert (np.abs(start["means"].numpy()) <= box.extent + 1e-5).all()

def test_bounded_scenes_start_their_splats_in_the_visual_hull():
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.splats.start import initial_splats

    box = SceneBox(np.zeros(3), np.array([2.0, 2.0, 2.0]))
    hull = np.zeros((4, 4, 4), bool)
    hull[1:3, 1:3, 1:3] = True  # the middle half of the box, less one cell
    hull[2, 2, 2] = False
    views = replace(_views_of(box), hull=hull)
    means = initial_splats(box, 200, 1, torch.Generator().manual_seed(0), views)["means"].numpy()
    assert len(means) > 150
    cells = np.clip(((means / box.extent * 0.5 + 0.5) * 4).astype(int), 0, 3)
    assert hull[tuple(cells.T)].all()

def test_splats_started_where_the_views_look_are_no_wider_than_the_reach_allows():
    """Far splats of an unbounded scene lie far apart: each starts at most ``widest`` times
    its distance to the nearest camera wide, as sparse points do."""
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.splats.start import initial_splats

    box = SceneBox(np.zeros(3), np.full(3, 2.0), unbounded=True)
    views = _views_of(box)
    eyes = (views.poses[:, :3, 3] - box.centre) / box.scale
    start = initial_splats(box, 300, 0, torch.Generator().manual_seed(0), views, eyes=eyes,
                           widest=0.02)
    nearest = np.linalg.norm(start["means"].numpy()[:, None] - eyes[None], axis=2).min(1)
    width = np.exp(start["scales"].numpy()[:, 0])
    assert (width <= 0.02 * nearest * (1 + 1e-5)).all()
    assert (width > 0.019 * nearest).mean() > 0.5  # the far ones, at least, are capped

def test_a_capture_with_sparse_points_starts_its_splats_there():
    """3D Gaussian splatting's start: splats at (at most ``n`` of) the points, in their
    colours, as wide as their neighbours are far."""
    from nerf_stage.data.points import Points
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.splats.sh import SH_C0
    from nerf_stage.splats.start import initial_splats

    box = SceneBox(np.array([1.0, 2.0, 3.0]), np.array([2.0, 1.0, 1.0]))
    rng = np.random.default_rng(0)
    points = Points(box.centre + rng.uniform(-1, 1, (40, 3)), rng.uniform(size=(40, 3)))
    start = initial_splats(box, 30, 2, torch.Generator().manual_seed(0), points=points)
    assert len(start["means"]) == 30
    world = start["means"].numpy() * box.scale + box.centre
    nearest = np.abs(world[:, None] - points.positions[None]).sum(-1).argmin(1)
    assert np.allclose(world, points.positions[nearest], atol=1e-5)
    colours = SH_C0 * start["colours"].numpy() + 0.5
    assert np.allclose(colours, points.colours[nearest], atol=1e-5)
    assert len(set(nearest.tolist())) == 30 and start["colours_rest"].shape == (30, 8, 3)

@pytest.mark.parametrize("unbounded", [False, True])
def test_splats_start_where_the_views_see_no_point_too(unbounded, monkeypatch):
    """Points seen in the left half of a view leave its right half empty: splats start
    there too, on rays through its pixels, in their colour, no nearer than the points, as
    many for that half as the points are for the other."""
    from nerf_stage.data.points import Points
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.splats.start import initial_splats

    monkeypatch.setattr(start, "COVER_CELLS", CAMERA.width // 2)  # cells of 2 x 2 pixels
    box = SceneBox(np.zeros(3), np.full(3, 2.0), unbounded=unbounded)
    alpha = np.ones((2, CAMERA.height, CAMERA.width), np.float32)
    alpha[1] = 0  # the second view is transparent: the first alone counts
    views = _views_of(box, alpha)
    pose, depth = views.poses[0], 0.8 * box.scale
    y, x = np.mgrid[:CAMERA.height, :CAMERA.width // 2] + 0.5  # the left half's pixel centres
    local = np.stack([(x - CAMERA.cx) / CAMERA.fx, -(y - CAMERA.cy) / CAMERA.fy,
                      -np.ones_like(x)], -1).reshape(-1, 3) * depth
    points = Points(local @ pose[:3, :3].T + pose[:3, 3], np.full((len(local), 3), 0.5))
    started = initial_splats(box, 1000, 0, torch.Generator().manual_seed(0), views, points)
    world = started["means"].numpy()[len(points):] * box.scale + box.centre
    assert len(world) == len(points)  # the empty half is as large as the other
    seen = (world - pose[:3, 3]) @ pose[:3, :3]
    px = CAMERA.cx + CAMERA.fx * seen[:, 0] / -seen[:, 2]
    distance = np.linalg.norm(world - pose[:3, 3], axis=1)
    assert (distance >= depth * (1 - 1e-5)).all() and (px >= CAMERA.width // 2).all()
    colours = SH_C0 * started["colours"].numpy()[len(points):] + 0.5
    assert np.allclose(colours, (0.2, 0.4, 0.9), atol=1e-5)

def test_sparse_points_near_a_camera_start_no_wider_than_the_reach_allows():
    """Points far apart start as wide as their neighbours are far, except where that would
    draw them past ``--splats-reach`` in the nearest view: there at most ``widest`` times
    their distance to it, so that no starting splat is cut off square."""
    from nerf_stage.data.points import Points
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.splats.start import initial_splats

    box = SceneBox(np.zeros(3), np.ones(3))
    positions = np.array([[0.0, 0, 0], [0.9, 0, 0], [0, 0.9, 0], [0, 0, 0.9], [0.9, 0.9, 0.9]])
    points = Points(positions, np.full((5, 3), 0.5))
    eyes = np.array([[0.0, 0, 2], [0, 0, -5]])
    free = initial_splats(box, 5, 0, torch.Generator().manual_seed(0), points=points)
    capped = initial_splats(box, 5, 0, torch.Generator().manual_seed(0), points=points, eyes=eyes,
                            widest=0.05)
    means = capped["means"].numpy()
    nearest = np.linalg.norm(means[:, None] - eyes[None], axis=2).min(1)
    width = np.exp(capped["scales"].numpy()[:, 0])
    assert np.allclose(width, np.minimum(np.exp(free["scales"].numpy()[:, 0]), 0.05 * nearest),
                       rtol=1e-5)
    assert (width < np.exp(free["scales"].numpy()[:, 0])).all()
