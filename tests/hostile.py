"""Hostile files for the security tests and the fuzzing harness: NPZ members whose headers
lie, zip directories that lie about sizes, and a child process under a memory cap in which
a reader meets them."""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import resource
import struct
import sys
import tempfile
import traceback
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

from palette_core.basis import Basis
from palette_core.stack import WeightStack


def npy_bytes(array: np.ndarray, shape: tuple | None = None, dtype: str | None = None) -> bytes:
    """``array`` as a ``.npy`` file, its header declaring ``shape`` and ``dtype`` instead when
    given (the data stays ``array``'s bytes)."""
    header = {"descr": dtype or np.lib.format.dtype_to_descr(array.dtype),
              "fortran_order": False, "shape": tuple(array.shape if shape is None else shape)}
    out = io.BytesIO()
    np.lib.format.write_array_header_2_0(out, header)
    return out.getvalue() + np.ascontiguousarray(array).tobytes()


def zip_bytes(members: dict[str, bytes], claimed: dict[str, int] | None = None,
              deflate: bool = False) -> bytes:
    """A zip file of ``members`` made by hand (ZIP64 sizes always), whose directory claims the
    uncompressed sizes in ``claimed`` instead of the true ones."""
    claimed = claimed or {}
    body, directory = bytearray(), bytearray()
    for name, data in members.items():
        stored = zlib.compress(data)[2:-4] if deflate else data
        method, crc, raw = (8 if deflate else 0), zlib.crc32(data), name.encode()
        size = claimed.get(name, len(data))
        extra = struct.pack("<HHQQ", 1, 16, size, len(stored))
        offset = len(body)
        body += struct.pack("<IHHHHHIIIHH", 0x04034B50, 45, 0, method, 0, 0, crc,
                            0xFFFFFFFF, 0xFFFFFFFF, len(raw), len(extra)) + raw + extra + stored
        extra = struct.pack("<HHQQQ", 1, 24, size, len(stored), offset)
        directory += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, method, 0, 0, crc,
                                 0xFFFFFFFF, 0xFFFFFFFF, len(raw), len(extra), 0, 0, 0, 0,
                                 0xFFFFFFFF) + raw + extra
    start, n = len(body), len(members)
    end = struct.pack("<IQHHIIQQQQ", 0x06064B50, 44, 45, 45, 0, 0, n, n, len(directory), start)
    locator = struct.pack("<IIQI", 0x07064B50, 0, start + len(directory), 1)
    tail = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    return bytes(body + directory + end + locator + tail)


def lying_npz(source: Path, target: Path, key: str, rows: int = 10**12) -> None:
    """``source`` NPZ rewritten as ``target``, member ``key``'s header declaring ``rows`` rows
    and the zip directory claiming the bytes that would take."""
    with np.load(source, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    members = {f"{name}.npy": npy_bytes(array) for name, array in arrays.items()}
    array = arrays[key]
    shape = (rows, *array.shape[1:])
    data = npy_bytes(array, shape)
    members[f"{key}.npy"] = data
    declared = rows * int(np.prod(array.shape[1:], dtype=np.int64)) * array.dtype.itemsize
    header = len(data) - array.nbytes
    target.write_bytes(zip_bytes(members, {f"{key}.npy": header + declared}))


#: Address space a reader may add in ``capped``: far more than any tiny file needs, far less
#: than a lying header asks for.
MEMORY_CAP = 1 << 30
#: Seconds a reader may take on a tiny file before ``capped`` stops it.
CHILD_SECONDS = 60


def capped(target, *args, cap: int = MEMORY_CAP) -> tuple[int, str]:
    """Run ``target(*args) -> int`` (a command; module-level, so that it pickles) in a child
    process whose address space may grow by at most ``cap`` bytes; (its exit code, what it
    wrote to stderr). A Python exception in the child is exit code 99 with its traceback.

    Children come from a fork server: forking this process, whose thread pools (zarr's event
    loop, torch's) would not exist in the child, can deadlock it."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([target.__module__])  # imported once, in the server
    with tempfile.NamedTemporaryFile("w+") as err:
        child = context.Process(target=_child, args=(err.name, cap, target, args))
        child.start()
        child.join(CHILD_SECONDS)
        if child.is_alive():
            child.kill()
            child.join()
            return -9, f"still running after {CHILD_SECONDS} s\n" + Path(err.name).read_text()
        return child.exitcode, Path(err.name).read_text()


def _child(err: str, cap: int, target, args) -> None:
    code = 99
    try:
        with open(err, "w") as stream:
            os.dup2(stream.fileno(), 2)
        sys.stderr = os.fdopen(2, "w", closefd=False)
        used = _address_space()
        resource.setrlimit(resource.RLIMIT_AS, (used + cap, used + cap))
        code = target(*args)
    except BaseException:
        traceback.print_exc()
    finally:
        sys.stderr.flush()
        os._exit(code if isinstance(code, int) else 98)


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def check_refused(code: int, err: str) -> None:
    """The contract for a hostile input: exit code 2 and one line on stderr, no traceback."""
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err[-3000:])


# --- valid small files of each kind -------------------------------------------------------

K = 4
PALETTE = np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.1, 0.2, 0.9], [0.9, 0.9, 0.8]])


def small_stack(rng) -> WeightStack:
    weights = [rng.dirichlet(np.ones(K), (6, 5)).astype(np.float32) for _ in range(2)]
    return WeightStack(PALETTE.astype(np.float32), weights, ["a.png", "b.png"])


def write_photos(folder: Path, rng, n: int = 3, size=(8, 6)) -> list[str]:
    folder.mkdir(parents=True)
    names = [f"f{i}.png" for i in range(n)]
    for name in names:
        Image.fromarray(rng.integers(0, 256, (*size[::-1], 3), dtype=np.uint8)).save(
            folder / name)
    return names


def _poses(n: int) -> list[np.ndarray]:
    poses = []
    for i in range(n):
        pose = np.eye(4)
        pose[:3, 3] = [0.3 * i, 0.0, 2.0]
        poses.append(pose)
    return poses


def nerfstudio_capture(folder: Path, rng, lens: dict | None = None, size=(8, 6)) -> Path:
    """A nerfstudio capture of three random photos of ``size``, the camera's focal length
    its width, its lens ``lens`` (nerfstudio's keys) or none."""
    w, h = size
    names = write_photos(folder / "images", rng, size=size)
    frames = [{"file_path": f"images/{name}", "transform_matrix": pose.tolist()}
              for name, pose in zip(names, _poses(len(names)))]
    (folder / "transforms.json").write_text(json.dumps(
        {"w": w, "h": h, "fl_x": float(w), "fl_y": float(w), "cx": w / 2, "cy": h / 2,
         **(lens or {"k1": 0.0}), "frames": frames}))
    return folder


def turned_capture(folder: Path, rng) -> Path:
    """A nerfstudio capture of three 8 x 6 JPEGs stored a quarter turn off with EXIF
    orientation 6, as phones take them upright."""
    (folder / "images").mkdir(parents=True)
    exif = Image.Exif()
    exif[0x0112] = 6
    names = []
    for i in range(3):
        names.append(f"images/f{i}.jpg")
        stored = rng.integers(0, 256, (8, 6, 3), dtype=np.uint8)
        Image.fromarray(stored).save(folder / names[-1], quality=95, exif=exif)
    frames = [{"file_path": name, "transform_matrix": pose.tolist()}
              for name, pose in zip(names, _poses(3))]
    (folder / "transforms.json").write_text(json.dumps(
        {"w": 8, "h": 6, "fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "frames": frames}))
    return folder


def blender_capture(folder: Path, rng) -> Path:
    names = write_photos(folder / "train", rng)
    frames = [{"file_path": f"train/{name[:-4]}", "transform_matrix": pose.tolist()}
              for name, pose in zip(names, _poses(len(names)))]
    (folder / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.8, "frames": frames}))
    return folder


def colmap_capture(folder: Path, rng, binary: bool, camera: str = "SIMPLE_RADIAL 8 6 8.0 4.0 "
                   "3.0 0.0", size=(8, 6), points: str = "") -> Path:
    """A COLMAP capture (text or ``binary`` model) of three random photos of ``size`` taken
    by ``camera`` (a line of COLMAP's cameras.txt after the camera id), with ``points``
    (lines of COLMAP's points3D.txt)."""
    names = write_photos(folder / "images", rng, size=size)
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(f"1 {camera}\n")
    (model / "images.txt").write_text("".join(
        f"{i + 1} 1 0 0 0 {-0.3 * i} 0 2 1 {name}\n\n" for i, name in enumerate(names)))
    (model / "points3D.txt").write_text(points)
    if binary:
        import pycolmap

        reconstruction = pycolmap.Reconstruction(model)
        for name in ("cameras.txt", "images.txt", "points3D.txt"):
            (model / name).unlink()
        reconstruction.write_binary(model)
    return folder


def small_render(path: Path, rng) -> Path:
    """A weight render of one 4x3 view with a sample behind each pixel."""
    from nerf_stage.edit.editing import WeightRender, write_render
    from nerf_stage.render.samples import PixelSamples

    weights = rng.dirichlet(np.ones(K), (1, 3, 4)).astype(np.float32)
    samples = PixelSamples(np.arange(12, dtype=np.int64),
                           rng.normal(size=(12, 3)).astype(np.float32),
                           rng.uniform(0, 1, 12).astype(np.float32))
    write_render(WeightRender(weights, np.ones((1, 3, 4), np.float32), ["v0"], PALETTE,
                              Basis.ADDITIVE, 1, np.ones(3), {}, samples), path)
    return path


def small_bake(path: Path, rng) -> Path:
    from nerf_stage.splats import Splats, write_splats

    n = 20
    q = rng.normal(size=(n, 4))
    write_splats(Splats(rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                        rng.uniform(0.05, 0.2, (n, 3)).astype(np.float32),
                        (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                        rng.uniform(0.3, 0.9, n).astype(np.float32),
                        rng.dirichlet(np.ones(K), n).astype(np.float32), PALETTE,
                        Basis.ADDITIVE, 1, np.ones(3), {"cell": 0.1}), path)
    return path
