"""One image reader for every command: decompose, training, masks and poses see the same
pixels for the same file (EXIF orientation, 16-bit, palette images, alpha, colour profile)."""

import json
import struct

import numpy as np
import pytest
from PIL import Image, ImageCms

from palette_core.io import image_size, load_image

torch = pytest.importorskip("torch")

from nerf_stage.data.dataset import join_weights, load_dataset  # noqa: E402
from palette_core.cli import decompose  # noqa: E402
from palette_core.stack import read_stack  # noqa: E402

from .hostile import _poses  # noqa: E402


def _turned(path, upright: np.ndarray, quality: int | None = None) -> None:
    """Save ``upright`` (H, W, C) stored a quarter turn anticlockwise, with EXIF orientation
    6 (turn clockwise to show), so that a reader honouring the tag gives ``upright``."""
    exif = Image.Exif()
    exif[0x0112] = 6
    options = {"quality": quality} if quality else {}
    Image.fromarray(np.ascontiguousarray(np.rot90(upright, 1))).save(path, exif=exif, **options)


def _png16(path, pixels: np.ndarray) -> None:
    import png

    h, w, planes = pixels.shape
    with open(path, "wb") as f:
        png.Writer(w, h, bitdepth=16, greyscale=False, alpha=planes == 4).write(
            f, pixels.reshape(h, -1))


def _s15(values) -> bytes:
    return b"".join(struct.pack(">i", round(v * 65536)) for v in values)


def wide_gamut_profile() -> bytes:
    """An ICC v2 RGB display profile of Adobe RGB's primaries (D50-adapted) and gamma 2.2,
    built byte by byte (Pillow can make only sRGB's)."""
    text = b"wide gamut\0"
    desc = (b"desc\0\0\0\0" + struct.pack(">I", len(text)) + text + b"\0" * 8
            + b"\0\0\0" + b"\0" * 67)
    curve = b"curv\0\0\0\0" + struct.pack(">IH", 1, round(2.2 * 256)) + b"\0\0"
    xyz = {"wtpt": (0.9642, 1.0, 0.8249), "rXYZ": (0.6097, 0.3111, 0.0195),
           "gXYZ": (0.2053, 0.6257, 0.0609), "bXYZ": (0.1492, 0.0632, 0.7446)}
    tags = {"desc": desc, **{k: b"XYZ \0\0\0\0" + _s15(v) for k, v in xyz.items()},
            "rTRC": curve, "gTRC": curve, "bTRC": curve}
    offset, table, body = 128 + 4 + 12 * len(tags), b"", b""
    for name, data in tags.items():
        data += b"\0" * (-len(data) % 4)
        table += name.encode() + struct.pack(">II", offset + len(body), len(data))
        body += data
    size = offset + len(body)
    header = (struct.pack(">I", size) + b"lcms" + struct.pack(">I", 0x02100000) + b"mntrRGB XYZ "
              + b"\0" * 12 + b"acsp" + b"\0" * 24 + struct.pack(">I", 0) + _s15(xyz["wtpt"])
              + b"\0" * 4 + b"\0" * 44)
    assert len(header) == 128
    return header + struct.pack(">I", len(tags)) + table + body


def _kinds(rng) -> dict:
    """File name -> writer of an 8 x 6 (W x H, upright) image of each kind."""
    h, w = 6, 8
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    rgba = np.concatenate([rgb, rng.integers(0, 256, (h, w, 1), dtype=np.uint8)], -1)
    deep = rng.integers(0, 65536, (h, w, 3), dtype=np.uint16)
    return {
        "turned.png": lambda p: _turned(p, rgb),
        "turned.jpg": lambda p: _turned(p, rgb, quality=95),
        "deep.png": lambda p: _png16(p, deep),
        "alpha.png": lambda p: Image.fromarray(rgba).save(p),
        "palette.png": lambda p: Image.fromarray(rgb).quantize(16).save(p, transparency=3),
        "grey-alpha.png": lambda p: Image.fromarray(rgba[..., [0, 3]]).save(p),
        "profiled.jpg": lambda p: Image.fromarray(rgb).save(p, quality=100,
                                                            icc_profile=wide_gamut_profile()),
    }


@pytest.mark.parametrize("name", list(_kinds(np.random.default_rng(0))))
def test_training_reads_the_pixels_decompose_reads(name, tmp_path):
    """A nerfstudio capture of three such images: the dataset's pixels are the reader's,
    composited on the background, and their weights join."""
    rng = np.random.default_rng(1)
    images = tmp_path / "capture" / "images"
    images.mkdir(parents=True)
    names = []
    for i in range(3):
        names.append(f"images/{i}{name}")
        _kinds(rng)[name](tmp_path / "capture" / names[-1])
    read = load_image(tmp_path / "capture" / names[0])
    assert read.pixels.shape[:2] == (6, 8) and image_size(tmp_path / "capture" / names[0]) == (8, 6)
    (tmp_path / "capture" / "transforms.json").write_text(json.dumps({
        "w": 8, "h": 6, "fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0,
        "frames": [{"file_path": n, "transform_matrix": p.tolist()}
                   for n, p in zip(names, _poses(3))]}))
    dataset = load_dataset(tmp_path / "capture", background=(0.0, 0.0, 0.0))
    alpha = np.ones((6, 8), np.float32) if read.alpha is None else read.alpha
    np.testing.assert_allclose(dataset.images[0], read.rgb * alpha[..., None], atol=1e-6)
    np.testing.assert_allclose(dataset.alpha[0], alpha, atol=1e-6)
    stack = tmp_path / "w.npz"
    assert decompose.main([str(images), "-k", "4", "-o", str(stack)]) == 0
    assert join_weights(dataset, read_stack(stack)).shape[:3] == (3, 6, 8)


def test_orientation_turns_the_stored_pixels(tmp_path, rng):
    upright = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    _turned(tmp_path / "t.png", upright)
    np.testing.assert_array_equal(load_image(tmp_path / "t.png").pixels, upright)


def test_a_profile_other_than_srgb_is_converted(tmp_path):
    """Adobe RGB's saturated red is redder than sRGB's: converted, it clips in sRGB; an sRGB
    profile leaves the pixels as stored."""
    pixels = np.full((4, 4, 3), (200, 120, 60), np.uint8)
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    Image.fromarray(pixels).save(tmp_path / "s.png", icc_profile=srgb)
    np.testing.assert_array_equal(load_image(tmp_path / "s.png").pixels, pixels)
    Image.fromarray(pixels).save(tmp_path / "a.png", icc_profile=wide_gamut_profile())
    red, green, _ = load_image(tmp_path / "a.png").pixels[0, 0].astype(int)
    assert red > 210  # more saturated in sRGB's terms
