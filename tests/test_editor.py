"""The studio's palette editor without a page: edits, undo, reset, harmonisation, saving in
the command line's palette format."""

import json

import numpy as np
import pytest

pytest.importorskip("viser")

from harmonize import harmonize_palette, palette_shares  # noqa: E402
from palette_core.cli.recolor import main as recolor  # noqa: E402
from palette_core.errors import InputError, OutputExists  # noqa: E402
from palette_core.palette_file import read_palette_json, write_palette_json  # noqa: E402
from studio import PaletteEditor  # noqa: E402
from studio.photos import PhotoTarget  # noqa: E402

from .helpers import PALETTE, tiny_stack  # noqa: E402


def test_editor_edits_undo_reset():
    editor = PaletteEditor(PALETTE, lambda: np.full(4, 0.25))
    assert not editor.can_undo and not editor.undo()
    assert editor.set_colour(1, [0, 0, 0]) and not editor.set_colour(1, [0, 0, 0])
    editor.set_colour(2, [1, 1, 1])
    assert editor.palette[1].tolist() == [0, 0, 0] and editor.palette[2].tolist() == [1, 1, 1]
    assert editor.undo() and editor.palette[2].tolist() == PALETTE[2].tolist()
    assert editor.reset() and np.array_equal(editor.palette, PALETTE)
    assert editor.undo() and editor.palette[1].tolist() == [0, 0, 0]  # reset is undoable
    with pytest.raises(InputError):
        editor.set_colour(4, [0, 0, 0])


def test_editor_harmonises_like_the_library(tmp_path, rng):
    stack_path = tiny_stack(tmp_path / "w.npz", rng)
    target = PhotoTarget.open(stack_path)
    editor = PaletteEditor(target.palette, target.shares)
    name = editor.harmonize("best", 0.5)
    expected = harmonize_palette(PALETTE, palette_shares(target.stack), "best", 0.5)
    assert name == expected.fit.template.name
    assert np.allclose(editor.palette, expected.palette)
    with pytest.raises(InputError):
        editor.harmonize("no-such-template")


def test_editor_saves_the_cli_format_and_asks_before_replacing(tmp_path):
    editor = PaletteEditor(PALETTE, lambda: np.full(4, 0.25))
    editor.set_colour(0, [0, 0, 1])
    path = tmp_path / "edit.json"
    editor.save(path)
    assert np.array_equal(read_palette_json(path, k=4), editor.palette)
    editor.set_colour(0, [1, 1, 1])
    with pytest.raises(OutputExists):
        editor.save(path)
    assert read_palette_json(path)[0].tolist() == [0, 0, 1]  # kept
    editor.save(path, force=True)
    assert read_palette_json(path)[0].tolist() == [1, 1, 1]
    with pytest.raises(InputError, match=".json"):
        editor.save(tmp_path / "edit.txt")


def test_a_hand_edited_hex_code_wins_over_its_exact_colour(tmp_path):
    path = tmp_path / "p.json"
    write_palette_json(path, PALETTE)
    data = json.loads(path.read_text())
    data["palette"][1] = "#00ff00"
    path.write_text(json.dumps(data))
    read = read_palette_json(path)
    assert read[1].tolist() == [0, 1, 0]
    assert np.array_equal(np.delete(read, 1, 0), np.delete(PALETTE, 1, 0))  # exact


def test_what_the_studio_exports_is_what_palette_recolor_makes_of_its_palette(tmp_path, rng):
    """Harmonised colours are off the 8-bit grid: the saved file keeps them exactly, so the
    command line recolours to the same bytes."""
    target = PhotoTarget.open(tiny_stack(tmp_path / "w.npz", rng))
    editor = PaletteEditor(target.palette, target.shares)
    editor.harmonize("triad")
    assert not np.array_equal(np.round(editor.palette * 255) / 255, editor.palette)
    editor.save(tmp_path / "edit.json")
    exported = target.export(tmp_path / "studio", editor.palette)
    assert recolor([str(tmp_path / "w.npz"), "--palette", str(tmp_path / "edit.json"), "-o",
                    str(tmp_path / "cli")]) == 0
    for path in exported:
        assert path.read_bytes() == (tmp_path / "cli" / path.name).read_bytes()
