"""Writing outputs: full disks, races with other writers, stale temporaries, signals,
collisions, permissions, paths that links would take outside."""

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from PIL import Image

from nerf_stage.cli import main as nerf_stage
from palette_core import InputError
from palette_core.cli import decompose, recolor
from palette_core.folders import inside
from palette_core.outputs import atomic_outputs, publish_folder

from .helpers import expect_error, stack_file


def test_output_paths_are_checked_again_after_links(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "link").symlink_to(tmp_path)
    with pytest.raises(InputError, match="outside"):
        inside(tmp_path / "out", "link/evil.png")
    assert inside(tmp_path / "out", "sub/fine.png") == tmp_path / "out" / "sub" / "fine.png"


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
