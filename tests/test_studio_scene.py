"""The studio's scene mode without a browser: views cached and recoloured without the
network, turntable and splat exports, the splats drawn and recoloured."""

import numpy as np
import pytest

pytest.importorskip("viser")

from palette_core.basis import weights_to_rgb  # noqa: E402
from palette_core.errors import InputError, OutputExists  # noqa: E402
from studio.app import Studio  # noqa: E402


def test_scene_views_are_cached_and_recoloured_without_the_network(scene_run, monkeypatch):
    from studio.scene import SceneTarget

    target = SceneTarget.open(scene_run)
    camera = target.intrinsics(1.5, 12)
    assert (camera.width, camera.height) == (18, 12)
    pose = target.home_pose()
    first = target.render(pose, camera)
    assert np.isclose(target.shares().sum(), 1)
    assert first.weights.shape[1:3] == (12, 18)
    calls = []
    monkeypatch.setattr(target.run, "render", lambda *a, **k: calls.append(a))
    again = target.render(pose.copy(), camera)
    assert again is first and not calls
    edited = target.palette[::-1]
    image = again.recolor(edited)[0]
    expected = weights_to_rgb(first.weights[0], edited) + (1 - first.opacity[0, ..., None]) * \
        first.background
    assert np.allclose(image, np.clip(expected, 0, 1))


def test_scene_turntable_and_splat_exports(scene_run, tmp_path):
    import trimesh

    from nerf_stage.edit.regions import Region
    from nerf_stage.splats import SH_C0
    from studio.scene import SceneTarget

    target = SceneTarget.open(scene_run)
    gif = tmp_path / "turn.gif"
    args = (target.palette, target.home_pose(), target.intrinsics(1.0, 8))
    assert target.export(gif, *args, views=3) == [gif]
    from PIL import Image

    assert Image.open(gif).n_frames == 3
    with pytest.raises(OutputExists):
        target.export(gif, *args, views=3)
    with pytest.raises(InputError, match=".gif"):
        target.export(tmp_path / "turn.png", *args, views=3)
    ply, edited = tmp_path / "scene.ply", target.palette[::-1]
    nowhere = Region("box", (1e3, 1e3, 1e3), (1.0, 1.0, 1.0))  # the edit reaches no splat
    assert target.export(ply, edited, *args[1:], regions=[nowhere]) == [ply]
    table = trimesh.load(ply).metadata["_ply_raw"]["vertex"]["data"]
    colours = np.stack([table[f"f_dc_{i}"] for i in range(3)], 1) * SH_C0 + 0.5
    assert np.allclose(colours, target.splats.colours(), atol=1e-5)


def test_scene_mode_draws_splats_and_recolours_them(scene_run, monkeypatch):
    from nerf_stage import splats as splat_module
    from studio.scene import SceneTarget

    target = SceneTarget.open(scene_run, refine_steps=5)
    assert target.splats is not None and (scene_run / splat_module.SPLAT_CACHE).is_file()
    monkeypatch.setattr(splat_module, "bake_run", lambda *a, **k: pytest.fail("baked again"))
    again = SceneTarget.open(scene_run)  # the kept bake of the same run
    assert np.array_equal(again.splats.centres, target.splats.centres)
    run_pose = target.run.dataset().poses[0]
    assert np.array_equal(target.home_pose(), run_pose)  # the first training camera
    studio = Studio(target, port=0)
    try:
        view = studio.view
        assert view.splats_drawn
        edited = target.palette[::-1].copy()
        studio._apply(lambda: [studio.editor.set_colour(i, c) for i, c in enumerate(edited)])
        assert np.allclose(view.splat_colours(), target.splats.colours(edited))
        view.gizmo.position = tuple(target.splats.centres[0])
        view.size.value = (1e-3, 1e-3, 1e-3)
        view.local.value = True  # a box around one splat: only it takes the edit
        colours = view.splat_colours()
        assert np.allclose(colours[0], target.splats.colours(edited)[0])
        assert np.allclose(colours[1:], target.splats.colours()[1:])
        view.drawer.value = "network (on the server)"
        assert not view.splats_drawn
    finally:
        studio.stop()


def test_a_splat_file_opens_in_the_studio_and_exports_its_edit(tmp_path, rng):
    """A splat file is decomposed as it opens; the browser's colours follow the palette's
    change; the unedited export is the file again and a box keeps an edit inside it."""
    from splat_files import read_splat_file, write_splat_file
    from studio.app import open_target

    from .test_splat_files import ATTRIBUTES, scene

    path = write_splat_file(scene(rng, 200), tmp_path / "scene.ply")
    target = open_target(str(path))
    assert target.mode == "splat file" and target.splats.weights.shape == (200, 6)
    assert np.allclose(target.splats.colours(), target.stack.colours(), atol=1e-5)
    studio = Studio(target, port=0)
    try:
        view = studio.view
        assert view.splats_drawn and view.drawer.options == ("splats (in the browser)",)
        edited = target.palette.copy()
        edited[0] = [1.0, 0.0, 0.0]
        studio._apply(lambda: studio.editor.set_colour(0, edited[0]))
        change = target.stack.change(edited)
        assert np.allclose(view.splat_colours(), np.clip(target.stack.colours() + change, 0, 1),
                           atol=1e-5)
    finally:
        studio.stop()
    same = target.export(tmp_path / "same.ply", target.palette)[0]
    assert all(np.array_equal(getattr(read_splat_file(same), k), getattr(target.stack.fields, k))
               for k in ATTRIBUTES)
    from nerf_stage.edit.regions import Region

    box = Region("box", tuple(map(float, target.stack.fields.means[0])), (1e-3, 1e-3, 1e-3))
    one = read_splat_file(target.export(tmp_path / "one.ply", edited, regions=[box])[0])
    moved = (one.sh0 != target.stack.fields.sh0).any(1)
    assert moved.sum() <= 1 and not moved[1:].any()
    with pytest.raises(InputError, match="turntable"):
        target.export(tmp_path / "turn.gif", edited)
