"""Hostile values and careless use end in one line on stderr and exit code 2, naming only
flags the command has; non-finite numbers are refused by every reader; lenses that fold
are refused; any signal at any moment ends a command cleanly."""

import json
import os
import signal
import struct
import subprocess
import sys
import time
import zlib

import numpy as np
import pytest

from palette_core.cli import decompose, run_cli
from palette_core.errors import InputError

from .helpers import expect_error
from .hostile import colmap_capture, nerfstudio_capture

torch = pytest.importorskip("torch")
pytest.importorskip("pycolmap")

from nerf_stage.cli import main as nerf_stage  # noqa: E402
from nerf_stage.data.points import Points, write_points  # noqa: E402
from nerf_stage.train.checkpoint import CHECKPOINT  # noqa: E402


def _binary_model_with(folder, rng, camera: str, points: str = ""):
    """A binary COLMAP capture of ``camera`` whose points are ``points`` (points3D.txt)."""
    import pycolmap

    capture = colmap_capture(folder, rng, binary=False, camera=camera)
    model = capture / "sparse" / "0"
    (model / "points3D.txt").write_text(points)
    reconstruction = pycolmap.Reconstruction(model)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        (model / name).unlink()
    reconstruction.write_binary(model)
    return capture


def _set_double(path, offset: int, value: float) -> None:
    data = bytearray(path.read_bytes())
    data[offset:offset + 8] = struct.pack("<d", value)
    path.write_bytes(bytes(data))


# --- non-finite values ----------------------------------------------------------------------

@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_a_colmap_point_that_is_not_finite_is_refused_by_training_and_poses(value, tmp_path,
                                                                           rng, capsys):
    capture = _binary_model_with(tmp_path / "c", rng, "SIMPLE_RADIAL 8 6 8.0 4.0 3.0 0.0",
                                 "1 0.1 0.2 0.3 255 0 0 0.5\n")
    _set_double(capture / "sparse" / "0" / "points3D.bin", 16, value)  # the first point's x
    expect_error(nerf_stage, ["train", str(capture), "--backbone", "splats", "-o",
                              str(tmp_path / "run")], "3D points hold NaN or infinity", capsys)
    expect_error(nerf_stage, ["poses", str(capture), "-o", str(tmp_path / "out")],
                 "3D points hold NaN or infinity", capsys)
    assert not (tmp_path / "run").exists() and not (tmp_path / "out").exists()


def test_points_we_would_refuse_to_read_are_never_made(tmp_path):
    with pytest.raises(InputError, match="finite"):
        write_points(Points(np.array([[0.0, np.nan, 1.0]]), np.zeros((1, 3), np.float32)),
                     tmp_path / "p.ply")
    assert not (tmp_path / "p.ply").exists()


# --- one line, whatever the value -----------------------------------------------------------

def test_a_camera_parameter_that_is_not_finite_is_one_line(tmp_path, rng, capsys):
    capture = _binary_model_with(tmp_path / "c", rng,
                                 "OPENCV 8 6 8.0 8.0 4.0 3.0 0.01 0.02 0.001 0.001")
    _set_double(capture / "sparse" / "0" / "cameras.bin", 8 + 4 + 4 + 8 + 8 + 4 * 8, np.nan)
    expect_error(nerf_stage, ["train", str(capture), "-o", str(tmp_path / "run")],
                 "parameters hold NaN or infinity", capsys)


@pytest.mark.parametrize("value", [[], ["OPENCV"], {}, {"a": 1}, 3, None, True, 1.5])
def test_a_camera_model_of_any_json_type_is_one_line(value, tmp_path, rng, capsys):
    capture = nerfstudio_capture(tmp_path / "c", rng, lens={"camera_model": value})
    expect_error(nerf_stage, ["train", str(capture), "-o", str(tmp_path / "run")],
                 "camera_model", capsys)


def test_a_pickled_checkpoint_is_refused_in_one_line_without_torchs_warning(scene_run,
                                                                          tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(scene_run, run)
    state = torch.load(run / CHECKPOINT, weights_only=True)
    state["log"] = [os.path.join]  # a global: weights_only refuses to unpickle it
    torch.save(state, run / CHECKPOINT)
    expect_error(nerf_stage, ["export", str(run), "-o", str(tmp_path / "s.ply")],
                 "cannot read checkpoint", capsys)


def test_every_message_is_folded_onto_one_line_and_cut(capsys):
    def body():
        raise InputError("a value:\n[[1. 2.]\n [3. 4.]]" + " x" * 5000)

    assert run_cli("cmd", body) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and len(err) < 1100


def test_warnings_before_a_refusal_stay_off_stderr_and_show_on_success(capsys):
    import warnings

    def refused():
        warnings.warn("a library's remark", UserWarning, stacklevel=1)
        raise InputError("bad input")

    def fine():
        warnings.warn("a library's remark", UserWarning, stacklevel=1)
        return 0

    assert run_cli("cmd", refused) == 2
    assert capsys.readouterr().err.strip() == "cmd: error: bad input"
    with pytest.warns(UserWarning, match="remark"):
        assert run_cli("cmd", fine) == 0


# --- hints name the command's own flags ----------------------------------------------------

def _huge_png(path, side: int = 20000) -> None:
    """A PNG whose header declares side x side pixels (a few hundred bytes)."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side,
                                                                       8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 100)) + chunk(b"IEND", b""))


def test_a_hint_names_only_flags_the_command_has(tmp_path, rng, capsys):
    capture = nerfstudio_capture(tmp_path / "c", rng)
    _huge_png(capture / "images" / "f0.png")
    for argv in (["train", str(capture), "-o", str(tmp_path / "run")],
                 ["poses", str(capture / "images"), "-o", str(tmp_path / "out")]):
        assert nerf_stage(argv) == 2
        err = capsys.readouterr().err
        assert "more than" in err and "--max-pixels" not in err, err
    expect_error(decompose.main, [str(capture / "images"), "-o", str(tmp_path / "w.npz")],
                 "(use --max-pixels to allow more)", capsys)


# --- lenses ---------------------------------------------------------------------------------

@pytest.mark.parametrize("lens", [{"k1": -10.0}, {"k1": -0.2, "k2": -8.0},
                                  {"camera_model": "OPENCV_FISHEYE", "k1": -3.0}])
def test_a_lens_that_folds_over_the_photo_is_refused(lens, tmp_path, rng, capsys):
    capture = nerfstudio_capture(tmp_path / "c", rng, lens=lens, size=(63, 47))
    expect_error(nerf_stage, ["train", str(capture), "-o", str(tmp_path / "run")],
                 "folds over itself", capsys)


# --- signals --------------------------------------------------------------------------------

SIGNALLED = """
import os, signal, sys, time
from palette_core.cli import run_cli

def body():
    try:
        os.kill(os.getpid(), signal.{first})
        time.sleep(5)
    finally:  # the clean-up, interrupted by a second signal
        os.kill(os.getpid(), signal.{second})
        time.sleep(0.2)
        os.kill(os.getpid(), signal.{second})
        time.sleep(0.2)
    return 0

sys.exit(run_cli("cmd", body))
"""


@pytest.mark.parametrize("first, second", [("SIGTERM", "SIGTERM"), ("SIGINT", "SIGINT"),
                                           ("SIGTERM", "SIGINT"), ("SIGHUP", "SIGTERM")])
def test_signals_during_clean_up_end_the_command_cleanly(first, second):
    done = subprocess.run([sys.executable, "-c", SIGNALLED.format(first=first, second=second)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 128 + getattr(signal, first), done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr


def test_a_transforms_file_of_every_json_type_in_every_field_is_one_line(tmp_path, rng,
                                                                         capsys):
    """Each field of a nerfstudio transforms.json given each JSON type: read, or one line."""
    capture = nerfstudio_capture(tmp_path / "c", rng)
    original = json.loads((capture / "transforms.json").read_text())
    values = [None, True, 0, -1, 1.5, 1e308, "x", [], [1, 2], {}, {"a": 1}]
    fields = [k for k in original if k != "frames"] + ["camera_model", "ply_file_path",
                                                       "train_filenames", "k4", "p1"]
    frame_fields = ["file_path", "transform_matrix", "w", "fl_x", "camera_model", "k1"]
    from nerf_stage.data.dataset import load_dataset

    def read() -> int:
        return run_cli("read", lambda: (load_dataset(capture), 0)[1])

    for value in values:
        for field in fields + [f"frames.{f}" for f in frame_fields] + ["frames"]:
            data = json.loads(json.dumps(original))
            if field.startswith("frames."):
                data["frames"][1][field[7:]] = value
            else:
                data[field] = value
            (capture / "transforms.json").write_text(json.dumps(data))
            code = read()
            err = capsys.readouterr().err
            assert code == 0 or (code == 2 and len(err.strip().splitlines()) == 1), \
                (field, value, err)


WAITING = """
import sys, time
from palette_core.cli import run_cli

def body():
    try:
        print("ready", flush=True)
        time.sleep(30)
    finally:
        time.sleep(0.002)  # a short clean-up
    return 0

sys.exit(run_cli("cmd", body))
"""


def test_a_second_signal_at_any_moment_leaves_the_first_to_end_the_command():
    """SIGTERM twice, from 0 to 5 ms apart: every run ends through the first one (exit
    143, one line), never killed by the second mid-way."""
    for trial in range(12):
        child = subprocess.Popen([sys.executable, "-c", WAITING], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        assert child.stdout.readline() == "ready\n"
        child.send_signal(signal.SIGTERM)
        time.sleep(trial * 0.0004)
        child.send_signal(signal.SIGTERM)
        err = child.communicate(timeout=60)[1]
        assert child.returncode == 143 and err.strip() == "cmd: stopped by SIGTERM", (trial, err)
