"""Local edits in photos: an edited palette inside a selection, the original outside."""

import json

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import gaussian_filter

from palette_core import InputError, read_stack
from palette_core.basis import Basis, weights_to_rgb
from palette_core.cli import decompose, recolor
from palette_core.edit_file import masks_folder
from palette_core.selection import LocalEdit, Selection, _feathered, parse_near, recolor_local

from .helpers import expect_error


@pytest.fixture
def stack_and_edit(photo_dir, tmp_path):
    """A decomposed stack of ``photo_dir`` and an edited palette file (every colour
    inverted)."""
    assert decompose.main([str(photo_dir), "-k", "5", "-o", str(tmp_path / "w.npz")]) == 0
    stack = read_stack(tmp_path / "w.npz")
    edit = tmp_path / "edit.json"
    edit.write_text(json.dumps({"palette": (1 - np.asarray(stack.palette)).tolist()}))
    return stack, 1 - np.asarray(stack.palette), tmp_path


def _png(path, grey):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(grey, np.uint8)).save(path)


def test_a_hard_mask_edits_inside_and_leaves_the_rest_exactly(stack_and_edit):
    stack, edited, tmp = stack_and_edit
    w = np.asarray(stack.weights[0], np.float64)
    inside = np.zeros(w.shape[:2], bool)
    inside[:, : w.shape[1] // 2] = True
    _png(tmp / "mask.png", inside * 255)
    rgb = recolor_local(w, stack.palette, [LocalEdit(Selection(mask=tmp / "mask.png"), edited)],
                        "a.png", stack.basis)
    assert np.array_equal(rgb[~inside], weights_to_rgb(w, stack.palette)[~inside])
    assert np.allclose(rgb[inside], weights_to_rgb(w, edited)[inside], atol=1e-12)


def test_a_feathered_edit_moves_each_pixel_by_at_most_its_share(stack_and_edit):
    stack, edited, tmp = stack_and_edit
    w = np.asarray(stack.weights[0], np.float64)
    mask = np.zeros(w.shape[:2])
    mask[4:8, 4:8] = 255
    _png(tmp / "mask.png", mask)
    selection = Selection(mask=tmp / "mask.png", feather=1.5)
    original, full = weights_to_rgb(w, stack.palette), weights_to_rgb(w, edited)
    m = selection.values("a.png", w, original)
    assert 0 <= m.min() and m.max() <= 1 and 0 < m[3, 3] < 1  # soft at the edge
    rgb = recolor_local(w, stack.palette, [LocalEdit(selection, edited)], "a.png", stack.basis)
    assert np.allclose(rgb - original, m[..., None] * (full - original), atol=1e-12)
    assert np.all(np.abs(rgb - original) <= np.abs(full - original) + 1e-12)
    assert np.array_equal(rgb[m == 0], original[m == 0])


@pytest.mark.parametrize("box", [np.s_[50:80, 100:180], np.s_[0:30, 250:300], np.s_[:, :]])
@pytest.mark.parametrize("sigma", [0.7, 8.0])
def test_feathering_around_the_selection_equals_feathering_everywhere(box, sigma, rng):
    m = np.zeros((200, 300))
    m[box] = rng.random(m[box].shape)
    assert np.array_equal(_feathered(m, sigma), np.clip(gaussian_filter(m, sigma), 0, 1))


def test_colour_and_near_selections(stack_and_edit):
    stack, edited, _ = stack_and_edit
    w = np.asarray(stack.weights[0], np.float64)
    original = weights_to_rgb(w, stack.palette)
    by_weight = Selection(colour=2, threshold=0.4).values("a.png", w, original)
    assert np.array_equal(by_weight == 1, w[..., 2] >= 0.4)
    target = original[3, 5]
    near = Selection(near=tuple(target), distance=0.05).values("a.png", w, original)
    assert near[3, 5] == 1
    assert np.array_equal(near == 1, np.linalg.norm(original - target, axis=-1) <= 0.05)
    transport = np.concatenate([np.zeros_like(w[..., :1]), w], -1)  # first-order terms
    assert np.array_equal(Selection(colour=2, threshold=0.4).values(
        "a.png", transport, original, Basis.TRANSPORT), by_weight)
    assert parse_near("#ff8000") == (1.0, 128 / 255, 0.0)


def test_palette_recolor_with_a_folder_of_masks(stack_and_edit, capsys):
    stack, edited, tmp = stack_and_edit
    for name, w in zip(stack.names, stack.weights):
        mask = np.zeros(w.shape[:2])
        mask[0] = 255  # the first row of each image
        _png(tmp / "masks" / name.replace(".jpg", ".png"), mask)
    assert recolor.main([str(tmp / "w.npz"), "--palette", str(tmp / "edit.json"), "-o",
                         str(tmp / "out"), "--mask", str(tmp / "masks")]) == 0
    assert "(1 local edit)" in capsys.readouterr().out
    for name, w in zip(stack.names, stack.weights):
        written = np.asarray(Image.open(tmp / "out" / name), float)
        original = np.round(np.clip(weights_to_rgb(w, stack.palette), 0, 1) * 255)
        full = np.round(np.clip(weights_to_rgb(w, edited), 0, 1) * 255)
        if name.endswith(".png"):  # lossless: exactly each side's colours
            assert np.array_equal(written[1:], original[1:])
            assert np.array_equal(written[0], full[0])


@pytest.mark.parametrize("flags, message", [
    (["--mask", "wrong"], "mask wrong/ is 3x3, image a.png is 16x12"),
    (["--mask", "missing"], "no mask for image b.jpg"),
    (["--mask", "nowhere.png"], "does not exist"),
    (["--select-colour", "7"], "selected palette colour 7 is not one of the palette's 5"),
    (["--select-near", "#12345"], "must be #rrggbb"),
    (["--select-near", "#123456", "--feather", "nan"], "must be finite"),
    (["--select-colour", "1", "--feather", "-1"], "cannot be negative"),
])
def test_bad_selections_are_one_line_and_write_nothing(stack_and_edit, capsys, flags, message):
    _, _, tmp = stack_and_edit
    _png(tmp / "wrong" / "a.png", np.zeros((3, 3)))
    _png(tmp / "missing" / "a.png", np.zeros((12, 16)))
    flags = [str(tmp / f) if f in ("wrong", "missing", "nowhere.png") else f for f in flags]
    message = message.replace("wrong/", str(tmp / "wrong" / "a.png"))
    expect_error(recolor.main, [str(tmp / "w.npz"), "--palette", str(tmp / "edit.json"),
                                "-o", str(tmp / "out"), *flags], message, capsys)
    assert not (tmp / "out").exists()


def test_a_selection_is_one_thing():
    with pytest.raises(InputError, match="exactly one"):
        Selection(colour=1, near=(0.0, 0.0, 0.0))


def test_stacked_edits_cover_each_other_like_layers(stack_and_edit, rng):
    stack, edited, tmp = stack_and_edit
    w = np.asarray(stack.weights[0], np.float64)
    h, width = w.shape[:2]
    left, top = np.zeros((h, width)), np.zeros((h, width))
    left[:, : width // 2] = 255
    top[: h // 2] = 255
    _png(tmp / "left.png", left)
    _png(tmp / "top.png", top)
    second = rng.uniform(0, 1, edited.shape)
    edits = [LocalEdit(Selection(mask=tmp / "left.png"), edited),
             LocalEdit(Selection(mask=tmp / "top.png", feather=1.0), second)]
    rgb = recolor_local(w, stack.palette, edits, "a.png", stack.basis)
    original = weights_to_rgb(w, stack.palette)
    m_top = edits[1].selection.values("a.png", w, original)
    shares = [(left / 255) * (1 - m_top), m_top]
    expected = original + sum(s[..., None] * (weights_to_rgb(w, p) - original)
                              for s, p in zip(shares, (edited, second)))
    assert np.allclose(rgb, expected, atol=1e-12)
    untouched = (left == 0) & (m_top == 0)
    assert untouched.any() and np.array_equal(rgb[untouched], original[untouched])
    covered = m_top == 1
    assert np.allclose(rgb[covered], weights_to_rgb(w, second)[covered], atol=1e-12)


def test_edits_save_replay_and_stack_from_the_command_line(stack_and_edit, capsys):
    stack, edited, tmp = stack_and_edit
    masks = tmp / "masks"
    for name, w in zip(stack.names, stack.weights):
        mask = np.zeros(w.shape[:2])
        mask[2:6] = 255
        _png(masks / name.replace(".jpg", ".png"), mask)
    stack_path = str(tmp / "w.npz")
    assert recolor.main([stack_path, "--palette", str(tmp / "edit.json"), "--mask", str(masks),
                         "--feather", "1.5", "-o", str(tmp / "first"),
                         "--save-edits", str(tmp / "look.json")]) == 0
    assert sorted(p.name for p in (tmp / "look.masks" / "0").iterdir()) == sorted(
        p.name for p in masks.iterdir())
    masks.rename(tmp / "gone")  # the saved copies are used from now on
    assert recolor.main([stack_path, "--edits", str(tmp / "look.json"),
                         "-o", str(tmp / "again")]) == 0
    for name in stack.names:
        assert (tmp / "again" / name).read_bytes() == (tmp / "first" / name).read_bytes()
    assert recolor.main([stack_path, "--edits", str(tmp / "look.json"), "--palette",
                         str(tmp / "edit.json"), "--select-colour", "1", "-o", str(tmp / "both"),
                         "--save-edits", str(tmp / "both.json")]) == 0
    assert "(2 local edits)" in capsys.readouterr().out
    saved = json.loads((tmp / "both.json").read_text())
    assert [("mask" in e, e.get("colour")) for e in saved["edits"]] == [(True, None), (False, 1)]
    assert masks_folder(tmp / "both.json").is_dir()
    expect_error(recolor.main, [stack_path, "--edits", str(tmp / "look.json"), "-o",
                                str(tmp / "x"), "--save-edits", str(tmp / "both.json")],
                 "already exists", capsys)
    assert not (tmp / "x").exists()


def test_edit_files_from_elsewhere_are_refused(stack_and_edit, photo_dir, capsys):
    stack, edited, tmp = stack_and_edit
    assert recolor.main([str(tmp / "w.npz"), "--palette", str(tmp / "edit.json"),
                         "--select-colour", "0", "-o", str(tmp / "a"),
                         "--save-edits", str(tmp / "e.json")]) == 0
    assert decompose.main([str(photo_dir), "-k", "4", "-o", str(tmp / "other.npz")]) == 0
    expect_error(recolor.main, [str(tmp / "other.npz"), "--edits", str(tmp / "e.json"),
                                "-o", str(tmp / "b")], "made for another stack", capsys)
    data = json.loads((tmp / "e.json").read_text())
    for change, message in (({"mask": "../../etc/passwd"}, "outside"),
                            ({"colour": 9}, "not one of the palette's 5"),
                            ({"near": "#12"}, "must be #rrggbb"),
                            ({"palette": ["#000000"]}, "has 1 colours, expected 5"),
                            ({"hook": 1}, "unknown field 'hook'")):
        entry = {k: v for k, v in data["edits"][0].items() if k != "colour" or "mask" not in change}
        if "palette" in change:
            entry.pop("rgb")
        (tmp / "bad.json").write_text(json.dumps({**data, "edits": [{**entry, **change}]}))
        expect_error(recolor.main, [str(tmp / "w.npz"), "--edits", str(tmp / "bad.json"),
                                    "-o", str(tmp / "b")], message, capsys)
    expect_error(recolor.main, [str(tmp / "w.npz"), "-o", str(tmp / "b")], "give --palette",
                 capsys)
    assert not (tmp / "b").exists()
