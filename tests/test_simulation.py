"""Scene simulation: exactness of transport weights, cameras, dataset files, bad scenes."""

import json
import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from nerf_stage.cli import main
from nerf_stage.cli import main as nerf_stage
from nerf_stage.data.cameras import focal_from_fov, look_at, rig_poses
from nerf_stage.data.dataset import load_dataset
from nerf_stage.simulation import (
    BUILTIN_SCENES,
    load_scene,
    parse_scene,
    render_terms,
    simulate,
    view_poses,
    with_overrides,
    with_palette,
)
from nerf_stage.simulation.geometry import next_term_table
from nerf_stage.simulation.pathtracer import CYLINDER, DISC, QUAD, SPHERE, TRIANGLE, _intersect
from palette_core import InputError, read_stack
from palette_core.basis import transport_basis, transport_terms, weights_to_rgb
from palette_core.cli import recolor

from .helpers import expect_error, stack_file

EXACT = 1e-5


def tiny(scene, **overrides):
    """A few 8x8 views with few samples."""
    options = {"resolution": 8, "spp": 4, "views": [2, 0, 1]} | overrides
    return with_overrides(load_scene(scene) if isinstance(scene, str) else scene, **options)


def rgb_render(scene):
    """Radiance rendered with the albedos multiplied in (no term sorting)."""
    _, poses = view_poses(scene)
    terms, _ = render_terms(scene, poses, split=False)
    return terms[..., 0, :]


def lit_quad_scene(light="direct", editable=True, **render):
    """A floor seen from above, lit by a point light, and a wall facing away from the light."""
    return parse_scene({
        "materials": {"floor": {"albedo": [0.8, 0.3, 0.2], "editable": editable},
                      "wall": {"albedo": [0.5, 0.5, 0.5]}},
        "objects": [
            {"type": "quad", "material": "floor", "corner": [-1, 0, -1], "edge1": [0, 0, 2],
             "edge2": [2, 0, 0]},
        ],
        "lights": [{"type": "point", "position": [0, 2, 0], "intensity": 4}],
        "camera": {"rig": "hemisphere", "radius": 3, "elevation": 60, "fov": 30,
                   "resolution": 8, "views": {"train": 1}},
        "render": {"light": light, "spp": 4, **render},
    })


# --- exactness of the transport weights ------------------------------------------------------

@pytest.mark.parametrize("order", [0, 1, 2, 3])
def test_weights_recompose_the_render_exactly(order):
    scene = tiny("cornell-box", order=order)
    sim = simulate(scene, progress=False)
    assert sim.weights.shape[-1] == math.comb(4 + order, order)
    direct = rgb_render(scene)
    recomposed = weights_to_rgb(sim.weights, sim.palette, "transport", order)
    assert np.abs(recomposed - direct).max() < EXACT
    assert np.abs(sim.radiance - direct).max() < EXACT


@pytest.mark.parametrize("order", [1, 2])
def test_edited_palette_matches_a_fresh_render_of_the_edited_scene(order, rng):
    scene = tiny("cornell-box", order=order)
    sim = simulate(scene, progress=False)
    for _ in range(3):
        edited = rng.uniform(0, 1, sim.palette.shape)
        fresh = rgb_render(with_palette(scene, edited))
        recoloured = weights_to_rgb(sim.weights, edited, "transport", order)
        assert np.abs(recoloured - fresh).max() < EXACT
    assert np.abs(recoloured - sim.radiance).max() > 1e-3  # the edit did change the image


def test_written_float32_weights_recompose_to_1e5(tmp_path):
    assert main(["simulate", "cornell-box", str(tmp_path / "cb"), "--resolution", "8",
                 "--spp", "4", "--views", "2", "1", "1"]) == 0
    stack = read_stack(tmp_path / "cb" / "weights.npz")
    assert (stack.basis, stack.order, stack.method) == ("transport", 2, "simulated")
    scene = tiny("cornell-box", views=[2, 1, 1])
    assert np.allclose(stack.palette, [m.albedo for m in scene.palette_materials], atol=1e-7)
    weights = np.stack(stack.weights)
    assert np.abs(weights_to_rgb(weights, stack.palette, "transport", 2)
                  - rgb_render(scene)).max() < EXACT


def test_same_seed_same_paths_other_seed_other_paths():
    a = simulate(tiny("cornell-box"), progress=False).radiance
    b = simulate(tiny("cornell-box"), progress=False).radiance
    c = simulate(tiny("cornell-box", seed=1), progress=False).radiance
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_direct_only_weights_sit_in_the_degree_one_term():
    sim = simulate(lit_quad_scene(), progress=False)
    assert sim.order == 1 and sim.weights.shape[-1] == 2  # terms (), (0,)
    covered = sim.alpha > 0
    assert (sim.weights[..., 1][covered] > 0).all()
    assert np.abs(sim.weights[..., 0]).max() == 0  # no light reaches the camera unreflected


def test_direct_light_traces_no_bounce():
    """The back of a box, turned from the light, is black with direct light only."""
    def scene(light):
        return parse_scene({
            "materials": {"white": {"albedo": 0.8}, "red": {"albedo": [0.8, 0.1, 0.1],
                                                            "editable": True}},
            "objects": [
                {"type": "quad", "material": "white", "corner": [-2, 0, -2], "edge1": [0, 0, 4],
                 "edge2": [4, 0, 0]},
                {"type": "box", "material": "red", "center": [0, 0.5, 0], "size": [1, 1, 1]},
            ],
            "lights": [{"type": "point", "position": [0, 3, -3], "intensity": 20}],
            "camera": {"rig": "front-arc", "arc": 0, "radius": 4, "elevation": 0,
                       "target": [0, 0.5, 0], "fov": 10, "resolution": 8,
                       "views": {"train": 1}},
            "render": {"light": light, "spp": 16} | ({"order": 2} if light == "indirect"
                                                     else {}),
        })
    direct = simulate(scene("direct"), progress=False).radiance
    indirect = simulate(scene("indirect"), progress=False).radiance
    assert direct[0, 2:6, 2:6].max() == 0 and indirect[0, 2:6, 2:6].mean() > 1e-3


def test_next_term_table_walks_the_design_basis():
    for k, order in [(1, 3), (3, 2), (4, 3)]:
        terms = transport_terms(k, order)
        table = next_term_table(k, order)
        for m, term in enumerate(terms):
            for i in range(k):
                grown = tuple(sorted(term + (i,)))
                expect = terms.index(grown) if len(grown) <= order else -1
                assert table[m, i] == expect
    basis = transport_basis(np.array([[0.5, 0.5, 0.5], [0.25, 0.25, 0.25]]), 2)[:, 0]
    assert basis.tolist() == [1, 0.5, 0.25, 0.25, 0.125, 0.0625]  # 1, v0, v1, v0v0, v0v1, v1v1


def test_fixed_albedos_and_textures_stay_rgb():
    sim = simulate(lit_quad_scene(editable=False), progress=False)
    assert sim.weights is None
    pixel = sim.radiance[sim.alpha == 1][0]
    assert np.allclose(pixel / pixel[0], [1, 0.3 / 0.8, 0.2 / 0.8])


def test_still_life_has_textures_and_no_weights():
    sim = simulate(tiny("still-life"), progress=False)
    assert sim.weights is None and sim.radiance.max() > 0


# --- geometry ----------------------------------------------------------------------------------

def _row(values):
    row = np.zeros(18)
    row[: len(values)] = values
    return row


@pytest.mark.parametrize("kind, data, expect", [
    (SPHERE, [0, 0, -5, 1], 4.0),
    (QUAD, [-1, -1, -3, 2, 0, 0, 0, 2, 0, 0, 0, 1, 0, 0, 0.25], 3.0),
    (TRIANGLE, [-1, -1, -2, 3, 0, 0, 0, 3, 0, 0, 0, 1], 2.0),
    (DISC, [0, 0, -6, 0, 0, 1, 0.5, 1, 0, 0], 6.0),
    (CYLINDER, [0, -1, -4, 0, 1, 0, 1, 2, 1, 0, 0], 3.0),  # vertical, radius 1, near side
])
def test_primitive_intersections(kind, data, expect):
    t = _intersect(kind, _row(data), 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, np.inf)
    assert t == pytest.approx(expect)
    assert _intersect(kind, _row(data), 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, np.inf) == np.inf


def test_mesh_box_renders_like_the_box_primitive(tmp_path):
    trimesh.creation.box(extents=[1, 1, 1]).export(tmp_path / "cube.obj")

    def scene(obj):
        return parse_scene({
            "materials": {"grey": {"albedo": 0.5}},
            "objects": [obj | {"material": "grey"}],
            "lights": [{"type": "point", "position": [2, 3, 4], "intensity": 10}],
            "camera": {"rig": "orbit", "radius": 4, "elevation": 30, "fov": 30,
                       "resolution": 16, "views": {"train": 2}},
            "render": {"spp": 16},
        }, root=tmp_path)
    mesh = simulate(scene({"type": "mesh", "path": "cube.obj", "translate": [0, 0.5, 0]}),
                    progress=False)
    box = simulate(scene({"type": "box", "center": [0, 0.5, 0], "size": [1, 1, 1]}),
                   progress=False)
    assert np.abs(mesh.alpha - box.alpha).mean() < 0.01
    assert np.abs(mesh.radiance - box.radiance).mean() < 0.01


# --- cameras and dataset files -----------------------------------------------------------------

def test_look_at_hand_computed():
    assert np.allclose(look_at([0, 0, 4], [0, 0, 0]),
                       [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]])
    pose = look_at([0, 3, 0], [0, 0, 0])  # straight down: still a rotation
    assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3))
    assert np.allclose(-pose[:3, 2], [0, -1, 0])


@pytest.mark.parametrize("rig", ["orbit", "hemisphere", "front-arc"])
def test_rig_cameras_look_at_the_target(rig):
    poses = rig_poses(rig, 7, [0, 1, 0], 3.0, (10, 40), arc=60)
    for pose in poses:
        assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3))
        assert np.linalg.det(pose[:3, :3]) == pytest.approx(1)
        assert np.linalg.norm(pose[:3, 3] - [0, 1, 0]) == pytest.approx(3)
        forward = -pose[:3, 2]
        assert np.allclose(pose[:3, 3] + 3 * forward, [0, 1, 0])
        elevation = np.degrees(np.arcsin((pose[1, 3] - 1) / 3))
        assert 10 - 1e-9 <= elevation <= 40 + 1e-9 or rig == "hemisphere"
    train, test = (rig_poses(rig, 7, [0, 1, 0], 3.0, (10, 40), 60, p) for p in (0, 2 / 3))
    assert not np.isclose(train[:, None, :3, 3], test[None, :, :3, 3]).all(-1).any()


def test_blender_files_load_like_a_blender_loader(tmp_path):
    out = tmp_path / "cb"
    assert main(["simulate", "cornell-box", str(out), "--resolution", "8", "--spp", "2",
                 "--views", "3", "1", "2"]) == 0
    names = []
    for split, count in (("train", 3), ("val", 1), ("test", 2)):
        meta = json.loads((out / f"transforms_{split}.json").read_text())
        assert len(meta["frames"]) == count
        focal = 0.5 * 8 / np.tan(0.5 * float(meta["camera_angle_x"]))  # as nerf-pytorch does
        assert focal == pytest.approx(focal_from_fov(8, 40))
        for frame in meta["frames"]:
            image = np.asarray(Image.open(out / (frame["file_path"] + ".png")))
            assert image.shape == (8, 8, 4) and image.dtype == np.uint8
            pose = np.array(frame["transform_matrix"], np.float32)
            assert pose.shape == (4, 4) and np.allclose(pose[3], [0, 0, 0, 1])
            names.append(frame["file_path"] + ".png")
    assert read_stack(out / "weights.npz").names == names
    materials = json.loads((out / "materials.json").read_text())
    assert materials["materials"] == ["red wall", "green wall", "tall box", "sphere"]


def test_png_alpha_is_coverage_and_colour_is_straight(tmp_path):
    scene = tiny("cornell-box", resolution=16)
    sim = simulate(scene, progress=False)
    out = tmp_path / "cb"
    assert main(["simulate", "cornell-box", str(out), "--resolution", "16", "--spp", "4",
                 "--views", "2", "0", "1"]) == 0
    image = np.asarray(Image.open(out / "train" / "r_000.png")) / 255
    assert np.abs(image[..., 3] - sim.alpha[0]).max() <= 0.5 / 255 + 1e-12
    opaque = sim.alpha[0] == 1
    expect = np.clip(sim.radiance[0][opaque], 0, 1)
    assert np.abs(image[..., :3][opaque] - expect).max() <= 0.5 / 255 + 1e-12


def test_toml_scene_equals_json_scene(tmp_path):
    (tmp_path / "s.toml").write_text("""
[materials.floor]
albedo = [0.8, 0.3, 0.2]
editable = true

[[objects]]
type = "quad"
material = "floor"
corner = [-1, 0, -1]
edge1 = [0, 0, 2]
edge2 = [2, 0, 0]

[[lights]]
type = "point"
position = [0, 2, 0]
intensity = 4

[camera]
rig = "hemisphere"
radius = 3
elevation = 60
fov = 30
resolution = 8
views = {train = 1}

[render]
spp = 4
""")
    a = simulate(load_scene(str(tmp_path / "s.toml")), progress=False)
    b = simulate(lit_quad_scene(), progress=False)
    assert np.array_equal(a.weights, b.weights)


# --- bad input ---------------------------------------------------------------------------------

def _scene_file(tmp_path, change):
    data = json.loads(json.dumps(lit_quad_scene().source))
    change(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    return str(path)


@pytest.mark.parametrize("change, message", [
    (lambda d: d["camera"].pop("radius"), "'camera.radius'"),
    (lambda d: d["objects"][0].update(material="nope"), "'objects[0].material'"),
    (lambda d: d["objects"][0].update(type="torus"), "'objects[0].type'"),
    (lambda d: d["objects"][0].update(edge2=[0, 0, 4]), "'objects[0].edge2'"),
    (lambda d: d["materials"]["floor"].update(albedo=[2, 0, 0]), "'materials.floor.albedo'"),
    (lambda d: d["materials"]["floor"].update(texture="skimage:coffee"), "'materials.floor'"),
    (lambda d: d["materials"].update(tex={"texture": "skimage:eagle"}), "'materials.tex.texture'"),
    (lambda d: d["render"].update(light="indirect", order=-1), "'render.order'"),
    (lambda d: d["render"].update(spp=0), "'render.spp'"),
    (lambda d: d["lights"].clear(), "'lights'"),
    (lambda d: d.update(colour=1), "unknown field 'colour'"),
    (lambda d: d["camera"].update(views={"train": 0}), "'camera.views.train'"),
    (lambda d: d["objects"].append({"type": "mesh", "material": "floor", "path": "no.obj"}),
     "'objects[1].path'"),
])
def test_malformed_scene_names_the_field(tmp_path, capsys, change, message):
    expect_error(main, ["simulate", _scene_file(tmp_path, change), str(tmp_path / "out")],
                 message, capsys)
    assert not (tmp_path / "out").exists()


def test_unknown_scene_lists_builtins(tmp_path, capsys):
    expect_error(main, ["simulate", "cornell", str(tmp_path / "o")], ", ".join(BUILTIN_SCENES),
                 capsys)


def test_transport_scene_without_editable_material(tmp_path, capsys):
    def make_fixed(d):
        d["materials"]["floor"]["editable"] = False
        d["render"].update(light="indirect", order=2)
    expect_error(main, ["simulate", _scene_file(tmp_path, make_fixed), str(tmp_path / "o")],
                 "no material is marked", capsys)
    expect_error(main, ["simulate", "still-life", str(tmp_path / "o"), "--order", "1"],
                 "no editable material", capsys)


def test_negative_order_and_coloured_fixed_material(tmp_path, capsys):
    expect_error(main, ["simulate", "cornell-box", str(tmp_path / "o"), "--order", "-1"],
                 "order must be at least 0", capsys)
    path = _scene_file(tmp_path, lambda d: d["materials"].update(
        wall={"albedo": [0.5, 0.2, 0.2]}) or d["objects"].append(
        {"type": "sphere", "material": "wall", "center": [0, 0.5, 0], "radius": 0.2}))
    expect_error(main, ["simulate", path, str(tmp_path / "o")], "fixed material 'wall'", capsys)


def test_existing_output_needs_force(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    argv = ["simulate", "cornell-box", str(out), "--resolution", "4", "--spp", "1",
            "--views", "1", "0", "0"]
    expect_error(main, argv, "use --force", capsys)
    assert (out / "keep.txt").read_text() == "mine"
    assert main(argv + ["--force"]) == 0
    assert not (out / "keep.txt").exists() and (out / "weights.npz").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folders left


def test_with_palette_checks_the_shape():
    with pytest.raises(InputError, match=r"palette must have shape \(4, 3\)"):
        with_palette(load_scene("cornell-box"), np.zeros((3, 3)))


def test_deeply_nested_files(tmp_path, capsys):
    stack = stack_file(tmp_path / "s.npz")
    palette = tmp_path / "p.json"
    palette.write_text('{"palette": ' + "[" * 100000 + "]" * 100000 + "}")
    expect_error(recolor.main, [str(stack), "--palette", str(palette), "-o", str(tmp_path / "o")],
                 "not valid JSON", capsys)
    for name, text in [("deep.json", "[" * 100000 + "]" * 100000),
                       ("deep.toml", "a = " + "[" * 100000 + "]" * 100000)]:
        (tmp_path / name).write_text(text)
        expect_error(nerf_stage, ["simulate", str(tmp_path / name), str(tmp_path / "o")],
                     "cannot be parsed", capsys)


# --- simulation limits, checked before any work ---------------------------------------------

@pytest.mark.parametrize("args, message", [
    (["--views", "1000000000000", "0", "0"], "views must be"),
    (["--order", "1000"], "order must be at most"),
    (["--seed", str(2**64)], "seed must be at most"),
    (["--resolution", "100000"], "resolution must be at most"),
    (["--resolution", "4096", "--views", "100", "0", "0"], "GiB"),
])
def test_simulation_limits(tmp_path, capsys, args, message):
    expect_error(nerf_stage, ["simulate", "cornell-box", str(tmp_path / "o"), *args], message,
                 capsys)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("path, value, message", [
    (("camera", "target"), [float("nan"), 0, 0], "finite"),
    (("camera", "radius"), float("inf"), "camera.radius"),
    (("camera", "radius"), 0, "camera.radius"),
    (("lights", 0, "emission"), [float("inf")] * 3, "emission"),
    (("objects", 0, "corner"), [0, float("nan"), 0], "finite"),
])
def test_scene_numbers_must_be_finite(tmp_path, capsys, path, value, message):
    from nerf_stage.simulation.scene import builtin_scene_path

    scene = json.loads(builtin_scene_path("cornell-box").read_text())
    target = scene
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    (tmp_path / "s.json").write_text(json.dumps(scene))
    expect_error(nerf_stage, ["simulate", str(tmp_path / "s.json"), str(tmp_path / "o")],
                 message, capsys)


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_every_builtin_scene_simulates_with_its_editable_materials_in_view(name):
    """Each built-in scene simulates (two tiny views here); the editable ones show every
    palette material in the transport weights of their views."""
    scene = with_overrides(load_scene(name), spp=4, resolution=24, views=(2, 0, 0))
    sim = simulate(scene, progress=False)
    assert np.isfinite(sim.radiance).all() and sim.alpha.max() > 0
    if scene.palette_materials:
        terms = transport_terms(len(sim.palette), sim.order)
        for k in range(len(sim.palette)):
            uses = [i for i, combo in enumerate(terms) if k in combo]
            assert sim.weights[..., uses].sum() > 0, scene.palette_materials[k].name


# --- test views off the training rig ------------------------------------------------------------

def test_off_ring_views_are_written_marked_and_read(tmp_path, capsys):
    out = tmp_path / "sl"
    assert main(["simulate", "still-life", str(out), "--resolution", "8", "--spp", "2",
                 "--views", "3", "0", "2", "--off-ring", "3"]) == 0
    frames = json.loads((out / "transforms_test.json").read_text())["frames"]
    assert [(f["file_path"], f.get("off_ring", False)) for f in frames] == [
        ("test/r_000", False), ("test/r_001", False), ("test/o_000", True),
        ("test/o_001", True), ("test/o_002", True)]
    data = load_dataset(out)
    assert data.indices("test").tolist() == [3, 4, 5, 6, 7]
    assert data.indices("test", off_ring=True).tolist() == [5, 6, 7]
    assert data.indices("test", off_ring=False).tolist() == [3, 4]
    ring = data.poses[data.indices("train"), :3, 3]
    away = data.poses[data.indices("test", off_ring=True), :3, 3]
    target = np.array([0, 0.4, 0])
    ring_distance = np.linalg.norm(ring - target, axis=1)
    elevation = np.degrees(np.arcsin((ring - target)[:, 1] / ring_distance))
    away_distance = np.linalg.norm(away - target, axis=1)
    assert np.allclose(ring_distance, 4.5) and elevation.max() <= 40 + 1e-6
    assert np.degrees(np.arcsin((away[0] - target)[1] / away_distance[0])) > 55  # above
    assert np.allclose(away_distance[1:], [0.6 * 4.5, 1.5 * 4.5])  # closer, farther
    capsys.readouterr()
    expect_error(main, ["simulate", "still-life", str(tmp_path / "ns"), "--resolution", "8",
                        "--views", "3", "0", "1", "--off-ring", "2", "--layout", "nerfstudio"],
                 "blender layout only", capsys)
    transforms = json.loads((out / "transforms_test.json").read_text())
    transforms["frames"][2]["off_ring"] = "yes"
    (out / "transforms_test.json").write_text(json.dumps(transforms))
    with pytest.raises(InputError, match="'off_ring' must be true or false"):
        load_dataset(out)
