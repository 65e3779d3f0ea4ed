"""Hostile and faulty inputs: crafted stacks, images, scenes and datasets, full disks,
signals, races with other writers. Each ends in one line and exit 2, or is handled."""

import errno
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap
import warnings
import zipfile
import zlib

import numpy as np
import pytest
import tifffile
from PIL import Image

from harmonize.cli import main as harmonize
from nerf_stage.cli import main as nerf_stage
from nerf_stage.data import load_dataset
from palette_core import InputError, WeightStack, load_image, read_stack, write_stack
from palette_core.cli import decompose, recolor
from palette_core.outputs import atomic_outputs, inside, publish_folder
from palette_core.stack import FLOAT16_SUM_TOL

from .helpers import expect_error


def stack_file(path, names=("a.png",), weights=None, **arrays):
    """A valid additive stack of 2x2 images, with arrays replaced by ``arrays``."""
    weights = weights or [np.full((2, 2, 4), 0.25, np.float32)] * len(names)
    write_stack(WeightStack(np.eye(4, 3, dtype=np.float32), list(weights), list(names)), path)
    if arrays:
        with np.load(path) as npz:
            data = dict(npz)
        data.update({key.rstrip("_"): value for key, value in arrays.items()})
        np.savez(path, **data)
    return path


def png_header_only(path, width, height):
    """A PNG whose header declares width x height and whose data is a few bytes."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + chunk(b"IEND", b""))
    return path


# --- security: names from a stack never write outside the output folder ---------------------

@pytest.mark.parametrize("name", ["../evil.png", "/tmp/evil.png", "", "a\0b.png",
                                  "sub/../../e.png"])
def test_stack_names_cannot_escape(tmp_path, capsys, name):
    path = stack_file(tmp_path / "s.npz", names=["ok.png", name])
    palette = tmp_path / "p.json"
    palette.write_text(json.dumps({"palette": ["#000000"] * 4}))
    out = tmp_path / "deep" / "out"
    expect_error(recolor.main, [str(path), "--palette", str(palette), "-o", str(out), "--force"],
                 "is not a distinct relative path", capsys)
    expect_error(harmonize, [str(path), "--template", "triad", "--render", str(out)],
                 "is not a distinct relative path", capsys)
    assert not (tmp_path / "deep" / "evil.png").exists() and not out.exists()


def test_output_paths_are_checked_again_after_links(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "link").symlink_to(tmp_path)
    with pytest.raises(InputError, match="outside"):
        inside(tmp_path / "out", "link/evil.png")
    assert inside(tmp_path / "out", "sub/fine.png") == tmp_path / "out" / "sub" / "fine.png"


def test_duplicate_names_in_a_stack(tmp_path):
    with pytest.raises(InputError, match="distinct"):
        read_stack(stack_file(tmp_path / "s.npz", names=["a.png", "a.png"]))


# --- malformed stacks ----------------------------------------------------------------------

def npy_bytes(shape, dtype, payload=b""):
    """A .npy member whose header declares ``shape`` and whose data is ``payload``."""
    header = {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape}
    text = repr(header).encode()
    text += b" " * (63 - (10 + len(text)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + payload


@pytest.mark.parametrize("make, message", [
    (lambda p: p.write_bytes(b""), "not a readable NPZ"),
    (lambda p: stack_file(p, weights_=np.float32(1.0)), "must have shape"),
    (lambda p: stack_file(p, palette=np.array(["red"] * 4)), "dtype"),
    (lambda p: stack_file(p, weights=[np.full((2, 2, 4), np.nan, np.float32)]), "NaN"),
    (lambda p: stack_file(p, weights=[np.full((2, 2, 4), np.inf, np.float32)]), "NaN"),
    (lambda p: stack_file(p, meta=np.array("[" * 100000)), "meta"),
])
def test_malformed_stacks(tmp_path, make, message):
    path = tmp_path / "s.npz"
    make(path)
    with pytest.raises(InputError, match=message):
        read_stack(path)


def test_declared_shapes_are_checked_before_loading(tmp_path):
    path = stack_file(tmp_path / "s.npz")
    huge = npy_bytes((100000, 100000, 1000, 4), "<f4", b"\0" * 64)
    with zipfile.ZipFile(path, "a") as z:  # an unused member is never read
        z.writestr("junk.npy", huge)
    assert read_stack(path).names == ["a.png"]
    with zipfile.ZipFile(path, "a") as z:
        z.writestr("weights_0000.npy", huge)
    bare = tmp_path / "bare.npz"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(bare, "w") as dst:
        for info in src.infolist():
            if info.filename not in ("weights.npy", "junk.npy"):
                dst.writestr(info.filename, src.read(info.filename))
    with pytest.raises(InputError, match="declares shape"):
        read_stack(bare)


def test_stack_without_hull_faces_loads(tmp_path):
    path = stack_file(tmp_path / "s.npz")
    with np.load(path) as npz:
        data = {k: npz[k] for k in npz.files if k != "hull_faces"}
    np.savez(path, **data)
    assert read_stack(path).hull_faces.shape == (0, 3)


# --- images --------------------------------------------------------------------------------

def test_decompression_bombs_are_refused_from_the_header(tmp_path, capsys):
    bomb = png_header_only(tmp_path / "bomb.png", 100000, 100000)
    expect_error(decompose.main, [str(bomb), "-o", str(tmp_path / "w.npz")], "--max-pixels",
                 capsys)
    Image.fromarray(np.zeros((100, 100, 3), np.uint8)).save(tmp_path / "flat.png")
    expect_error(decompose.main, [str(tmp_path / "flat.png"), "--max-pixels", "5000",
                                  "-o", str(tmp_path / "w.npz")], "100x100", capsys)


def test_decompression_bomb_as_dataset_frame(tmp_path):
    (tmp_path / "train").mkdir()
    png_header_only(tmp_path / "train" / "r_0.png", 100000, 100000)
    frames = [{"file_path": "train/r_0", "transform_matrix": np.eye(4).tolist()}]
    (tmp_path / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    with pytest.raises(InputError, match="max-pixels"):
        load_dataset(tmp_path)


def test_fully_transparent_images(tmp_path, capsys):
    Image.fromarray(np.zeros((4, 4, 4), np.uint8)).save(tmp_path / "clear.png")
    expect_error(decompose.main, [str(tmp_path / "clear.png"), "-o", str(tmp_path / "w.npz")],
                 "fully transparent", capsys)


def test_planar_16_bit_tiff(tmp_path, rng):
    planes = rng.integers(0, 65536, (3, 5, 64), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "planar.tif", planes, planarconfig="separate", photometric="rgb")
    image = load_image(tmp_path / "planar.tif")
    assert image.pixels.shape == (5, 64, 3)
    assert np.array_equal(image.pixels, np.moveaxis(planes, 0, -1))


def test_float_tiff_with_nan(tmp_path):
    tifffile.imwrite(tmp_path / "nan.tif", np.full((4, 4), np.nan, np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="NaN"):
            load_image(tmp_path / "nan.tif")


def test_symlinked_input_keeps_its_name(tmp_path, rng):
    (tmp_path / "store").mkdir()
    (tmp_path / "in").mkdir()
    Image.fromarray(rng.integers(0, 256, (4, 4, 3), dtype=np.uint8)).save(
        tmp_path / "store" / "x1234.png")
    (tmp_path / "in" / "holiday.png").symlink_to(tmp_path / "store" / "x1234.png")
    assert decompose.main([str(tmp_path / "in"), "-k", "4", "-o", str(tmp_path / "w.npz")]) == 0
    assert read_stack(tmp_path / "w.npz").names == ["holiday.png"]


def test_float16_sums(photo_dir, tmp_path):
    assert decompose.main([str(photo_dir), "-k", "6", "--dtype", "float16",
                           "-o", str(tmp_path / "w.npz")]) == 0
    for w in read_stack(tmp_path / "w.npz").weights:
        assert np.abs(w.astype(np.float32).sum(-1) - 1).max() <= FLOAT16_SUM_TOL


# --- deep JSON and TOML ---------------------------------------------------------------------

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


def test_nan_camera_matrix(tmp_path):
    (tmp_path / "train").mkdir()
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(tmp_path / "train" / "r_0.png")
    pose = np.eye(4).tolist()
    pose[0][3] = float("nan")
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": "train/r_0", "transform_matrix": pose}]}))
    with pytest.raises(InputError, match="NaN"):
        load_dataset(tmp_path)


# --- writing: full disks, races, collisions, permissions ------------------------------------

def test_full_disk_leaves_nothing(tmp_path, capsys, monkeypatch):
    import palette_core.recolor

    stack = stack_file(tmp_path / "s.npz", names=["a.png", "b.png"])
    palette = tmp_path / "p.json"
    palette.write_text(json.dumps({"palette": ["#000000"] * 4}))
    calls = []

    def full(path, rgb):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        path.write_bytes(b"x")

    monkeypatch.setattr(palette_core.recolor, "save_image", full)
    out = tmp_path / "out"
    expect_error(recolor.main, [str(stack), "--palette", str(palette), "-o", str(out)],
                 "No space left on device", capsys)
    assert not out.exists()  # nothing, not even the folder made for the outputs


def test_a_file_created_meanwhile_is_kept(tmp_path):
    final = tmp_path / "a.txt"
    with pytest.raises(InputError, match="appeared while writing"):
        with atomic_outputs() as stage:
            stage(tmp_path / "b.txt").write_text("ours")
            stage(final).write_text("ours")
            final.write_text("theirs")
    assert final.read_text() == "theirs" and not (tmp_path / "b.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_a_folder_filled_meanwhile_is_kept(tmp_path):
    final = tmp_path / "out"
    with pytest.raises(InputError, match="appeared while writing"):
        with publish_folder(final) as staging:
            (staging / "x.png").write_text("ours")
            final.mkdir()
            (final / "mine.txt").write_text("theirs")
    assert [p.name for p in final.iterdir()] == ["mine.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_stale_temporaries_are_swept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale = tmp_path / f".w.~{dead}~abcd.tmp.npz"
    live = tmp_path / f".w.~{os.getpid()}~efgh.tmp.npz"
    stale_dir = tmp_path / f".out.~{dead}~ijkl"
    for path in (stale, live):
        path.write_text("x")
    stale_dir.mkdir()
    with atomic_outputs() as stage:
        stage(tmp_path / "new.txt").write_text("new")
    assert not stale.exists() and not stale_dir.exists() and live.exists()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_signals_clean_up(tmp_path, sig):
    child = textwrap.dedent(f"""
        import signal, sys, time
        from palette_core.cli import run_cli
        from palette_core.outputs import atomic_outputs, publish_folder

        # a shell's background job starts with SIGINT ignored; a terminal's Ctrl+C does not
        signal.signal(signal.SIGINT, signal.default_int_handler)

        def body():
            with atomic_outputs() as stage, publish_folder({str(tmp_path / "dir")!r}) as d:
                stage({str(tmp_path / "file.npz")!r}).write_bytes(b"x" * 1000)
                (d / "view.png").write_bytes(b"y")
                print("ready", flush=True)
                time.sleep(30)
            return 0

        sys.exit(run_cli("child", body))
    """)
    process = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "ready"
    process.send_signal(sig)
    _, err = process.communicate(timeout=20)
    assert process.returncode == 128 + sig and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_outputs_may_not_collide(photo_dir, tmp_path, capsys, rng):
    Image.fromarray(rng.integers(0, 256, (3, 3, 3), dtype=np.uint8)).save(photo_dir / "a.bmp")
    expect_error(decompose.main, [str(photo_dir), "-o", str(tmp_path / "w.npz"),
                                  "--layers", str(tmp_path / "layers")], "two outputs", capsys)
    assert not (tmp_path / "w.npz").exists()
    expect_error(decompose.main, [str(photo_dir), "-o", str(photo_dir / "w.npz")],
                 "among the inputs", capsys)
    (photo_dir / "a.png").rename(photo_dir / "w.palette.png")  # named like the output swatch
    expect_error(decompose.main, [str(photo_dir / "w.palette.png"), "-o", str(photo_dir / "w.npz"),
                                  "--force"], "among the inputs", capsys)
    assert (photo_dir / "w.palette.png").stat().st_size > 0


def test_outputs_respect_the_umask(photo_dir, tmp_path):
    old = os.umask(0o027)
    try:
        assert decompose.main([str(photo_dir), "-k", "4", "-o", str(tmp_path / "o" / "w.npz"),
                               "--layers", str(tmp_path / "layers")]) == 0
        assert nerf_stage(["simulate", "cornell-box", str(tmp_path / "sim"), "--resolution",
                           "4", "--spp", "1", "--views", "1", "0", "0"]) == 0
    finally:
        os.umask(old)
    assert (tmp_path / "o" / "w.npz").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "layers" / "a_w0.png").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "sim").stat().st_mode & 0o777 == 0o750


# --- NERF_STAGE_CONFIG and run folders from elsewhere ---------------------------------------

@pytest.mark.parametrize("config, message", [
    ({"grid": [1, 2]}, "grid must be an object"),
    ({"grid": {"voxels": "many"}}, "voxels must be an integer"),
    ({"seed": 1.5}, "seed must be an integer"),
    ({"grid": {"voxels": 10**12}}, "voxels must be an integer in [1, 33554432]"),
    ({"supersampling": 100_000}, "supersampling must be an integer in [1, 8]"),
    ({"batch_rays": True}, "batch_rays must be an integer"),
    ({"background": ["white", 0, 0]}, "background must be three numbers"),
    ({"lr_decay": "0.3"}, "lr_decay must be a finite number"),
])
def test_bad_training_configs_are_one_line(tmp_path, capsys, monkeypatch, config, message):
    path = tmp_path / "config.json"
    path.write_text(json.dumps(config))
    monkeypatch.setenv("NERF_STAGE_CONFIG", str(path))
    expect_error(nerf_stage, ["train", str(tmp_path)], message, capsys)
    # only train reads it: the other commands are not broken by it
    expect_error(nerf_stage, ["simulate", "no-such-scene", str(tmp_path / "o")],
                 "no-such-scene", capsys)


def _crafted_run(scene_run, tmp_path, change):
    import shutil

    import torch

    run = tmp_path / "run"
    shutil.copytree(scene_run, run)
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    change(state)
    torch.save(state, run / "checkpoint.pt")
    return run


@pytest.mark.parametrize("change, message", [
    (lambda s: s["intrinsics"].update(width=10**6, height=10**6), "a camera of 1000000x1000000"),
    (lambda s: s["intrinsics"].update(fx=float("nan")), "finite numbers"),
    (lambda s: s.update(basis="transport", order=1000), "channels, more than 4096"),
    (lambda s: s.update(palette=[[2.0, 0.0, 0.0]] * 4), "palette must have shape"),
    (lambda s: s["box"].update(half=[0.0, 1.0, 1.0]), "positive extent"),
    (lambda s: s["config"]["grid"].update(voxels=10**12), "voxels must be an integer"),
])
def test_crafted_run_folders_are_refused_before_allocating(scene_run, tmp_path, capsys, change,
                                                           message):
    pytest.importorskip("torch")
    run = _crafted_run(scene_run, tmp_path, change)
    expect_error(nerf_stage, ["render", str(run), "--orbit", "2", "-o", str(tmp_path / "out")],
                 message, capsys)
    assert not (tmp_path / "out").exists()
