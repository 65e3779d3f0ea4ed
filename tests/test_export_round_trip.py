"""Exports lose nothing silently: each format read back holds what was meant within its
quantisation, over extreme scenes, or the export is refused in one line and not written."""

import numpy as np
import pytest

from palette_core.basis import Basis
from palette_core.errors import InputError

pytest.importorskip("torch")
gsply = pytest.importorskip("gsply")

from nerf_stage.splats import Splats, export_splats, splat_fields  # noqa: E402
from splat_files import FORMATS, read_splat_file  # noqa: E402
from splat_files.spz import fractional_bits  # noqa: E402


def scene(rng, reach: float, n: int = 300, opacity=None, scale=None) -> Splats:
    """``n`` splats of random colours, spread up to ``reach`` from the origin (one at it)."""
    q = rng.normal(size=(n, 4))
    centres = rng.uniform(-1, 1, (n, 3)) * reach
    centres[0] = [reach, -reach, 0.5 * reach]
    return Splats(centres.astype(np.float32),
                  (rng.uniform(0.01, 0.2, (n, 3)) if scale is None else np.full((n, 3), scale))
                  .astype(np.float32),
                  (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                  (rng.uniform(0.05, 0.95, n) if opacity is None else np.full(n, opacity))
                  .astype(np.float32), rng.dirichlet(np.ones(4), n).astype(np.float32),
                  rng.uniform(0, 1, (4, 3)), Basis.ADDITIVE, 1, np.ones(3), {})


SCENES = {"unit": dict(reach=1.0), "a city block": dict(reach=1e4),
          "opaque": dict(reach=1.0, opacity=1.0), "faint": dict(reach=1.0, opacity=1e-9),
          "large splats": dict(reach=50.0, scale=30.0)}


@pytest.mark.parametrize("suffix", [".ply", ".spz"])
@pytest.mark.parametrize("name", list(SCENES))
def test_every_format_holds_extreme_scenes_to_its_quantisation(name, suffix, tmp_path, rng):
    splats = scene(rng, **SCENES[name])
    path = export_splats(splats, tmp_path / f"s{suffix}")
    meant, read = splat_fields(splats), read_splat_file(path)
    step = 0.0 if suffix == ".ply" else 2.0 ** -fractional_bits(meant.means)
    error = np.abs(read.means - meant.means) - 1e-6 * np.abs(meant.means)
    assert error.max() <= step / 2
    tolerance = FORMATS[suffix].tolerances(meant)["scales"]
    assert np.abs(read.scales - meant.scales).max() <= tolerance + 1e-5


def test_spz_positions_take_the_fractional_bits_their_extent_needs(tmp_path, rng):
    """10^4 from the origin: 12 fractional bits would clip at 2048; 9 hold it."""
    splats = scene(rng, 1e4)
    export_splats(splats, tmp_path / "s.spz")
    with open(tmp_path / "s.spz", "rb") as f:
        import gzip

        header = gzip.decompress(f.read())[:16]
    assert header[13] == 9
    assert np.abs(read_splat_file(tmp_path / "s.spz").means[0] - [1e4, -1e4, 5e3]).max() < 2**-9


@pytest.mark.parametrize("reach, suffix, message", [
    (1e7, ".spz", "24-bit positions"),
    (1e39, ".ply", "do not fit in float32"),
])
def test_what_a_format_cannot_hold_is_refused_unwritten(reach, suffix, message, tmp_path, rng):
    splats = scene(rng, 1.0)
    splats.centres = splats.centres.astype(np.float64) * reach
    with pytest.raises(InputError, match=message):
        export_splats(splats, tmp_path / f"s{suffix}")
    assert list(tmp_path.iterdir()) == []


def test_colours_spz_cannot_hold_are_refused(tmp_path, rng):
    """SPZ's spherical harmonics stop at +-1: a residual beyond is refused, the PLY keeps it."""
    splats = scene(rng, 1.0)
    splats.residual = np.zeros((len(splats), 3, 4), np.float32)
    splats.residual[0, 0] = [3.0, -1.0, -1.0, -1.0]
    export_splats(splats, tmp_path / "s.ply")
    with pytest.raises(InputError, match="SPZ cannot hold the splats' shN"):
        export_splats(splats, tmp_path / "s.spz")
    assert not (tmp_path / "s.spz").exists()
