"""Local edits of scenes: regions split a render's weights exactly, recolour without the
network, and the simulator re-traces one object of a shared colour alone."""

import json

import numpy as np
import pytest

from nerf_stage.edit.regions import ColourRegion, Region, parse_region, read_regions
from nerf_stage.render.samples import PixelSamples
from nerf_stage.simulation import (
    load_scene,
    parse_scene,
    render_terms,
    view_poses,
    with_overrides,
    with_palette,
)
from palette_core.errors import InputError

from .helpers import expect_error

EVERYWHERE = Region("box", (0.0, 0.0, 0.0), (1e6, 1e6, 1e6))
NOWHERE = Region("ellipsoid", (1e5, 1e5, 1e5), (1.0, 1.0, 1.0))


# --- regions --------------------------------------------------------------------------------

def test_regions_parse_and_contain_points(tmp_path):
    box, = parse_region("box:1,0,0,0,2,-1")  # corners in any order
    assert box == Region("box", (0.5, 1.0, -0.5), (0.5, 1.0, 0.5))
    ball, = parse_region("ellipsoid:0,0,0,1,2,3")
    points = np.array([[0.5, 1.0, -0.5], [1.0, 2.0, 0.0], [1.01, 1, 0], [0, 1.9, 0.5], [0, 0, 3.1]])
    assert box.contains(points).tolist() == [True, True, False, False, False]
    assert ball.contains(points).tolist() == [True, False, False, True, False]
    path = tmp_path / "regions.json"
    path.write_text(json.dumps({"palette": ["#000000"], "regions": [box.to_dict(),
                                                                    ball.to_dict()]}))
    assert read_regions(path) == parse_region(str(path)) == [box, ball]
    assert parse_region("colour:2") == [ColourRegion(2, 0.5)]
    assert parse_region("colour:2,0.3") == [ColourRegion(2, 0.3)]
    path.write_text(json.dumps({"regions": [ColourRegion(1, 0.4).to_dict()]}))
    assert read_regions(path) == [ColourRegion(1, 0.4)]


@pytest.mark.parametrize("text, message", [
    ("cube:0,0,0,1,1,1", "unknown region shape 'cube'"),
    ("box:0,0,0,1,1", "6 finite numbers"),
    ("box:0,0,0,1,nan,1", "6 finite numbers"),
    ("box:0,0,0,1,x,1", "6 finite numbers"),
    ("box:0,0,0,1,0,1", "sizes above zero"),
    ("ellipsoid:0,0,0,1,-1,1", "sizes above zero"),
    ("missing.json", "does not exist"),
    ("colour:x", "palette colour index"),
    ("colour:1.5", "palette colour index"),
    ("colour:1,nan", "must be finite"),
])
def test_bad_regions_are_one_clear_error(text, message):
    with pytest.raises(InputError, match=message):
        parse_region(text)


@pytest.mark.parametrize("content, message", [
    ("{", "not valid JSON"),
    ('{"regions": []}', "must hold"),
    ('{"regions": [{"shape": "box", "centre": [0, 0, 0]}]}', "a region is"),
    ('{"regions": [{"shape": "prism", "centre": [0, 0, 0], "half": [1, 1, 1]}]}',
     "unknown region shape"),
    ('{"regions": [{"shape": "box", "centre": [0, 0], "half": [1, 1, 1]}]}', "3 finite"),
    ('{"regions": [{"shape": "box", "centre": [0, 0, 0], "half": "big"}]}', "lists of 3"),
])
def test_bad_region_files_are_one_clear_error(tmp_path, content, message):
    path = tmp_path / "r.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message):
        read_regions(path)


def test_shares_weigh_the_first_half_of_each_pixels_light():
    inside, outside = [0, 0, 0], [5, 0, 0]
    samples = PixelSamples(  # given out of pixel order, in marching order within a pixel
        np.array([3, 0, 0, 1, 1, 3]),
        np.array([inside, outside, inside, inside, outside, outside], np.float32),
        np.array([0.2, 0.1, 0.3, 0.6, 0.4, 0.3], np.float32))
    share = samples.shares([Region("box", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))], (1, 2, 2))
    # pixels 0 and 3: both samples bring some of the first half (the second crosses it);
    # pixel 1: what leaks through behind its first does not count; pixel 2 has no samples
    assert np.allclose(share, [[[0.75, 1.0], [0.0, 0.4]]])
    assert samples.pixel.tolist() == [0, 0, 1, 1, 3, 3]
    # the sample that crosses half of each pixel's light; none in pixel 2
    points = samples.median_points(4)
    assert np.array_equal(points[[0, 1, 3]], [inside, inside, outside])
    assert np.isnan(points[2]).all()


# --- region edits of a render ----------------------------------------------------------------

torch = pytest.importorskip("torch")

from nerf_stage.cli import main  # noqa: E402
from nerf_stage.edit.editing import (  # noqa: E402
    RENDER_FILE,
    read_render,
    render_weights,
    write_render,
)
from nerf_stage.train.loading import load_run  # noqa: E402


@pytest.fixture(scope="module")
def sampled(cornell_run):
    rundir, _ = cornell_run
    run = load_run(rundir)
    return run, render_weights(run, ["a", "b"], run.dataset().poses[:2], {}, False,
                               samples=True)


def test_a_region_splits_the_weights_exactly(sampled, rng):
    run, render = sampled
    edit = rng.uniform(0, 1, run.palette.shape)
    assert render.samples.pixel.max() < render.opacity.size
    nowhere = render.with_regions([NOWHERE])
    assert not nowhere.inside.any()
    assert np.array_equal(nowhere.recolor(inside=edit), render.recolor())  # bit for bit
    everywhere = render.with_regions([EVERYWHERE])
    assert np.allclose(everywhere.recolor(inside=edit), render.recolor(edit), atol=1e-6)
    right = run.box.centre + [5.0, 0.0, 0.0]  # the half of space beyond the centre's x
    half = render.with_regions([Region("box", tuple(right), (5.0, 10.0, 10.0))])
    outside = render.weights - half.inside
    assert (half.inside >= 0).all() and (outside >= -1e-7).all()
    assert np.allclose(half.inside + outside, render.weights)
    untouched = ~half.inside.any(-1)
    assert untouched.any() and (~untouched).any()
    assert np.array_equal(half.recolor(inside=edit)[untouched], render.recolor()[untouched])


def test_a_colour_region_selects_by_weight_as_in_photos(sampled):
    run, render = sampled
    split = render.with_regions([ColourRegion(1, 0.3)])
    straight = render.weights / np.maximum(render.opacity, 1e-6)[..., None]
    chosen = straight[..., 2] >= 0.3  # colour 1's first-order term, after the constant one
    assert chosen.any() and (~chosen).any()
    assert np.array_equal(split.inside[chosen], render.weights[chosen])
    assert not split.inside[~chosen].any()
    with pytest.raises(InputError, match="not one of the palette's 4"):
        render.with_regions([ColourRegion(4)])


def test_render_regions_from_the_command_line(cornell_run, tmp_path, capsys):
    rundir, _ = cornell_run
    palette = tmp_path / "teal.json"
    palette.write_text(json.dumps({"palette": [[0.1, 0.6, 0.55]] * 4}))
    out = tmp_path / "local"
    region = "box:-0.2,0.5,-2,2,2,2"
    assert main(["render", str(rundir), "--palette", str(palette), "--region", region,
                 "-o", str(out)]) == 0
    assert "inside 1 region" in capsys.readouterr().out
    saved = read_render(out / RENDER_FILE)
    assert saved.regions == parse_region(region) and saved.samples is not None
    first = sorted((out / "teal").iterdir())
    regions = tmp_path / "regions.json"
    regions.write_text(json.dumps({"regions": [NOWHERE.to_dict()]}))
    assert main(["render", str(rundir), "--palette", str(palette), "--region", str(regions),
                 "-o", str(out), "--force"]) == 0
    assert "does not run" in capsys.readouterr().out  # moved: split again from the samples
    assert read_render(out / RENDER_FILE).regions == [NOWHERE]
    assert main(["render", str(rundir), "-o", str(tmp_path / "plain")]) == 0
    original = sorted((tmp_path / "plain" / "original").glob("r_*.png"))
    for ours, theirs in zip(sorted((out / "teal").glob("r_*.png")), original):
        assert ours.read_bytes() == theirs.read_bytes()  # a region of nothing changes nothing
    assert len(first) == len(original) + 1


def test_bad_region_arguments_write_nothing(cornell_run, tmp_path, capsys):
    rundir, _ = cornell_run
    palette = tmp_path / "p.json"
    palette.write_text(json.dumps({"palette": [[0.1, 0.6, 0.55]] * 4}))
    out = tmp_path / "out"
    for region, message in (("box:0,0,0,1,nan,1", "6 finite numbers"),
                            ("sphere:0,0,0,1,1,1", "unknown region shape"),
                            ("box:0,0,0,0,1,1", "sizes above zero"),
                            ("colour:4", "not one of the palette's 4")):
        expect_error(main, ["render", str(rundir), "--palette", str(palette), "--region", region,
                            "-o", str(out)], message, capsys)
    expect_error(main, ["render", str(rundir), "--region", "box:0,0,0,1,1,1", "-o", str(out)],
                 "needs a palette", capsys)
    assert not out.exists()


def test_version_1_renders_are_still_read(sampled, tmp_path):
    _, render = sampled
    path = tmp_path / "v1.npz"
    np.savez(path, format=np.array("palette-render/1"), weights=render.weights,
             opacity=render.opacity, names=np.array(render.names), palette=render.palette,
             basis=np.array(str(render.basis)), order=np.array(render.order),
             background=render.background, source=np.array("{}"))
    old = read_render(path)
    assert old.samples is None and old.inside is None
    assert np.array_equal(old.recolor(), render.recolor())
    with pytest.raises(InputError, match="kept no samples"):
        old.with_regions([EVERYWHERE])


def test_malformed_samples_are_refused(sampled, tmp_path):
    _, render = sampled
    path = tmp_path / "r.npz"
    write_render(render, path)
    with np.load(path) as npz:
        arrays = dict(npz)
    arrays["sample_pixel"] = arrays["sample_pixel"] + render.opacity.size
    np.savez(path, **arrays)
    with pytest.raises(InputError, match="samples behind its pixels"):
        read_render(path)


# --- one colour, two materials ----------------------------------------------------------------

def test_a_material_can_share_another_ones_colour():
    scene = with_overrides(load_scene("clay-twins"), resolution=12, spp=4, views=[1, 0, 0])
    assert [m.name for m in scene.palette_materials] == ["clay vase", "blue box", "yellow bead"]
    ball = next(m for m in scene.materials if m.name == "clay ball")
    assert ball.colour_of == "clay vase" and scene.palette_index(ball) == 0
    _, poses = view_poses(scene)
    edit = np.array([[0.1, 0.6, 0.55], [0.15, 0.3, 0.7], [0.85, 0.7, 0.15]])

    def rgb(changed):
        return render_terms(changed, poses, split=False)[0][..., 0, :]

    before, both = rgb(scene), rgb(with_palette(scene, edit))
    ball_only = rgb(with_palette(scene, edit, only={"clay ball"}))
    vase_only = rgb(with_palette(scene, edit, only={"clay vase"}))
    assert np.allclose(ball_only + vase_only - before, both, atol=1e-9)  # direct light: additive
    for one in (ball_only, vase_only):
        assert np.abs(one - before).max() > 0.05 and np.abs(one - both).max() > 0.05
    with pytest.raises(InputError, match="no editable material 'floor'"):
        with_palette(scene, edit, only={"floor"})


@pytest.mark.parametrize("spec, message", [
    ({"colour_of": "nobody"}, "colour_of"),
    ({"colour_of": "fixed"}, "colour_of"),
    ({"colour_of": "owner", "albedo": [1, 1, 1]}, "unknown field"),
])
def test_bad_shared_colours_are_refused(spec, message):
    data = {"materials": {"fixed": {"albedo": [0.5, 0.5, 0.5]},
                          "owner": {"albedo": [0.5, 0.2, 0.1], "editable": True},
                          "twin": spec},
            "objects": [{"type": "sphere", "material": "twin", "center": [0, 0, 0],
                         "radius": 1}],
            "lights": [{"type": "point", "position": [0, 3, 0], "intensity": 4}],
            "camera": {"rig": "orbit", "radius": 4, "fov": 40, "resolution": 8,
                       "views": {"train": 1, "val": 0, "test": 0}},
            "render": {"light": "direct", "spp": 1}}
    with pytest.raises(InputError, match=message):
        parse_scene(data)
