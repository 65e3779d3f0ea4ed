"""A fuzzing harness for every reader of a file we did not write.

Valid small files of each kind are mutated (truncated, bytes flipped or inserted, NPZ
headers and zip directories that lie, dtypes swapped, JSON values replaced by huge, NaN,
negative, deeply nested or wrongly typed ones, files replaced by links out of their folder)
and read in a child process whose address space may grow by at most ``hostile.MEMORY_CAP``.
Checkpoints get their tensors' dtypes, types, counts and shapes changed; binary COLMAP
models and checkpoints get doubles set to NaN, infinity or 10^300; a splat run is read and
exported to PLY and SPZ (the writers' round trips under hostile input); photos turned by
their EXIF orientation go through training's and the palette's readers.
The contract: the read succeeds, or it ends in one line on stderr and exit code 2; never a
traceback, never an allocation beyond the cap, nothing written outside the output folder.
``make test`` runs a few hundred examples; ``pytest -m slow tests/test_fuzz.py`` a long run.
"""

from __future__ import annotations

import io
import json
import shutil
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from palette_core.cli import run_cli
from palette_core.edit_file import read_edits, write_edits
from palette_core.palette_file import read_palette_json, write_palette_json
from palette_core.selection import LocalEdit, Selection
from palette_core.stack import read_stack, write_stack

from .hostile import (
    PALETTE,
    K,
    blender_capture,
    capped,
    colmap_capture,
    nerfstudio_capture,
    npy_bytes,
    small_bake,
    small_render,
    small_stack,
    turned_capture,
    write_photos,
    zip_bytes,
)

torch = pytest.importorskip("torch")
pycolmap = pytest.importorskip("pycolmap")

from nerf_stage.data import colmap  # noqa: E402
from nerf_stage.data.dataset import load_dataset  # noqa: E402

#: A tiny model reads in milliseconds; one whose counts a mutation broke is stopped sooner.
colmap.READ_SECONDS = 2
from nerf_stage.edit.editing import read_render  # noqa: E402
from nerf_stage.edit.regions import read_regions  # noqa: E402
from nerf_stage.splats import read_splats  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402


def read_npz_stack(folder: Path) -> None:
    [np.asarray(w) for w in read_stack(folder / "w.npz").weights]


def read_zarr_stack(folder: Path) -> None:
    [np.asarray(w) for w in read_stack(folder / "w.zarr").weights]


def read_edit_file(folder: Path) -> None:
    from palette_core.recolor import recolor_stack

    stack = read_stack(folder / "w.npz")
    recolor_stack(stack, stack.palette, folder / "out", force=True,
                  edits=read_edits(folder / "e.json", stack))


def read_bake(folder: Path) -> None:
    read_splats(folder / "b.splat.npz").colours(PALETTE)


def read_weight_render(folder: Path) -> None:
    read_render(folder / "render.npz").recolor()


def read_region_file(folder: Path) -> None:
    read_regions(folder / "r.json")


def read_palette_file(folder: Path) -> None:
    read_palette_json(folder / "p.json", K)


def read_run(folder: Path) -> None:
    load_run(folder / "run")


def export_run(folder: Path) -> None:
    """A splat run read and exported as each format (``nerf-stage export``, without the bake
    it keeps in its folder)."""
    from nerf_stage.splats import export_splats

    splats = load_run(folder / "run").splats({})
    for suffix in (".ply", ".spz"):
        export_splats(splats, folder / "out" / f"s{suffix}")


def read_turned_capture(folder: Path) -> None:
    """Training's reader and the palette's on photos turned by their EXIF orientation."""
    from nerf_stage.data.dataset import join_weights
    from palette_core.decompose import decompose

    dataset = load_dataset(folder)
    join_weights(dataset, decompose([folder / "images"], k=4).stack)


READERS = {"npz-stack": read_npz_stack, "zarr-stack": read_zarr_stack, "bake": read_bake,
           "render": read_weight_render, "edits": read_edit_file, "regions": read_region_file,
           "palette": read_palette_file, "nerfstudio": load_dataset, "blender": load_dataset,
           "colmap-text": load_dataset, "colmap-binary": load_dataset, "run": read_run,
           "colmap-points": load_dataset, "splat-run": export_run,
           "turned": read_turned_capture}
KINDS = list(READERS)


@pytest.fixture(scope="module")
def originals(tmp_path_factory, scene_run, splat_scene_run):
    """One folder per kind of file we read (``READERS``), each holding a valid small one."""
    root = tmp_path_factory.mktemp("originals")
    rng = np.random.default_rng(7)
    stack = small_stack(rng)

    def make_edits(folder):
        write_stack(stack, folder / "w.npz")
        masks = folder / "drawn"
        write_photos(masks, rng, 0)
        for name, w in zip(stack.names, stack.weights):
            Image.fromarray(rng.integers(0, 256, w.shape[:2], dtype=np.uint8)).save(masks / name)
        write_edits(folder / "e.json", stack,
                    [LocalEdit(Selection(mask=masks, feather=1.0), PALETTE[::-1])])
        shutil.rmtree(masks)

    makers = {
        "npz-stack": lambda f: write_stack(stack, f / "w.npz"),
        "zarr-stack": lambda f: write_stack(stack, f / "w.zarr"),
        "bake": lambda f: small_bake(f / "b.splat.npz", rng),
        "render": lambda f: small_render(f / "render.npz", rng),
        "edits": make_edits,
        "regions": lambda f: (f / "r.json").write_text(json.dumps({"regions": [
            {"shape": "box", "centre": [0, 0, 0], "half": [1, 1, 1]},
            {"shape": "colour", "colour": 1, "threshold": 0.4}]})),
        "palette": lambda f: write_palette_json(f / "p.json", PALETTE),
        "nerfstudio": lambda f: nerfstudio_capture(f, rng),
        "blender": lambda f: blender_capture(f, rng),
        "colmap-text": lambda f: colmap_capture(f, rng, binary=False),
        "colmap-binary": lambda f: colmap_capture(f, rng, binary=True),
        "run": lambda f: shutil.copytree(scene_run, f / "run"),
        "colmap-points": lambda f: colmap_capture(f, rng, binary=True, points="".join(
            f"{i + 1} {x:.3f} {y:.3f} {z:.3f} 200 100 50 0.5\n"
            for i, (x, y, z) in enumerate(rng.uniform(-1, 1, (4, 3))))),
        "splat-run": lambda f: shutil.copytree(splat_scene_run, f / "run"),
        "turned": lambda f: turned_capture(f, rng),
    }
    for kind, make in makers.items():
        (root / kind).mkdir()
        make(root / kind)
    return root


# --- mutations ------------------------------------------------------------------------------

NESTED: list = []
for _ in range(500):
    NESTED = [NESTED]
HOSTILE_VALUES = [10**12, -1, 0, 1e308, float("nan"), float("inf"), "x" * 300, None, True, {},
                  [], NESTED,
                  {"shape": "box"}, "../../../etc/hostname", "/etc/hostname"]
DTYPES = ["<f8", "<f2", ">i8", "<u1", "|b1", "<U7", "|V8", "|O", "<c16", "<M8[s]"]
#: What a checkpoint's tensor may become: another dtype, a list, a view repeating one row
#: 10^9 times, rows dropped or added, another shape, a plain number.
TENSOR_CHANGES = ["half", "double", "bfloat16", "int64", "bool", "complex", "list", "repeat",
                  "drop-rows", "add-rows", "flatten", "scalar", "number", "nan", "none"]

MUTATION = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(1, 255)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=12)),
    st.tuples(st.just("json"), st.integers(0, 10**6), st.sampled_from(HOSTILE_VALUES)),
    st.tuples(st.just("shape"), st.integers(0, 100), st.sampled_from(
        [(10**12,), (10**6, 10**6), (), (0,), (3, 10**9, 4), (2**62, 2)])),
    st.tuples(st.just("dtype"), st.integers(0, 100), st.sampled_from(DTYPES)),
    st.tuples(st.just("directory"), st.integers(0, 100), st.sampled_from([0, 10**12, 2**63])),
    st.tuples(st.just("link"), st.integers(0, 10**6)),
    st.tuples(st.just("tensor"), st.integers(0, 100), st.sampled_from(TENSOR_CHANGES)),
    st.tuples(st.just("double"), st.floats(0, 1), st.sampled_from(
        [float("nan"), float("inf"), -float("inf"), 1e300])),
)


def mutate(folder: Path, secret: Path, which: int, mutation: tuple) -> None:
    """Apply ``mutation`` to file number ``which`` (modulo their count) under ``folder``, or
    link it to ``secret`` outside; a structured mutation that does not fit the file (JSON
    on an NPZ, a header lie on a file already broken) changes its bytes instead."""
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    path = files[which % len(files)]
    kind, *args = mutation
    if kind == "link":
        path.unlink()
        path.symlink_to(secret)
        return
    data = path.read_bytes()
    try:
        if kind == "tensor":
            _tensor_changed(path, *args)
            return
        if kind == "double":
            at = int(args[0] * max(len(data) - 8, 0)) // 8 * 8
            data = data[:at] + struct.pack("<d", args[1]) + data[at + 8:]
        elif kind == "json":
            data = json.dumps(_replaced(json.loads(data), *args)).encode()
        elif kind in ("shape", "dtype", "directory"):
            data = _npz_lie(data, kind, *args)
        else:
            data = _bytes_changed(data, kind, *args)
    except Exception:  # noqa: BLE001 - not JSON, not a sound NPZ: change bytes
        data = _bytes_changed(data, "insert", 0.5, str(args[-1]).encode())
    path.write_bytes(data)


def _tensor_changed(path: Path, index: int, change: str) -> None:
    """The checkpoint at ``path`` with tensor ``index`` of its ``field`` (modulo their count)
    changed by ``change`` (``TENSOR_CHANGES``); ValueError for a file that is no checkpoint."""
    if path.suffix != ".pt":
        raise ValueError("not a checkpoint")
    state = torch.load(path, weights_only=True)
    field = state["field"]
    name = sorted(field)[index % len(field)]
    t = field[name]
    field[name] = {
        "half": lambda: t.half(), "double": lambda: t.double(), "bfloat16": lambda: t.bfloat16(),
        "int64": lambda: t.long(), "bool": lambda: t.bool(),
        "complex": lambda: t.to(torch.complex64), "list": lambda: t.tolist(),
        "repeat": lambda: t.reshape(-1)[:1].expand(10**9) if t.ndim < 2 else
        t[:1].expand(10**9, *t.shape[1:]),
        "drop-rows": lambda: t[: len(t) // 2] if t.ndim else t,
        "add-rows": lambda: torch.cat([t, t]) if t.ndim else t,
        "flatten": lambda: t.reshape(-1), "scalar": lambda: t.reshape(-1)[0].clone(),
        "number": lambda: 1.0, "nan": lambda: t.float().fill_(float("nan")), "none": lambda: None,
    }[change]()
    torch.save(state, path)


def _bytes_changed(data: bytes, kind: str, where: float, arg=None) -> bytes:
    """``data`` truncated, with a byte flipped by ``arg``, or with bytes ``arg`` inserted, at
    fraction ``where`` of its length."""
    at = int(where * len(data))
    if kind == "truncate":
        return data[:at]
    if kind == "flip" and data:
        at = min(at, len(data) - 1)
        return data[:at] + bytes([data[at] ^ arg]) + data[at + 1:]
    return data[:at] + arg + data[at:]


def _replaced(value, index: int, new):
    """``value`` (parsed JSON) with its ``index``-th node (modulo their count) set to ``new``."""
    places = []

    def walk(node):
        items = node.items() if isinstance(node, dict) else enumerate(node) \
            if isinstance(node, list) else ()
        for key, child in items:
            places.append((node, key))
            walk(child)

    walk(value)
    if not places:
        return new
    node, key = places[index % len(places)]
    node[key] = new
    return value


def _npz_lie(data: bytes, kind: str, index: int, arg) -> bytes:
    """NPZ ``data`` with member ``index``'s header declaring shape or dtype ``arg``, or its
    directory entry claiming ``arg`` bytes."""
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        members = {name: z.read(name) for name in z.namelist()}
    name = sorted(members)[index % len(members)]
    array = np.load(io.BytesIO(members[name]), allow_pickle=False)
    claimed = {}
    if kind == "shape":  # the directory agrees with the header: both lie
        members[name] = npy_bytes(array, shape=arg)
        declared = int(np.prod(arg, dtype=np.float64)) * array.dtype.itemsize
        claimed[name] = min(len(members[name]) - array.nbytes + declared, 2**63 - 1)
    elif kind == "dtype":
        members[name] = npy_bytes(array, dtype=arg)
    else:
        claimed[name] = arg
    return zip_bytes(members, claimed)


# --- the contract ---------------------------------------------------------------------------

def command(kind: str, folder: Path) -> int:
    """Read ``folder`` with ``READERS[kind]`` as a command would: exit code 0, or 2 with one
    line for bad input."""
    def body() -> int:
        READERS[kind](folder)
        return 0
    return run_cli("reader", body)


def listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def meets_contract(originals: Path, kind: str, tmp_path_factory, mutations) -> None:
    work = tmp_path_factory.mktemp("fuzz")
    secret = work / "secret.png"
    Image.new("RGB", (6, 8), (1, 2, 3)).save(secret)
    folder = work / kind
    shutil.copytree(originals / kind, folder, symlinks=True)
    for which, mutation in mutations:
        mutate(folder, secret, which, mutation)
    before = listing(work)
    code, err = capped(command, kind, folder)
    lines = err.strip().splitlines()
    assert code == 0 or (code == 2 and len(lines) == 1), (kind, mutations, code, err[-3000:])
    written = {p for p in listing(work) - before if not p.startswith(f"{kind}/out")}
    assert not written, (kind, mutations, written)
    shutil.rmtree(work)


MUTATIONS = st.lists(st.tuples(st.integers(0, 10**6), MUTATION), min_size=1, max_size=3)


def test_valid_originals_are_read(originals):
    for kind in KINDS:
        code, err = capped(command, kind, originals / kind)
        assert code == 0, (kind, err)


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutations=MUTATIONS)
def test_mutated_files_meet_the_contract(originals, tmp_path_factory, kind, mutations):
    meets_contract(originals, kind, tmp_path_factory, mutations)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutations=MUTATIONS)
def test_mutated_files_meet_the_contract_long(originals, tmp_path_factory, kind, mutations):
    meets_contract(originals, kind, tmp_path_factory, mutations)


@pytest.mark.parametrize("change", TENSOR_CHANGES)
def test_every_change_of_a_checkpoint_tensor_meets_the_contract(originals, tmp_path_factory,
                                                                change):
    files = sorted(p for p in (originals / "splat-run").rglob("*") if p.is_file())
    checkpoint = next(i for i, p in enumerate(files) if p.suffix == ".pt")
    for index in (0, 3):  # the first tensor (means) and another
        meets_contract(originals, "splat-run", tmp_path_factory,
                       [(checkpoint, ("tensor", index, change))])
