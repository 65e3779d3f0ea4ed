"""NPZ weight stack format v1: round trips and validation."""

import json
import struct
import zipfile

import numpy as np
import pytest

from harmonize.cli import main as harmonize
from palette_core import (
    InputError,
    WeightStack,
    read_stack,
    transport_basis,
    weights_to_rgb,
    write_stack,
)
from palette_core.cli import decompose, recolor
from palette_core.stack import FLOAT16_SUM_TOL

from .helpers import expect_error, stack_file


def make_stack(rng, shapes=((4, 5), (4, 5)), k=4):
    weights = [rng.dirichlet(np.ones(k), size=s).astype(np.float32) for s in shapes]
    names = [f"img{i}.png" for i in range(len(shapes))]
    return WeightStack(rng.random((k, 3)).astype(np.float32), weights, names,
                       hull_faces=np.array([[0, 1, 2], [0, 2, 3]]), meta={"k": k})


@pytest.mark.parametrize("shapes", [((4, 5), (4, 5)), ((4, 5), (3, 7), (1, 1))])
@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_round_trip(tmp_path, rng, shapes, dtype):
    stack = make_stack(rng, shapes)
    write_stack(stack, tmp_path / "s.npz", dtype)
    with np.load(tmp_path / "s.npz", allow_pickle=False) as raw:
        assert str(raw["format"]) == "palette-weights/1"
        assert ("weights" in raw.files) == (len(set(shapes)) == 1)
    back = read_stack(tmp_path / "s.npz")
    assert back.names == stack.names and back.meta == {"k": 4}
    np.testing.assert_array_equal(back.palette, stack.palette)
    for a, b in zip(back.weights, stack.weights):
        assert a.dtype == np.dtype(dtype)
        np.testing.assert_allclose(a, b, atol=1e-3 if dtype == "float16" else 0)


def corrupt(path, **changes):
    with np.load(path, allow_pickle=False) as raw:
        data = {key: raw[key] for key in raw.files}
    for key, value in changes.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    np.savez(path, **data)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"format": np.array("other/2")}, "format"),
        ({"palette": np.zeros((4, 2), np.float32)}, "palette must have shape"),
        ({"palette": np.full((4, 3), 2.0, np.float32)}, r"palette values"),
        ({"basis": np.array("mystery")}, "basis"),
        ({"order": np.array(2)}, "additive stack has order 1"),
        ({"names": None}, "missing key 'names'"),
        ({"weights": np.zeros((2, 4, 5, 3), np.float32)}, "weights of img0.png"),
        ({"hull_faces": np.array([[0, 1, 9]])}, "hull_faces index"),
        ({"meta": np.array("{not json")}, "meta is not valid JSON"),
    ],
)
def test_validation_names_the_problem(tmp_path, rng, changes, message):
    path = tmp_path / "s.npz"
    write_stack(make_stack(rng), path)
    corrupt(path, **changes)
    with pytest.raises(InputError, match=message):
        read_stack(path)


def test_not_an_npz(tmp_path):
    (tmp_path / "x.npz").write_text("hello")
    with pytest.raises(InputError, match="not a readable NPZ"):
        read_stack(tmp_path / "x.npz")
    with pytest.raises(InputError, match="does not exist"):
        read_stack(tmp_path / "missing.npz")


def test_transport_basis_order_and_recolour(rng):
    palette = rng.random((3, 3))
    terms = transport_basis(palette, 2)
    assert len(terms) == 10  # C(3 + 2, 2)
    np.testing.assert_array_equal(terms[0], 1.0)
    np.testing.assert_array_equal(terms[1:4], palette)
    np.testing.assert_allclose(terms[4], palette[0] ** 2)  # (0, 0)
    np.testing.assert_allclose(terms[5], palette[0] * palette[1])  # (0, 1)
    np.testing.assert_allclose(terms[9], palette[2] ** 2)  # (2, 2)
    weights = rng.random((5, 10))
    np.testing.assert_allclose(weights_to_rgb(weights, palette, "transport", 2), weights @ terms)
    with pytest.raises(InputError, match="channels"):
        weights_to_rgb(weights, palette)


def test_meta_is_json(tmp_path, rng):
    write_stack(make_stack(rng), tmp_path / "s.npz")
    with np.load(tmp_path / "s.npz", allow_pickle=False) as raw:
        assert json.loads(str(raw["meta"])) == {"k": 4}


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


def test_duplicate_names_in_a_stack(tmp_path):
    with pytest.raises(InputError, match="distinct"):
        read_stack(stack_file(tmp_path / "s.npz", names=["a.png", "a.png"]))


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


def test_float16_sums(photo_dir, tmp_path):
    assert decompose.main([str(photo_dir), "-k", "6", "--dtype", "float16",
                           "-o", str(tmp_path / "w.npz")]) == 0
    for w in read_stack(tmp_path / "w.npz").weights:
        assert np.abs(w.astype(np.float32).sum(-1) - 1).max() <= FLOAT16_SUM_TOL
