"""One test per class of fault of the fourth security round (docs/security.md): files that
lie about their sizes, folders that link outside, parameters without bounds, cameras
without a focal length, crafted renders, studio messages, and output suffixes."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from palette_core.cli import run_cli
from palette_core.cli.decompose import main as decompose
from palette_core.cli.recolor import main as recolor
from palette_core.edit_file import write_edits
from palette_core.errors import InputError
from palette_core.palette_file import write_palette_json
from palette_core.selection import LocalEdit, Selection
from palette_core.stack import write_stack

from .hostile import (
    PALETTE,
    capped,
    check_refused,
    colmap_capture,
    lying_npz,
    nerfstudio_capture,
    small_bake,
    small_render,
    small_stack,
    write_photos,
)


@pytest.fixture
def stack_files(tmp_path, rng):
    """A small stack ``w.npz`` and its palette file ``p.json``."""
    write_stack(small_stack(rng), tmp_path / "w.npz")
    write_palette_json(tmp_path / "p.json", PALETTE)
    return tmp_path / "w.npz", tmp_path / "p.json"


# 1. An NPZ member that lies about its size ---------------------------------------------------

def read_render_command(path) -> int:
    from nerf_stage.edit.editing import read_render

    return run_cli("read", lambda: (read_render(path), 0)[1])


@pytest.mark.parametrize("key", ["palette", "weights"])
def test_a_stack_whose_member_lies_about_its_size_is_refused(stack_files, tmp_path, key):
    stack, palette = stack_files
    lying_npz(stack, tmp_path / "lie.npz", key)
    assert (tmp_path / "lie.npz").stat().st_size < 4000
    code, err = capped(recolor, [str(tmp_path / "lie.npz"), "--palette", str(palette), "-o",
                                 str(tmp_path / "out")])
    check_refused(code, err)
    assert "more than its" in err and not (tmp_path / "out").exists()


def test_a_bake_and_a_render_that_lie_about_sizes_are_refused(tmp_path, rng):
    pytest.importorskip("torch")
    from nerf_stage.cli import main as nerf

    lying_npz(small_bake(tmp_path / "b.npz", rng), tmp_path / "lie.splat.npz", "centres")
    check_refused(*capped(nerf, ["export", str(tmp_path / "lie.splat.npz"), "-o",
                                 str(tmp_path / "x.ply")]))
    lying_npz(small_render(tmp_path / "r.npz", rng), tmp_path / "lie.npz", "weights")
    check_refused(*capped(read_render_command, tmp_path / "lie.npz"))


def load_image_command(path) -> int:
    from palette_core.io import load_image

    return run_cli("read", lambda: (load_image(path), 0)[1])


def test_a_png_whose_chunk_lies_about_its_length_is_refused(tmp_path, rng):
    write_photos(tmp_path / "p", rng, 1)
    data = bytearray((tmp_path / "p" / "f0.png").read_bytes())
    at = data.index(b"IDAT") - 4
    data[at:at + 4] = (0x7FFFFFF0).to_bytes(4, "big")  # 2 GiB of image data, says the chunk
    (tmp_path / "lie.png").write_bytes(bytes(data))
    code, err = capped(load_image_command, tmp_path / "lie.png")
    assert code in (0, 2) and "Traceback" not in err, err[-2000:]  # Pillow may accept it


# 2. Links followed out of a folder we read ---------------------------------------------------

def test_replayed_edits_do_not_copy_links_out_of_their_mask_folder(stack_files, tmp_path, rng,
                                                                  capsys):
    stack_path, _ = stack_files
    from palette_core.stack import read_stack

    stack = read_stack(stack_path)
    masks = tmp_path / "drawn"
    write_photos(masks, rng, 0)
    from PIL import Image
    for name, w in zip(stack.names, stack.weights):
        Image.fromarray(np.full(w.shape[:2], 255, np.uint8)).save(masks / name)
    write_edits(tmp_path / "e.json", stack, [LocalEdit(Selection(mask=masks), PALETTE[::-1])])
    secret = tmp_path / "private"
    secret.mkdir()
    (secret / "key").write_text("secret")
    (tmp_path / "e.masks" / "0" / "key").symlink_to(secret / "key")
    code = recolor([str(stack_path), "--edits", str(tmp_path / "e.json"), "--save-edits",
                    str(tmp_path / "mine.json"), "-o", str(tmp_path / "out")])
    assert code == 2 and "is a link out of" in capsys.readouterr().err
    assert not (tmp_path / "mine.masks").exists() and not (tmp_path / "mine.json").exists()


def test_a_capture_whose_photos_link_outside_is_refused(tmp_path, rng, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("pycolmap")
    from nerf_stage.cli import main as nerf
    from nerf_stage.data.dataset import load_dataset

    for make in (lambda f: colmap_capture(f, rng, binary=False),
                 lambda f: nerfstudio_capture(f, rng)):
        capture = make(tmp_path / "capture")
        write_photos(tmp_path / "elsewhere", rng, 1)
        (capture / "images" / "f1.png").unlink()
        (capture / "images" / "f1.png").symlink_to(tmp_path / "elsewhere" / "f0.png")
        if (capture / "sparse").exists():
            assert nerf(["poses", str(capture), "-o", str(tmp_path / "copy")]) == 2
            assert "is a link out of" in capsys.readouterr().err
            assert not (tmp_path / "copy").exists()
        with pytest.raises(InputError, match="lies outside"):
            load_dataset(capture)
        shutil.rmtree(tmp_path / "capture")
        shutil.rmtree(tmp_path / "elsewhere")


@pytest.mark.parametrize("name, content, message", [
    ("../points.ply", None, "lies outside"),
    (7, None, "ply_file_path must be a file name"),
    ("points.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 999999999\n"
                   b"property float x\nproperty float y\nproperty float z\nend_header\n",
     "not a PLY of points"),
    ("points.ply", b"not a ply at all", "not a PLY of points"),
])
def test_a_capture_whose_points_lie_is_refused(tmp_path, rng, name, content, message):
    """A ``ply_file_path`` out of the capture, of the wrong type, or naming a file whose
    header claims more points than it holds: one InputError each."""
    pytest.importorskip("torch")
    from nerf_stage.data.dataset import load_dataset

    capture = nerfstudio_capture(tmp_path / "c", rng)
    (tmp_path / "points.ply").write_bytes(b"ply\n")
    if content is not None:
        (capture / name).write_bytes(content)
    data = json.loads((capture / "transforms.json").read_text())
    data["ply_file_path"] = name
    (capture / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=message):
        load_dataset(capture)


# 3. Parameters without bounds ----------------------------------------------------------------

def test_a_feather_wider_than_the_images_is_refused(stack_files, tmp_path):
    stack_path, palette = stack_files
    from palette_core.stack import read_stack

    edit = LocalEdit(Selection(colour=0, feather=1e9), PALETTE[::-1])
    write_edits(tmp_path / "e.json", read_stack(stack_path), [edit])
    for where in (["--select-colour", "0", "--feather", "1e9", "--palette", str(palette)],
                  ["--edits", str(tmp_path / "e.json")]):
        code, err = capped(recolor, [str(stack_path), *where, "-o", str(tmp_path / "out")])
        check_refused(code, err)
        assert "wider than the images" in err and not (tmp_path / "out").exists()


@pytest.mark.parametrize("count, message", [(65, "at most 64 apply"), (10**6, "more than")])
def test_region_files_of_too_many_regions_are_refused(tmp_path, count, message):
    pytest.importorskip("torch")
    from nerf_stage.edit.regions import read_regions

    box = {"shape": "box", "centre": [0, 0, 0], "half": [1, 1, 1]}
    (tmp_path / "r.json").write_text(json.dumps({"regions": [box] * count}))
    with pytest.raises(InputError, match=message):
        read_regions(tmp_path / "r.json")


# 4. Cameras without a focal length -----------------------------------------------------------

@pytest.mark.parametrize("focal, binary", [("0", False), ("-3", False), ("0", True),
                                           ("nan", True), ("inf", True)])
def test_colmap_cameras_without_a_focal_length_are_refused(tmp_path, rng, capsys, focal,
                                                           binary):
    """(pycolmap's text reader refuses NaN itself; its binary reader does not.)"""
    pytest.importorskip("torch")
    pycolmap = pytest.importorskip("pycolmap")
    from nerf_stage.cli import main as nerf

    capture = colmap_capture(tmp_path / "c", rng, binary=False)
    model = capture / "sparse" / "0"
    text = (model / "cameras.txt").read_text()
    (model / "cameras.txt").write_text(text.replace(" 8.0 ", " 1.0 "))
    reconstruction = pycolmap.Reconstruction(model)
    if binary:
        reconstruction.cameras[1].params = [float(focal), 4.0, 3.0, 0.0]
        for name in ("cameras.txt", "images.txt", "points3D.txt"):
            (model / name).unlink()
        reconstruction.write_binary(model)
    else:
        (model / "cameras.txt").write_text(text.replace(" 8.0 ", f" {focal} "))
    assert nerf(["poses", str(capture), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "camera 1: " in err
    assert not (tmp_path / "out").exists()
    assert nerf(["train", str(capture), "-o", str(tmp_path / "run")]) == 2
    assert "camera 1: " in capsys.readouterr().err


def test_a_binary_model_that_makes_its_reader_loop_is_refused(tmp_path, rng, capsys,
                                                               monkeypatch):
    """A count inside a binary model, made of inserted bytes, keeps pycolmap's reader
    looping in C++: it is read first in a child that a time limit stops."""
    pytest.importorskip("torch")
    pytest.importorskip("pycolmap")
    from nerf_stage.cli import main as nerf
    from nerf_stage.data import colmap

    monkeypatch.setattr(colmap, "READ_SECONDS", 2)
    capture = colmap_capture(tmp_path / "c", rng, binary=True)
    frames = capture / "sparse" / "0" / "frames.bin"
    if not frames.exists():
        pytest.skip("this pycolmap writes no frames.bin")
    data = frames.read_bytes()
    middle = len(data) // 2
    frames.write_bytes(data[:middle] + b'"../../../etc/hostname"' + data[middle:])
    assert nerf(["train", str(capture), "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "COLMAP model" in err


@pytest.mark.parametrize("field, value", [("fl_x", 0), ("cx", 1e9), ("w", 10**9)])
def test_nerfstudio_cameras_out_of_bounds_are_refused(tmp_path, rng, field, value):
    pytest.importorskip("torch")
    from nerf_stage.data.dataset import load_dataset

    capture = nerfstudio_capture(tmp_path / "c", rng)
    data = json.loads((capture / "transforms.json").read_text())
    data[field] = value
    (capture / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(InputError):
        load_dataset(capture)


# 5. Crafted version-2 renders ----------------------------------------------------------------

@pytest.mark.parametrize("change", [
    lambda a: a.update(sample_pixel=np.array([10**12] * 12, np.int64)),
    lambda a: a.update(sample_pixel=-np.arange(12, dtype=np.int64)),
    lambda a: a.update(sample_weight=a["sample_weight"][:5]),
    lambda a: a.update(sample_pixel=np.int64(3)),
])
def test_crafted_render_samples_are_refused_before_use(tmp_path, rng, change):
    pytest.importorskip("torch")
    path = small_render(tmp_path / "r.npz", rng)
    with np.load(path) as npz:
        arrays = dict(npz)
    change(arrays)
    np.savez(path, **arrays)
    code, err = capped(read_render_command, path)
    check_refused(code, err)
    assert "samples behind its pixels" in err


# 6. Studio messages --------------------------------------------------------------------------

@pytest.mark.parametrize("stroke", [
    lambda d: d.box(0, np.array([[math.nan, 0.0], [3.0, 3.0]]), 1.0),
    lambda d: d.box(0, np.array([[math.inf, 0.0], [3.0, 3.0]]), 1.0),
    lambda d: d.box(0, np.zeros((2, 2)), 1e9),
    lambda d: d.dab(0, np.array([3.0, 3.0]), 1e9, 1.0),
    lambda d: d.dab(0, np.array([3.0, 3.0]), math.nan, 1.0),
    lambda d: d.dab(5, np.array([3.0, 3.0]), 2.0, 1.0),
    lambda d: d.dab(0, np.array([3.0]), 2.0, 1.0),
])
def test_studio_strokes_are_checked_like_arguments(stroke):
    pytest.importorskip("viser")
    from studio.drawing import Drawing

    drawing = Drawing(lambda i: (20, 30), 2)
    with pytest.raises(InputError):
        stroke(drawing)
    assert not drawing


def test_studio_clicks_far_outside_paint_nothing():
    pytest.importorskip("viser")
    from studio.drawing import Drawing

    drawing = Drawing(lambda i: (20, 30), 2)
    drawing.dab(0, np.array([1e12, -1e12]), 5.0, 2.0)
    drawing.box(1, np.array([[-1e15, -1e15], [-1e14, -1e14]]), 0.0)
    assert all(not mask.any() for mask in drawing.masks.values())


def test_the_browsers_camera_must_be_finite():
    pytest.importorskip("viser")
    from types import SimpleNamespace

    from studio.pictures import camera_pose

    with pytest.raises(InputError, match="finite"):
        camera_pose(SimpleNamespace(wxyz=(math.nan, 0, 0, 0), position=(0, 0, 0)))
    with pytest.raises(InputError, match="finite"):
        camera_pose(SimpleNamespace(wxyz=(0, 0, 0, 0), position=(0, 0, 0)))


# 7. An output whose suffix says one format gets another --------------------------------------

@pytest.mark.parametrize("force", [[], ["--force"]])
def test_an_npz_output_that_is_a_folder_is_refused(photo_dir, tmp_path, capsys, force):
    (tmp_path / "w.npz").mkdir()
    assert decompose([str(photo_dir), "-k", "4", "-o", str(tmp_path / "w.npz"), *force]) == 2
    assert "w.npz" in capsys.readouterr().err
    assert list((tmp_path / "w.npz").iterdir()) == []
