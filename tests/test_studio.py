"""palette-studio without a browser: the editing state, both targets, exports, bad input."""

import socket

import numpy as np
import pytest

pytest.importorskip("viser")

from palette_core.basis import weights_to_rgb  # noqa: E402
from palette_core.cli.recolor import main as recolor  # noqa: E402
from palette_core.errors import InputError, OutputExists  # noqa: E402
from palette_core.palette_file import read_palette_json, write_palette_json  # noqa: E402
from palette_core.selection import recolor_local  # noqa: E402
from palette_core.stack import WeightStack  # noqa: E402
from studio.app import Studio  # noqa: E402
from studio.cli import main as studio_main  # noqa: E402
from studio.drawing import Drawing  # noqa: E402
from studio.photos import PhotoTarget, downsample  # noqa: E402
from studio.pictures import letterbox, to_bytes  # noqa: E402

from .helpers import PALETTE, expect_error, tiny_stack  # noqa: E402


def test_photo_views_recolour_the_stack(tmp_path, rng):
    target = PhotoTarget.open(tiny_stack(tmp_path / "w.npz", rng))
    edited = PALETTE[::-1]
    view = target.view(1, edited)
    expected = np.clip(weights_to_rgb(target.stack.weights[1], edited), 0, 1) * 255
    assert view.dtype == np.uint8 and np.abs(view - expected).max() <= 0.5 + 1e-3
    small = target.view(1, edited, max_pixels=12)
    assert small.shape[0] * small.shape[1] <= 12
    weights = downsample(target.stack.weights[1], 12)
    assert np.allclose(weights.sum(-1), 1)  # strided: exact weights, still summing to one


def test_photo_export_matches_palette_recolor(tmp_path, rng):
    stack_path = tiny_stack(tmp_path / "w.npz", rng)
    edited = np.clip(PALETTE + 0.05, 0, 1)
    write_palette_json(tmp_path / "edit.json", edited)
    assert recolor([str(stack_path), "--palette", str(tmp_path / "edit.json"), "-o",
                    str(tmp_path / "cli")]) == 0
    target = PhotoTarget.open(stack_path)
    written = target.export(tmp_path / "studio", read_palette_json(tmp_path / "edit.json"))
    assert len(written) == 3
    for path in written:
        assert path.read_bytes() == (tmp_path / "cli" / path.name).read_bytes()
    with pytest.raises(OutputExists):
        target.export(tmp_path / "studio", edited)


def test_drawn_boxes_and_dabs_are_soft_masks_at_the_images_size():
    drawing = Drawing(lambda i: (20, 30), 2)
    assert not drawing
    drawing.box(0, np.array([[20.0, 15.0], [5.0, 4.0]]), feather=0)  # corners in any order
    hard = drawing.masks[0]
    assert hard.shape == (20, 30) and set(np.unique(hard)) == {0, 1}
    assert hard[4:15, 5:20].all() and hard.sum() == 11 * 15
    drawing.dab(1, np.array([10.0, 10.0]), radius=4, feather=2)
    soft = drawing.masks[1]
    assert soft[10, 10] == 1 and 0 < soft[10, 14] < 1 and soft[10, 17] == 0
    assert soft.min() >= 0 and soft.max() <= 1
    drawing.clear()
    assert not drawing


def test_a_drawn_edit_shows_exports_and_replays_as_the_library_makes_it(tmp_path, rng):
    stack_path = tiny_stack(tmp_path / "w.npz", rng)
    target = PhotoTarget.open(stack_path)
    drawing = Drawing(target.size, len(target.names))
    drawing.box(1, np.array([[2.0, 1.0], [9.0, 6.0]]), feather=1.5)
    edited = PALETTE[::-1]
    view = target.view(1, edited, drawing=drawing)
    masks = tmp_path / "masks"
    edits = drawing.local_edits(target.stack, edited, masks)
    expected = recolor_local(np.asarray(target.stack.weights[1], np.float64), PALETTE, edits,
                             target.names[1], target.stack.basis)
    assert np.abs(view - np.clip(expected, 0, 1) * 255).max() <= 1.5  # masks kept at 8 bits
    assert np.array_equal(target.view(0, edited, drawing=drawing), target.view(0, PALETTE))
    written = drawing.save(tmp_path / "edit.json", target.stack, edited)
    assert [p.name for p in written] == ["edit.json", "edit.masks"]
    exported = target.export(tmp_path / "studio", edited, drawing=drawing)
    assert recolor([str(stack_path), "--edits", str(tmp_path / "edit.json"), "-o",
                    str(tmp_path / "cli")]) == 0
    for path in exported:
        assert path.read_bytes() == (tmp_path / "cli" / path.name).read_bytes()
    with pytest.raises(InputError, match="nothing is selected"):
        Drawing(target.size, len(target.names)).save(tmp_path / "none.json", target.stack, edited)


def test_letterbox_centres_the_image():
    image = np.full((10, 20, 3), 255, np.uint8)
    boxed = letterbox(image, 1.0)
    assert boxed.shape == (20, 20, 3) and boxed[10, 10].tolist() == [255] * 3
    assert letterbox(image, 4.0).shape == (10, 40, 3)


def test_studio_edits_and_serves(tmp_path, rng):
    studio = Studio(PhotoTarget.open(tiny_stack(tmp_path / "w.npz", rng)), port=0)
    try:
        assert studio.url.startswith("http://127.0.0.1:")
        studio._apply(lambda: studio.editor.set_colour(0, [0, 0, 0]))
        assert studio.pickers[0].value == (0, 0, 0)
        studio._apply(studio.editor.undo)
        assert studio.pickers[0].value == tuple(to_bytes(studio.editor.original[0]).tolist())
        studio.view.show_image(2)
        assert studio.view.chooser.value == "p2.png"
    finally:
        studio.stop()


@pytest.fixture
def studio(tmp_path, rng):
    running = Studio(PhotoTarget.open(tiny_stack(tmp_path / "w.npz", rng)), port=0)
    yield running
    running.stop()


def test_the_panel_as_a_new_user_sees_it(studio):
    """Undo with nothing to undo says so; show original shows the original colours in the
    pickers too; the strip's buttons open their image and mark the current one."""
    studio._apply(studio._undo)
    assert studio.status.content == "nothing to undo"
    studio._apply(lambda: studio.editor.set_colour(0, [0, 0, 0]))
    studio.before.value = True
    studio._apply(lambda: None)
    assert studio.pickers[0].value == tuple(to_bytes(studio.editor.original[0]).tolist())
    studio.before.value = False
    studio._apply(lambda: None)
    assert studio.pickers[0].value == (0, 0, 0)
    assert studio.view.strip_buttons.options == ("[1]", "2", "3")
    studio.view.show_image(1)
    assert studio.view.strip_buttons.options == ("1", "[2]", "3")
    assert not studio.server.scene.world_axes.visible


def test_cli_bad_input(tmp_path, rng, capsys):
    expect_error(studio_main, [str(tmp_path / "missing.npz"), "--no-browser"], "does not exist",
                 capsys)
    (tmp_path / "notes.txt").write_text("hello")
    expect_error(studio_main, [str(tmp_path / "notes.txt"), "--no-browser"],
                 "neither a weight stack", capsys)
    expect_error(studio_main, [str(tmp_path), "--no-browser"], "neither a weight stack", capsys)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    expect_error(studio_main, [str(tmp_path / "bad.npz"), "--no-browser"], "bad.npz", capsys)
    stack = tiny_stack(tmp_path / "w.npz", rng)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        expect_error(studio_main, [str(stack), "--no-browser", "--port", str(port)],
                     f"cannot listen on 127.0.0.1:{port}", capsys)
    expect_error(studio_main, [str(stack), "--no-browser", "--port", "70000"], "--port", capsys)


def test_a_hundred_images_open_without_reading_them(tmp_path, rng):
    """Only the image on screen and the thumbnails beside it are read."""
    from studio.photo_view import STRIP

    class Counting(list):
        reads = 0

        def __getitem__(self, i):
            Counting.reads += 1
            return super().__getitem__(i)

    weights = Counting(rng.dirichlet(np.ones(4), size=(5, 6)).astype(np.float32)
                       for _ in range(100))
    stack = WeightStack(PALETTE, weights, [f"p{i:03d}.png" for i in range(100)], "mvc")
    studio = Studio(PhotoTarget(stack, tmp_path / "w.npz"), port=0)
    try:
        assert Counting.reads == 0
        studio.view.show_image(50)
        assert 0 < Counting.reads <= 1 + STRIP
    finally:
        studio.stop()


def test_photo_mode_reads_zarr_stacks(tmp_path, rng):
    pytest.importorskip("zarr")
    from palette_core.stack import read_stack
    from palette_core.stack.zarr import write_zarr_stack

    write_zarr_stack(read_stack(tiny_stack(tmp_path / "w.npz", rng)), tmp_path / "w.zarr")
    lazy, eager = PhotoTarget.open(tmp_path / "w.zarr"), PhotoTarget.open(tmp_path / "w.npz")
    assert np.array_equal(lazy.view(2, PALETTE), eager.view(2, PALETTE))
    assert np.allclose(lazy.shares(), eager.shares())


def test_the_url_is_the_first_line_and_a_signal_stops_it(tmp_path, rng):
    import signal
    import subprocess
    import sys
    import urllib.request

    stack = tiny_stack(tmp_path / "w.npz", rng)
    process = subprocess.Popen([sys.executable, "-m", "studio.cli", str(stack), "--no-browser",
                                "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        url = process.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
    finally:
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=30)
    assert process.returncode == 128 + signal.SIGTERM
    assert "Traceback" not in err
