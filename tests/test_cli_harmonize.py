"""palette-harmonize through main([...])."""

import numpy as np
import pytest
from PIL import Image

from harmonize import TEMPLATES, harmonize_palette, palette_shares
from harmonize.cli import main
from palette_core import WeightStack, read_stack, write_stack

from .helpers import expect_error

PALETTE = np.array([[0.85, 0.2, 0.15], [0.95, 0.75, 0.1], [0.2, 0.6, 0.3],
                    [0.15, 0.3, 0.8], [0.5, 0.5, 0.5]])


@pytest.fixture
def stack_file(tmp_path, rng):
    """An additive stack of two images of different sizes over a five-colour palette."""
    weights = [rng.dirichlet(np.ones(5), size=(h, w)).astype(np.float32)
               for h, w in [(6, 8), (5, 7)]]
    path = tmp_path / "w.npz"
    write_stack(WeightStack(PALETTE, weights, ["a.png", "sub/b.png"]), path)
    return path


def test_one_template_with_render(stack_file, tmp_path, capsys):
    out, render = tmp_path / "h.npz", tmp_path / "render"
    assert main([str(stack_file), "--template", "triad", "-o", str(out),
                 "--render", str(render)]) == 0
    printed = capsys.readouterr().out
    assert "triad: alpha" in printed and "cost" in printed
    source, result = read_stack(stack_file), read_stack(out)
    for before, after in zip(source.weights, result.weights):
        np.testing.assert_array_equal(before, after)
    expected = harmonize_palette(source.palette, palette_shares(source), "triad")
    np.testing.assert_allclose(result.palette, expected.palette, atol=1e-7)
    assert not np.allclose(result.palette, source.palette)
    record = result.meta["harmonize"]
    assert record["template"] == "triad" and record["alpha"] == pytest.approx(expected.fit.alpha)
    image = np.asarray(Image.open(render / "sub" / "b.png"), float)
    truth = np.clip(result.weights[1] @ result.palette.astype(float), 0, 1) * 255
    assert image.shape == (5, 7, 3) and np.abs(image - truth).max() <= 1.0
    assert Image.open(render / "hue_wheel.png").size == (320, 320)
    assert (render / "palette.png").is_file()


def test_default_output_name_and_strength_zero(stack_file, capsys):
    assert main([str(stack_file), "--template", "square", "--strength", "0"]) == 0
    result = read_stack(stack_file.with_name("w_square.npz"))
    np.testing.assert_array_equal(result.palette, read_stack(stack_file).palette)


def test_best_picks_the_least_cost(stack_file, tmp_path, capsys):
    assert main([str(stack_file), "--template", "best", "-o", str(tmp_path / "b.npz")]) == 0
    lines = capsys.readouterr().out.splitlines()
    table = {line.split()[0]: float(line.split()[2]) for line in lines[1:8]}
    assert set(table) == set(TEMPLATES)
    chosen = next(line.split()[0] for line in lines[1:8] if line.endswith("*"))
    assert table[chosen] == min(table.values())
    assert read_stack(tmp_path / "b.npz").meta["harmonize"]["template"] == chosen


def test_all_templates_and_contact_sheet(stack_file, tmp_path, capsys):
    render = tmp_path / "render"
    assert main([str(stack_file), "--template", "all", "-o", str(tmp_path / "h.npz"),
                 "--render", str(render)]) == 0
    palettes = [read_stack(tmp_path / f"h_{name}.npz").palette for name in TEMPLATES]
    assert len({p.tobytes() for p in palettes}) == len(TEMPLATES)
    for name in TEMPLATES:
        assert (render / name / "a.png").is_file() and (render / name / "hue_wheel.png").is_file()
    sheet = Image.open(render / "contact_sheet.png")
    assert sheet.width == 4 * 256 and sheet.height > 2 * 256


def test_all_templates_without_render(stack_file, tmp_path, capsys):
    assert main([str(stack_file), "--template", "all", "-o", str(tmp_path / "o" / "h.npz")]) == 0
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == sorted(
        f"h_{name}.npz" for name in TEMPLATES)


def test_transport_stack(tmp_path, rng, capsys):
    weights = [rng.random((4, 4, 6)).astype(np.float32)]  # K = 2, order 2
    path = tmp_path / "t.npz"
    write_stack(WeightStack(PALETTE[:2], weights, ["v.png"], "simulated", "transport", 2), path)
    assert main([str(path), "--template", "complementary", "--render",
                 str(tmp_path / "r")]) == 0
    result = read_stack(tmp_path / "t_complementary.npz")
    assert result.basis == "transport" and result.order == 2
    np.testing.assert_array_equal(result.weights[0], weights[0])


@pytest.mark.parametrize("args, message", [
    (["--template", "tetrad"], "unknown template 'tetrad'; choose one of monochrome, "),
    (["--template", "triad", "--strength", "1.5"], "strength must lie in [0, 1], got 1.5"),
    (["--template", "triad", "--strength", "-0.1"], "strength must lie in [0, 1]"),
    (["--template", "triad", "--strength", "nan"], "strength must lie in [0, 1]"),
    (["--template", "triad", "-o", "x.png"], "output must end in .npz"),
    (["--strength", "1"], "the following arguments are required: --template"),
])
def test_bad_arguments(stack_file, capsys, args, message):
    expect_error(main, [str(stack_file), *args], message, capsys)


def test_bad_stacks(tmp_path, capsys):
    expect_error(main, [str(tmp_path / "none.npz"), "--template", "triad"],
                 "does not exist", capsys)
    no_palette = tmp_path / "no_palette.npz"
    np.savez(no_palette, format=np.array("palette-weights/1"), weights=np.zeros((1, 2, 2, 3)))
    expect_error(main, [str(no_palette), "--template", "triad"], "missing key 'palette'", capsys)


def test_no_overwrite_without_force(stack_file, tmp_path, capsys):
    out = tmp_path / "h_triad.npz"
    out.write_bytes(b"keep")
    expect_error(main, [str(stack_file), "--template", "all", "-o", str(tmp_path / "h.npz"),
                        "--render", str(tmp_path / "r")], "already exists (use --force", capsys)
    assert out.read_bytes() == b"keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h_triad.npz", "w.npz"]
    assert main([str(stack_file), "--template", "triad", "-o", str(out), "--force"]) == 0
    assert read_stack(out).meta["harmonize"]["template"] == "triad"
