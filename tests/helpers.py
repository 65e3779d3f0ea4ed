"""Assertions shared by the tests."""

import struct
import zlib

import numpy as np
from PIL import Image

from palette_core.stack import WeightStack, write_stack


def weight_invariants(weights, palette, colours):
    """Assert the invariants every weight vector satisfies (docs/formats.md)."""
    from palette_core.constants import WEIGHT_MIN, WEIGHT_SUM_TOL

    weights = np.asarray(weights, np.float64)
    assert not np.isnan(weights).any()
    assert weights.min() >= WEIGHT_MIN
    assert np.abs(weights.sum(-1) - 1).max() < WEIGHT_SUM_TOL
    if colours is not None:
        assert np.abs(weights @ palette - colours).max() < 1e-6


def expect_error(main, argv, message, capsys):
    """Assert that a CLI exits 2 with one line on stderr containing ``message``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def stack_file(path, names=("a.png",), weights=None, **arrays):
    """A valid additive stack of 2x2 images, with arrays replaced by ``arrays``."""
    weights = weights or [np.full((2, 2, 4), 0.25, np.float32)] * len(names)
    write_stack(WeightStack(np.eye(4, 3, dtype=np.float32), list(weights), list(names)), path)
    if arrays:
        with np.load(path) as npz:
            data = dict(npz)
        data.update({key.rstrip("_"): value for key, value in arrays.items()})
        np.savez(path, **data)
    return path


def png_header_only(path, width, height):
    """A PNG whose header declares width x height and whose data is a few bytes."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + chunk(b"IEND", b""))
    return path


PALETTE = np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.1, 0.2, 0.9], [0.95, 0.9, 0.2]])


def tiny_stack(path, rng, n=3):
    """A weight stack of ``n`` small random images over ``PALETTE``, written to ``path``."""
    weights = [rng.dirichlet(np.ones(4), size=(6 + i, 8)).astype(np.float32) for i in range(n)]
    write_stack(WeightStack(PALETTE, weights, [f"p{i}.png" for i in range(n)], "mvc"), path)
    return path


def llff_capture(folder, rng, n=10, folder_name="images_2"):
    """An LLFF capture of ``n`` forward-facing 8 x 6 photos in ``folder_name``, whose
    ``poses_bounds.npy`` describes full-size 16 x 12 photos; the true OpenGL poses."""
    from nerf_stage.data.cameras import look_at

    poses = np.array([look_at([0.3 * np.cos(a), 0.2 * np.sin(a), 4.0], [0.0, 0.0, 0.0])
                      for a in np.linspace(0, 2 * np.pi, n, endpoint=False)])
    rows = []
    for pose in poses:
        llff = np.stack([-pose[:3, 1], pose[:3, 0], pose[:3, 2], pose[:3, 3],
                         [12.0, 16.0, 20.0]], 1)  # x down, y right, z back; then h, w, f
        rows.append(np.concatenate([llff.ravel(), [2.0 + rng.uniform(), 9.0]]))
    np.save(folder / "poses_bounds.npy", np.array(rows))
    (folder / folder_name).mkdir()
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)).save(
            folder / folder_name / f"IMG_{i:04d}.png")
    return poses, np.array(rows)[:, 15:]
