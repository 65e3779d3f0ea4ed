"""Splat files of other tools: every format read, the written ones round trip, hostile files
are refused in one line, and a palette edit of a splat file keeps what it does not touch
bit for bit (docs/splat_files.md)."""

import gzip
import json
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from harmonize.cli import main as harmonize
from palette_core.cli.decompose import main as decompose
from palette_core.cli.recolor import main as recolor
from palette_core.errors import InputError
from palette_core.palette_file import write_palette_json
from splat_files import FORMATS, SplatFields, read_splat_file, write_splat_file
from splat_files.fields import SH_C0
from splat_files.spz import SH_FLIPS, flip_axes
from splat_files.stack import decompose_splats, read_splat_stack

from .helpers import expect_error

FIXTURES = Path(__file__).parent / "data" / "splat-transform"
ATTRIBUTES = ("means", "sh0", "shN", "opacities", "scales", "quats")


def scene(rng, n: int = 300, degree: int = 3) -> SplatFields:
    """``n`` random splats of colours in [0.05, 0.95], spherical harmonics of ``degree``."""
    b = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    return SplatFields(
        rng.uniform(-2, 2, (n, 3)).astype(np.float32),
        ((rng.uniform(0.05, 0.95, (n, 3)) - 0.5) / SH_C0).astype(np.float32),
        rng.uniform(-0.3, 0.3, (n, b, 3)).astype(np.float32),
        rng.uniform(-3, 3, n).astype(np.float32), rng.uniform(-5, -1, (n, 3)).astype(np.float32),
        rng.normal(size=(n, 4)).astype(np.float32))


def same(a: SplatFields, b: SplatFields) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ATTRIBUTES)


def test_the_fixtures_of_splat_transform_land_in_one_frame():
    """``.splat`` and SPZ 3 and 4 (Niantic's RUB, converted) hold the same 2 x 2 grid in
    the PLY's frame; colours agree within SPZ's and ``.splat``'s 8 bits."""
    grid = [[-1, 0, -1], [0, 0, -1], [-1, 0, 0], [0, 0, 0]]
    splat = read_splat_file(FIXTURES / "minimal.splat")
    for name in ("minimal-v3.spz", "minimal-v4.spz"):
        spz = read_splat_file(FIXTURES / name)
        assert np.allclose(spz.means, grid) and np.allclose(splat.means, grid)
        assert np.abs(spz.colours() - splat.colours()).max() < 2 / 255
        assert np.allclose(np.exp(spz.scales), 0.1, rtol=0.05)
        assert np.allclose(1 / (1 + np.exp(-spz.opacities)), 0.9, atol=0.01)
    assert np.allclose(read_splat_file(FIXTURES / "minimal-v2.spz").means, np.multiply(
        grid, [1, 1, -1]))  # packed by hand in SPZ's frame, without the conversion


def test_the_spz_flips_are_the_parities_of_the_spherical_harmonics():
    torch = pytest.importorskip("torch")
    from nerf_stage.splats.sh import sh_basis

    d = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=1)
    flipped = d * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    ratio = (sh_basis(flipped, 3) / sh_basis(d, 3))[:, 1:].numpy()
    assert np.allclose(ratio, SH_FLIPS[None].astype(np.float64))


@pytest.mark.parametrize("suffix", [s for s, f in FORMATS.items() if f.writer])
@pytest.mark.parametrize("degree", [0, 3])
def test_every_written_format_round_trips_within_its_quantisation(suffix, degree, tmp_path,
                                                                  rng):
    fields = scene(rng, degree=degree)
    path = write_splat_file(fields, tmp_path / f"s{suffix}")
    read = read_splat_file(path)
    tolerances = FORMATS[suffix].tolerances(fields)
    for name, tolerance in tolerances.items():
        a, b = getattr(fields, name), getattr(read, name)
        if name == "opacities":
            a, b = 1 / (1 + np.exp(-a)), 1 / (1 + np.exp(-b))
        assert np.abs(a - b).max(initial=0) <= tolerance + 1e-5, name
    if suffix == ".ply":
        assert same(fields, read)


def test_gsply_reads_what_we_write(tmp_path, rng):
    """A second reader: gsply reads our PLY exactly and our SPZ in SPZ's own frame."""
    gsply = pytest.importorskip("gsply")
    from splat_files.fields import from_gsdata

    fields = scene(rng)
    write_splat_file(fields, tmp_path / "s.ply")
    assert same(from_gsdata(gsply.plyread(tmp_path / "s.ply")), fields)
    write_splat_file(fields, tmp_path / "s.spz")
    theirs = flip_axes(from_gsdata(gsply.read_spz(tmp_path / "s.spz")))
    assert np.abs(theirs.means - fields.means).max() <= 2.0 ** -13
    assert np.abs(theirs.shN - fields.shN).max() <= 1 / 128 + 1e-6


def test_a_ply_keeps_its_comments_other_properties_and_doubles(tmp_path, rng):
    fields = scene(rng, 20, degree=1)
    names = ["x", "y", "z", "nx", "f_dc_0", "f_dc_1", "f_dc_2",
             *[f"f_rest_{i}" for i in range(9)], "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3", "label"]
    table = np.zeros(20, [(n, "<f8") for n in names[:-1]] + [("label", "u1")])
    columns = np.concatenate([fields.means, np.zeros((20, 1)), fields.sh0,
                              fields.shN.transpose(0, 2, 1).reshape(20, -1), fields.opacities[:,
                              None], fields.scales, fields.quats], 1)
    for name, column in zip(names, columns.T):
        table[name] = column
    table["label"] = np.arange(20)
    header = ("ply\nformat binary_little_endian 1.0\ncomment made by hand\nelement vertex 20\n"
              + "".join(f"property {'uchar' if n == 'label' else 'double'} {n}\n"
                        for n in names) + "end_header\n")
    (tmp_path / "d.ply").write_bytes(header.encode() + table.tobytes())
    read = read_splat_file(tmp_path / "d.ply")
    assert same(read, fields) and read.comments == ["made by hand"]
    assert np.array_equal(read.extras["label"], np.arange(20))
    again = read_splat_file(write_splat_file(read, tmp_path / "again.ply"))
    assert again.comments == read.comments and np.array_equal(again.extras["nx"], np.zeros(20))


def _ply(tmp_path, body_rows: int, declared: int, value: float = 0.5, name="h.ply") -> Path:
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = np.full((body_rows, len(names)), value, np.float32)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {declared}\n"
              + "".join(f"property float {n}\n" for n in names) + "end_header\n")
    path = tmp_path / name
    path.write_bytes(header.encode() + rows.tobytes())
    return path


def _gzip_spz(count: int, payload: bytes, version: int = 3) -> bytes:
    return gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, version, count, 0, 12, 0, 0)
                         + payload)


HOSTILE = {
    "a count that lies": (lambda t: _ply(t, 4, 10**12), "declares"),
    "a truncated body": (lambda t: _ply(t, 3, 4), "truncated"),
    "an ASCII PLY": (lambda t: _write(t / "a.ply", b"ply\nformat ascii 1.0\nend_header\n"),
                     "binary_little_endian"),
    "a list property": (lambda t: _write(t / "l.ply", b"ply\nformat binary_little_endian 1.0\n"
                        b"element face 1\nproperty list uchar int v\nend_header\n"),
                        "list properties"),
    "a header that never ends": (lambda t: _write(t / "e.ply", b"ply\n" + b"comment x\n" * 20000),
                                 "does not end"),
    "NaN": (lambda t: _ply(t, 4, 4, np.nan), "NaN or infinite"),
    "infinity": (lambda t: _ply(t, 4, 4, np.inf), "NaN or infinite"),
    "a logit of 1e30": (lambda t: _ply(t, 4, 4, 1e30), "beyond"),
    "zero quaternions": (lambda t: _ply(t, 4, 4, 0.0), "length zero"),
    "a .splat of part records": (lambda t: _write(t / "p.splat", b"\0" * 33), "whole records"),
    "an SPZ of 10^9 splats": (lambda t: _write(t / "c.spz", _gzip_spz(10**9, b"")),
                              "more than"),
    "an SPZ bomb": (lambda t: _write(t / "b.spz", _gzip_spz(1, b"\0" * (50 << 20))),
                    "inflates beyond"),
    "a truncated SPZ": (lambda t: _write(t / "t.spz", _gzip_spz(100, b"\0" * 100)), "truncated"),
    "a corrupt SPZ": (lambda t: _write(t / "z.spz", b"\x1f\x8b" + b"\xff" * 40), "corrupt"),
    "SPZ version 9": (lambda t: _write(t / "v.spz", _gzip_spz(1, b"\0" * 20, 9)), "version 9"),
    "a SOG that is no zip": (lambda t: _write(t / "n.sog", b"PK no zip"), "not a SOG"),
    "a SOG of lying images": (lambda t: _sog(t, 1000), "not of"),
    "a SOG of 10^9 splats": (lambda t: _sog(t, 10**9), "cannot hold"),
    "a .ksplat": (lambda t: _write(t / "k.ksplat", b"\0" * 64), "not read"),
}


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _sog(tmp_path: Path, count: int) -> Path:
    """A SOG bundle whose meta declares ``count`` splats, its images 4 x 4."""
    picture = tmp_path / "p.webp"
    Image.new("RGBA", (4, 4)).save(picture, lossless=True)
    files = {"means": ["m.webp"], "quats": ["m.webp"], "scales": ["m.webp"],
             "sh0": ["m.webp"]}
    path = tmp_path / "s.sog"
    with zipfile.ZipFile(path, "w") as bundle:
        bundle.writestr("meta.json", json.dumps(
            {"version": 2, "count": count, **{k: {"files": v} for k, v in files.items()}}))
        bundle.write(picture, "m.webp")
    return path


@pytest.mark.parametrize("case", list(HOSTILE))
def test_a_hostile_splat_file_is_refused_in_one_line(case, tmp_path, capsys):
    make, message = HOSTILE[case]
    path = make(tmp_path)
    with pytest.raises(InputError, match=message):
        read_splat_file(path)
    expect_error(decompose, [str(path), "-o", str(tmp_path / "out.npz")], message, capsys)
    assert not (tmp_path / "out.npz").exists()


@pytest.fixture
def decomposed(tmp_path, rng):
    """A degree-3 PLY of 300 splats and its splat stack (K = 5), from the command line."""
    path = write_splat_file(scene(rng), tmp_path / "scene.ply")
    assert decompose([str(path), "-k", "5", "-o", str(tmp_path / "scene.splats.npz")]) == 0
    return path, tmp_path / "scene.splats.npz"


def test_a_splat_stack_holds_the_file_and_weights_on_the_simplex(decomposed):
    path, stack_path = decomposed
    stack = read_splat_stack(stack_path)
    assert same(stack.fields, read_splat_file(path)) and stack.palette.shape == (5, 3)
    assert np.isfinite(stack.weights).all() and stack.weights.min() >= -1e-6
    assert np.allclose(stack.weights.sum(1), 1, atol=1e-5)
    assert (stack_path.parent / "scene.splats.palette.json").is_file()


@pytest.mark.parametrize("suffix", [".ply", ".spz", ".compressed.ply", ".splat"])
def test_the_unedited_palette_gives_back_the_file(decomposed, suffix, tmp_path):
    """Exactly for the PLY; through the same format's quantisation for the others."""
    path, stack_path = decomposed
    out = tmp_path / f"same{suffix}"
    assert recolor([str(stack_path), "--palette", str(tmp_path / "scene.splats.palette.json"),
                    "-o", str(out)]) == 0
    if suffix == ".ply":
        assert same(read_splat_file(out), read_splat_file(path))
    else:
        direct = read_splat_file(write_splat_file(read_splat_file(path), tmp_path / f"d{suffix}"))
        assert same(read_splat_file(out), direct)


def test_a_selected_edit_leaves_every_other_splat_bit_identical(decomposed, tmp_path):
    path, stack_path = decomposed
    stack = read_splat_stack(stack_path)
    edited = stack.palette.copy()
    edited[0] = [1.0, 0.0, 0.0]
    with open(tmp_path / "edit.json", "w") as file:
        write_palette_json(file, edited)
    for residual in ("follow", "keep", "scale"):
        out = tmp_path / f"edit-{residual}.ply"
        assert recolor([str(stack_path), "--palette", str(tmp_path / "edit.json"),
                        "--select-colour", "0", "--threshold", "0.3", "--residual", residual,
                        "-o", str(out)]) == 0
        read, original = read_splat_file(out), stack.fields
        inside = stack.weights[:, 0] >= 0.3
        assert 0 < inside.sum() < len(stack)
        for name in ATTRIBUTES:
            assert np.array_equal(getattr(read, name)[~inside], getattr(original, name)[~inside])
        change = stack.weights[inside].astype(np.float64) @ (edited - stack.palette)
        assert np.allclose(read.colours()[inside] - original.colours()[inside], change,
                           atol=1e-5)
        assert np.array_equal(read.shN[inside], original.shN[inside]) == (residual == "keep")


def test_harmonising_a_splat_stack_writes_a_splat_file(decomposed, tmp_path, capsys):
    _, stack_path = decomposed
    assert harmonize([str(stack_path), "--template", "best", "-o", str(tmp_path / "h.spz")]) == 0
    assert len(read_splat_file(tmp_path / "h.spz")) == 300
    capsys.readouterr()
    expect_error(harmonize, [str(stack_path), "--template", "all", "-o",
                             str(tmp_path / "h2.ply")], "one template", capsys)


def test_splat_commands_refuse_what_is_for_images(decomposed, tmp_path, capsys):
    path, stack_path = decomposed
    expect_error(decompose, [str(path), "--layers", str(tmp_path / "l")], "for images", capsys)
    expect_error(decompose, [str(path), str(path)], "on its own", capsys)
    expect_error(recolor, [str(stack_path), "--palette", str(tmp_path / "scene.splats.palette"
                           ".json"), "--mask", str(path), "-o", str(tmp_path / "x.ply")],
                 "for images", capsys)
    expect_error(recolor, [str(stack_path), "--palette", str(tmp_path / "scene.splats.palette"
                           ".json"), "-o", str(tmp_path / "x.sog")], "written as", capsys)


def test_a_stack_with_weights_off_the_simplex_is_refused(decomposed, tmp_path):
    _, stack_path = decomposed
    with np.load(stack_path) as npz:
        data = dict(npz)
    data["weights"] = data["weights"] * 2
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(InputError, match="simplex"):
        read_splat_stack(tmp_path / "bad.npz")


def test_degenerate_colour_sets_decompose(rng):
    """One colour, and every splat on one line of colours: weights stay on the simplex."""
    for colours in (np.full((50, 3), 0.3), np.linspace(0, 1, 50)[:, None] * [1, 0.5, 0.2]):
        fields = scene(rng, 50, 0)
        fields.sh0 = ((colours - 0.5) / SH_C0).astype(np.float32)
        stack = decompose_splats(fields, 4)
        assert np.isfinite(stack.weights).all() and np.allclose(stack.weights.sum(1), 1,
                                                                   atol=1e-5)
        assert same(stack.recoloured(stack.palette), fields)
