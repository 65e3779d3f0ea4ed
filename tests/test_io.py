"""Image input: formats, bit depths, alpha, orientation, stitching."""

import warnings

import numpy as np
import png
import pytest
import tifffile
from PIL import Image

from palette_core import ColourSet, InputError, find_images, load_image, read_stack
from palette_core.cli import decompose

from .helpers import expect_error, png_header_only


@pytest.mark.parametrize("suffix", [".png", ".tif", ".bmp", ".webp"])
def test_lossless_formats_round_trip(tmp_path, rng, suffix):
    pixels = (rng.random((5, 6, 3)) * 255).astype(np.uint8)
    Image.fromarray(pixels).save(tmp_path / f"x{suffix}", **({"lossless": True}
                                                              if suffix == ".webp" else {}))
    image = load_image(tmp_path / f"x{suffix}")
    np.testing.assert_array_equal(image.pixels, pixels)
    assert image.opaque.all()


def test_jpeg_and_greyscale(tmp_path, rng):
    Image.fromarray((rng.random((8, 8, 3)) * 255).astype(np.uint8)).save(tmp_path / "x.jpg")
    assert load_image(tmp_path / "x.jpg").pixels.shape == (8, 8, 3)
    grey = (rng.random((4, 5)) * 255).astype(np.uint8)
    Image.fromarray(grey).save(tmp_path / "g.png")
    np.testing.assert_array_equal(load_image(tmp_path / "g.png").pixels, grey[..., None]
                                  .repeat(3, -1))


def test_16_bit_png_and_tiff(tmp_path, rng):
    pixels = (rng.random((4, 5, 3)) * 65535).astype(np.uint16)
    png.from_array(pixels.reshape(4, -1), "RGB;16").save(tmp_path / "x.png")
    tifffile.imwrite(tmp_path / "x.tif", pixels)
    for name in ("x.png", "x.tif"):
        image = load_image(tmp_path / name)
        assert image.pixels.dtype == np.uint16
        np.testing.assert_array_equal(image.pixels, pixels)
    grey = (rng.random((4, 5)) * 65535).astype(np.uint16)
    Image.fromarray(grey).save(tmp_path / "g.png")
    np.testing.assert_array_equal(load_image(tmp_path / "g.png").pixels[..., 0], grey)


def test_transparent_pixels_marked(tmp_path):
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., :3] = 200
    rgba[0, 0, 3] = 0
    rgba[1, :, 3] = 255
    rgba[0, 1:, 3] = 10
    Image.fromarray(rgba).save(tmp_path / "a.png")
    image = load_image(tmp_path / "a.png")
    np.testing.assert_array_equal(image.opaque, rgba[..., 3] > 0)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_matches_pillow(tmp_path, rng, orientation):
    from PIL import ImageOps

    im = Image.fromarray((rng.random((3, 5, 3)) * 255).astype(np.uint8))
    exif = Image.Exif()
    exif[0x0112] = orientation
    im.save(tmp_path / "o.png", exif=exif)
    with Image.open(tmp_path / "o.png") as reread:
        expected = np.asarray(ImageOps.exif_transpose(reread))
    np.testing.assert_array_equal(load_image(tmp_path / "o.png").pixels, expected)


def test_find_images_recursive_sorted(photo_dir):
    root, paths = find_images([photo_dir])
    assert root == photo_dir.resolve()
    assert [p.relative_to(root).as_posix() for p in paths] == ["a.png", "b.jpg", "sub/c.png"]


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        find_images([tmp_path / "nope"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images"):
        find_images([tmp_path / "empty"])
    (tmp_path / "bad.png").write_bytes(b"not really a png")
    with pytest.raises(InputError, match="bad.png"):
        load_image(tmp_path / "bad.png")


def test_colour_set_stitches_and_deduplicates(rng):
    from palette_core.io import LoadedImage

    a = (rng.random((3, 4, 3)) * 4).astype(np.uint8)
    b = (rng.random((2, 2, 3)) * 4).astype(np.uint16) * 257
    opaque = np.ones((2, 2), bool)
    opaque[0, 0] = False
    images = [LoadedImage("a", a, np.ones((3, 4), bool)), LoadedImage("b", b, opaque)]
    cs = ColourSet.from_images(images)
    assert len(np.unique(cs.colours, axis=0)) == len(cs.colours)
    for i, image in enumerate(images):
        np.testing.assert_allclose(cs.colours[cs.image_indices(i)], image.rgb.reshape(-1, 3))
    assert cs.counts.sum() == 12 + 3


def test_large_8_bit_sets_use_the_table(rng):
    from palette_core.io import LoadedImage

    pixels = (rng.random((1100, 1000, 3)) * 255).astype(np.uint8)
    cs = ColourSet.from_images([LoadedImage("big", pixels, np.ones((1100, 1000), bool))])
    np.testing.assert_array_equal(np.round(cs.colours[cs.inverse] * 255).astype(np.uint8),
                                  pixels.reshape(-1, 3))


def test_decompression_bombs_are_refused_from_the_header(tmp_path, capsys):
    bomb = png_header_only(tmp_path / "bomb.png", 100000, 100000)
    expect_error(decompose.main, [str(bomb), "-o", str(tmp_path / "w.npz")], "--max-pixels",
                 capsys)
    Image.fromarray(np.zeros((100, 100, 3), np.uint8)).save(tmp_path / "flat.png")
    expect_error(decompose.main, [str(tmp_path / "flat.png"), "--max-pixels", "5000",
                                  "-o", str(tmp_path / "w.npz")], "100x100", capsys)


def test_fully_transparent_images(tmp_path, capsys):
    Image.fromarray(np.zeros((4, 4, 4), np.uint8)).save(tmp_path / "clear.png")
    expect_error(decompose.main, [str(tmp_path / "clear.png"), "-o", str(tmp_path / "w.npz")],
                 "fully transparent", capsys)


def test_planar_16_bit_tiff(tmp_path, rng):
    planes = rng.integers(0, 65536, (3, 5, 64), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "planar.tif", planes, planarconfig="separate", photometric="rgb")
    image = load_image(tmp_path / "planar.tif")
    assert image.pixels.shape == (5, 64, 3)
    assert np.array_equal(image.pixels, np.moveaxis(planes, 0, -1))


def test_float_tiff_with_nan(tmp_path):
    tifffile.imwrite(tmp_path / "nan.tif", np.full((4, 4), np.nan, np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="NaN"):
            load_image(tmp_path / "nan.tif")


def test_symlinked_input_keeps_its_name(tmp_path, rng):
    (tmp_path / "store").mkdir()
    (tmp_path / "in").mkdir()
    Image.fromarray(rng.integers(0, 256, (4, 4, 3), dtype=np.uint8)).save(
        tmp_path / "store" / "x1234.png")
    (tmp_path / "in" / "holiday.png").symlink_to(tmp_path / "store" / "x1234.png")
    link = tmp_path / "in" / "holiday.png"
    assert decompose.main([str(link), "-k", "4", "-o", str(tmp_path / "w.npz")]) == 0
    assert read_stack(tmp_path / "w.npz").names == ["holiday.png"]


def test_folder_links_out_are_refused(tmp_path, rng, capsys):
    """A folder's link to a file outside it is not read (a folder from elsewhere could make
    us decompose a private photo); named directly, the same link is read (above)."""
    (tmp_path / "store").mkdir()
    (tmp_path / "in").mkdir()
    for name in ("x1234.png", "own.png"):
        Image.fromarray(rng.integers(0, 256, (4, 4, 3), dtype=np.uint8)).save(
            tmp_path / "store" / name)
    (tmp_path / "in" / "own.png").write_bytes((tmp_path / "store" / "own.png").read_bytes())
    (tmp_path / "in" / "holiday.png").symlink_to(tmp_path / "store" / "x1234.png")
    assert decompose.main([str(tmp_path / "in"), "-k", "4", "-o", str(tmp_path / "w.npz")]) == 2
    assert "holiday.png is a link out of" in capsys.readouterr().err
    assert not (tmp_path / "w.npz").exists()
