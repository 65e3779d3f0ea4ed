"""palette-decompose and palette-recolor through main([...]), and as processes."""

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from palette_core import read_stack
from palette_core.basis import weights_to_rgb
from palette_core.cli import decompose, recolor

from .helpers import expect_error, weight_invariants


def run_decompose(photo_dir, out, *extra):
    return decompose.main([str(photo_dir), "-k", "5", "-o", str(out / "w.npz"), *extra])


def test_decompose_then_recolor(photo_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_decompose(photo_dir, out, "--layers", str(out / "layers")) == 0
    printed = capsys.readouterr().out
    assert "palette (" in printed and "RMSE" in printed and "time:" in printed
    stack = read_stack(out / "w.npz")
    assert stack.names == ["a.png", "b.jpg", "sub/c.png"]
    assert [w.shape[:2] for w in stack.weights] == [(12, 16), (10, 9), (7, 11)]
    for w in stack.weights:
        weight_invariants(w.reshape(-1, w.shape[-1]), stack.palette, None)
    assert (out / "w.palette.png").is_file()
    k = len(stack.palette)
    assert len(json.loads((out / "w.palette.json").read_text())["palette"]) == k
    assert len(list((out / "layers").rglob("*.png"))) == 3 * k

    # Recolour with the unedited palette: the stack's own reconstruction comes back exactly
    # (the palette file keeps the exact colours beside the hex codes).
    assert recolor.main([str(out / "w.npz"), "--palette", str(out / "w.palette.json"),
                         "-o", str(out / "same")]) == 0
    expected = np.round(np.clip(weights_to_rgb(stack.weights[0], stack.palette), 0, 1) * 255)
    again = np.asarray(Image.open(out / "same" / "a.png"), float)
    assert np.array_equal(expected, again)
    assert (out / "same" / "sub" / "c.png").is_file()


def test_console_script_process(photo_dir, tmp_path):
    """As a process (``run``, which skips Python's teardown): every output in place and the
    streams flushed on success; one line on stderr and exit code 2 on bad input."""
    command = [sys.executable, "-m", "palette_core.cli.decompose", str(photo_dir), "-k", "5",
               "-o", str(tmp_path / "w.npz")]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.rstrip().splitlines()[-1].startswith("wrote ")
    assert len(read_stack(tmp_path / "w.npz").palette) == 5
    assert (tmp_path / "w.palette.json").is_file() and (tmp_path / "w.palette.png").is_file()
    again = subprocess.run(command, capture_output=True, text=True)  # no --force
    assert again.returncode == 2 and again.stderr.count("\n") == 1


def test_float16_stack(photo_dir, tmp_path):
    assert run_decompose(photo_dir, tmp_path, "--dtype", "float16") == 0
    assert read_stack(tmp_path / "w.npz").weights[0].dtype == np.float16


def test_fewer_hull_vertices_than_k(tmp_path, capsys):
    Image.fromarray(np.full((4, 4, 3), 128, np.uint8)).save(tmp_path / "grey.png")
    assert decompose.main([str(tmp_path / "grey.png"), "-k", "6",
                           "-o", str(tmp_path / "o" / "w.npz")]) == 0
    assert "fewer than -k 6" in capsys.readouterr().err
    assert read_stack(tmp_path / "o" / "w.npz").palette.shape == (1, 3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["MISSING"], "does not exist"),
        (["EMPTY"], "no images"),
        (["CORRUPT"], "bad.png"),
        (["PHOTOS", "-k", "3"], "at least 4"),
        (["PHOTOS", "--max-error", "-1"], "non-negative"),
        (["PHOTOS", "--method", "magic"], "invalid choice"),
        (["PHOTOS", "-o", "NOTDIR/x/w.npz"], "writable"),
    ],
)
def test_decompose_bad_input(photo_dir, tmp_path, capsys, args, message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad.png").write_bytes(b"garbage")
    (tmp_path / "afile").write_text("x")
    paths = {"MISSING": tmp_path / "missing", "EMPTY": tmp_path / "empty",
             "CORRUPT": tmp_path / "bad.png", "PHOTOS": photo_dir, "NOTDIR": tmp_path / "afile"}
    argv = [str(paths.get(a.split("/")[0], a)) + ("/" + a.split("/", 1)[1] if "/" in a else "")
            for a in args]
    if "-o" not in argv:
        argv += ["-o", str(tmp_path / "out" / "w.npz")]
    expect_error(decompose.main, argv, message, capsys)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_no_overwrite_without_force(photo_dir, tmp_path, capsys):
    assert run_decompose(photo_dir, tmp_path) == 0
    before = (tmp_path / "w.npz").read_bytes()
    expect_error(decompose.main, [str(photo_dir), "-o", str(tmp_path / "w.npz")],
                 "--force", capsys)
    assert (tmp_path / "w.npz").read_bytes() == before
    assert run_decompose(photo_dir, tmp_path, "--force") == 0


def test_recolor_bad_input(photo_dir, tmp_path, capsys):
    assert run_decompose(photo_dir, tmp_path) == 0
    k = len(read_stack(tmp_path / "w.npz").palette)
    stack = str(tmp_path / "w.npz")
    bad = tmp_path / "bad.json"
    cases = [
        ({"palette": ["#000000"] * (k + 1)}, f"expected {k}"),
        ({"palette": [[0.1, 2.0, 0.3]] * k}, "outside [0, 1]"),
        ({"palette": ["#zzzzzz"] * k}, "not #rrggbb"),
        ({"colours": []}, "must hold"),
        ({"palette": ["#000000"] * k, "rgb": [[0.0, 0.0, 0.0]] * (k - 1)}, "as many colours"),
        ({"palette": ["#000000"] * k, "rgb": [[0.0, 0.0, float("nan")]] * k}, "outside [0, 1]"),
        ({"palette": ["#000000"] * k, "rgb": ["#000000"] * k}, "neither #rrggbb"),
    ]
    for content, message in cases:
        bad.write_text(json.dumps(content))
        expect_error(recolor.main, [stack, "--palette", str(bad), "-o", str(tmp_path / "r")],
                     message, capsys)
    expect_error(recolor.main, [str(tmp_path / "nope.npz"), "--palette", str(bad), "-o",
                                str(tmp_path / "r")], "does not exist", capsys)
    assert not (tmp_path / "r").exists()
