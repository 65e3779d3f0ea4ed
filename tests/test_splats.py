"""Splat bakes: a weight NeRF as 3D Gaussians with palette weights; drawing, recolouring,
the PLY export and the checks of the bake file."""

import shutil

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

from nerf_stage.cli import main  # noqa: E402
from nerf_stage.data.cameras import Intrinsics, look_at  # noqa: E402
from nerf_stage.edit.regions import Region  # noqa: E402
from nerf_stage.splats import (  # noqa: E402
    BAKE_VERSION,
    SH_C0,
    SPLAT_CACHE,
    Splats,
    bake_run,
    cached_bake,
    covariances,
    draw,
    export_splats,
    matrix_quaternions,
    read_splats,
    refine,
    render_splats,
    splat_tensors,
    write_splats,
)
from nerf_stage.splats import baking as bake_module  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402
from palette_core.basis import Basis, basis_terms  # noqa: E402
from palette_core.errors import InputError  # noqa: E402

from .helpers import expect_error  # noqa: E402


@pytest.fixture(scope="module")
def additive_bake(scene_run):
    return bake_run(scene_run, refine_steps=5, progress=False)


@pytest.fixture
def hand_made(rng):
    """200 opaque-ish splats with additive weights in front of ``CAMERA`` at ``POSE``."""
    n, k = 200, 4
    q = rng.normal(size=(n, 4))
    weights = rng.dirichlet(np.ones(k), n)
    return Splats(rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                  rng.uniform(0.05, 0.2, (n, 3)).astype(np.float32),
                  (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                  rng.uniform(0.3, 0.95, n).astype(np.float32), weights.astype(np.float32),
                  rng.uniform(0, 1, (k, 3)), Basis.ADDITIVE, 1, np.ones(3), {"cell": 0.1})


def read_ply(path) -> np.ndarray:
    """The vertex table of a PLY, as trimesh reads it."""
    return trimesh.load(path).metadata["_ply_raw"]["vertex"]["data"]


CAMERA = Intrinsics(40, 30, 40.0, 40.0, 20.0, 15.0)
POSE = look_at([0.0, 0.5, 4.0], [0.0, 0.0, 0.0])


def test_a_tiny_run_bakes_with_weights_on_the_simplex(additive_bake, scene_run):
    splats = additive_bake
    assert len(splats) > 0 and splats.source["refine_steps"] == 5
    assert np.allclose(splats.weights.sum(1), 1, atol=1e-5) and splats.weights.min() >= 0
    assert ((splats.opacities > 0) & (splats.opacities < 1)).all() and (splats.scales > 0).all()
    run = load_run(scene_run)
    low, high = run.box.centre - run.box.half, run.box.centre + run.box.half
    assert ((splats.centres >= low - 1) & (splats.centres <= high + 1)).all()


def test_a_kept_bake_is_used_until_the_bake_changes(scene_run, tmp_path, monkeypatch):
    rundir = tmp_path / "run"
    shutil.copytree(scene_run, rundir)
    run = load_run(rundir)
    cached_bake(run, rundir, progress=False, refine_steps=1)
    kept = (rundir / SPLAT_CACHE).stat().st_mtime_ns
    cached_bake(run, rundir, progress=False, refine_steps=1)
    assert (rundir / SPLAT_CACHE).stat().st_mtime_ns == kept
    monkeypatch.setattr(bake_module, "BAKE_VERSION", BAKE_VERSION + 1)
    assert cached_bake(run, rundir, progress=False,
                       refine_steps=1).source["bake_version"] == BAKE_VERSION + 1
    assert read_splats(rundir / SPLAT_CACHE).source["bake_version"] == BAKE_VERSION + 1


def test_drawing_colours_is_recolouring_the_drawn_weights(hand_made, rng):
    edit = rng.uniform(0, 1, hand_made.palette.shape)
    centres, covariance, weights, opacities = splat_tensors(hand_made)
    drawn, covered = draw(centres, covariance, weights, opacities, torch.as_tensor(POSE),
                           CAMERA)
    colours = torch.as_tensor(hand_made.colours(edit))
    painted, _ = draw(centres, covariance, colours, opacities, torch.as_tensor(POSE), CAMERA)
    terms = torch.as_tensor(basis_terms(edit, hand_made.basis, hand_made.order)).float()
    assert covered.max() > 0.9 and covered.min() >= 0 and covered.max() <= 1
    assert torch.allclose(painted, drawn @ terms, atol=1e-6)
    assert torch.allclose(drawn.sum(1), covered, atol=1e-6)  # weights sum to the opacity
    views, opacity = render_splats(hand_made, POSE[None], CAMERA)
    assert views.shape == (1, 30, 40, 4) and np.allclose(opacity[0].ravel(), covered.numpy())


@pytest.fixture
def reweighted_drawing(hand_made):
    """(weights, opacity) of the hand-made splats drawn with their weights reversed."""
    target = Splats(**{**hand_made.__dict__, "weights": hand_made.weights[:, ::-1].copy()})
    return render_splats(target, POSE[None], CAMERA)


def test_refining_fits_the_views_it_is_given(hand_made, reweighted_drawing):
    """Refining the hand-made splats towards a drawing of themselves reweighted lowers the
    error, and keeps the weights on the simplex."""
    weights, opacity = reweighted_drawing
    before = np.abs(render_splats(hand_made, POSE[None], CAMERA)[0] - weights).mean()
    refined = refine(hand_made, POSE[None], [CAMERA], weights, opacity, 40, progress=False,
                     device=torch.device("cpu"))
    after = np.abs(render_splats(refined, POSE[None], CAMERA)[0] - weights).mean()
    assert after < 0.7 * before
    assert np.allclose(refined.weights.sum(1), 1, atol=1e-5) and refined.weights.min() >= 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_refining_on_cuda_agrees_with_the_cpu(hand_made, reweighted_drawing):
    weights, opacity = reweighted_drawing
    on = [refine(hand_made, POSE[None], [CAMERA], weights, opacity, 20, progress=False,
                 device=torch.device(d)) for d in ("cpu", "cuda")]
    for name in ("centres", "scales", "opacities", "weights"):
        assert np.allclose(getattr(on[0], name), getattr(on[1], name), atol=1e-3), name


def test_splats_are_drawn_front_to_back():
    """Two splats on the axis: the nearer one's colour covers the farther one's."""
    near_first = Splats(np.array([[0, 0, 1], [0, 0, -1]], np.float32),
                        np.full((2, 3), 0.3, np.float32), np.tile([1, 0, 0, 0], (2, 1)).astype(
                            np.float32), np.array([0.9, 0.9], np.float32),
                        np.eye(2, dtype=np.float32), np.eye(2, 3), Basis.ADDITIVE, 1, np.ones(3),
                        {})
    pose = look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
    weights, opacity = render_splats(near_first, pose[None], CAMERA)
    centre = weights[0, 15, 20]
    assert centre[0] > 0.85 and centre[1] < 0.1 and opacity[0, 15, 20] > 0.95


def test_quaternions_round_trip(rng):
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scales = rng.uniform(0.1, 2, (50, 3))
    cov = covariances(torch.as_tensor(q), torch.as_tensor(scales)).numpy()
    variance, axes = np.linalg.eigh(cov)
    axes[np.linalg.det(axes) < 0, :, 0] *= -1
    again = covariances(torch.as_tensor(matrix_quaternions(axes)),
                        torch.as_tensor(np.sqrt(variance))).numpy()
    assert np.allclose(again, cov, atol=1e-9)


def test_a_region_keeps_the_edit_to_the_splats_inside_it(hand_made, rng):
    edit = rng.uniform(0, 1, hand_made.palette.shape)
    half = Region("box", (-0.5, 0.0, 0.0), (0.5, 1.0, 1.0))  # x < 0
    inside = hand_made.centres[:, 0] <= 0
    colours = hand_made.colours(edit, [half])
    assert np.array_equal(colours[inside], hand_made.colours(edit)[inside])
    assert np.array_equal(colours[~inside], hand_made.colours()[~inside])


def test_the_ply_holds_what_splat_viewers_read(hand_made, tmp_path, rng):
    additive_bake = hand_made
    edit = rng.uniform(0, 1, additive_bake.palette.shape)
    export_splats(additive_bake, tmp_path / "s.ply", edit)
    data = read_ply(tmp_path / "s.ply")
    assert data.dtype.names == ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2",
                                "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
                                "rot_2", "rot_3")
    assert np.allclose(np.stack([data["x"], data["y"], data["z"]], 1), additive_bake.centres)
    colours = np.stack([data[f"f_dc_{i}"] for i in range(3)], 1) * SH_C0 + 0.5
    assert np.allclose(colours, additive_bake.colours(edit), atol=1e-5)
    assert np.allclose(1 / (1 + np.exp(-data["opacity"])), additive_bake.opacities, atol=1e-5)
    assert np.allclose(np.exp(np.stack([data[f"scale_{i}"] for i in range(3)], 1)),
                       additive_bake.scales, rtol=1e-5)


def test_bake_and_export_from_the_command_line(scene_run, cornell_run, tmp_path, capsys):
    bake = tmp_path / "cb.splat.npz"
    assert main(["bake", str(scene_run), "-o", str(bake), "--refine-steps", "2"]) == 0
    splats = read_splats(bake)
    assert len(splats) > 0 and splats.weights.shape[1] == 4
    assert main(["export", str(bake), "-o", str(tmp_path / "cb.ply")]) == 0
    assert (tmp_path / "cb.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")
    capsys.readouterr()
    expect_error(main, ["export", str(bake), "-o", str(tmp_path / "cb.ply")], "already exists",
                 capsys)
    expect_error(main, ["export", str(bake), "-o", str(tmp_path / "cb.obj")],
                 "splats are written as", capsys)
    expect_error(main, ["bake", str(scene_run), "-o", str(tmp_path / "x.npz"),
                        "--max-splats", "0"], "max splats", capsys)
    run = tmp_path / "run"  # by default the bake goes into the run, where export finds it
    shutil.copytree(scene_run, run, ignore=shutil.ignore_patterns("splats.npz"))
    assert main(["bake", str(run), "--refine-steps", "2"]) == 0
    assert main(["export", str(run), "-o", str(tmp_path / "run.ply")]) == 0
    assert read_ply(tmp_path / "run.ply").shape == (len(read_splats(run / "splats.npz")),)
    # order-2 transport weights, 15 a splat (a run of four steps: fog, but it bakes)
    assert main(["bake", str(cornell_run[0]), "-o", str(tmp_path / "x.npz"),
                 "--refine-steps", "1"]) == 0
    assert read_splats(tmp_path / "x.npz").weights.shape[1] == 15


@pytest.mark.parametrize("change, message", [
    ({"format": np.array("palette-render/2")}, "not a splat bake"),
    ({"scales": "negative"}, "scales must be positive"),
    ({"centres": "nan"}, "NaN"),
    ({"weights": "short"}, "wrong shapes"),
])
def test_bake_files_from_elsewhere_are_checked(hand_made, tmp_path, change, message):
    path = tmp_path / "s.npz"
    write_splats(hand_made, path)
    with np.load(path) as npz:
        arrays = dict(npz)
    for key, value in change.items():
        if value == "negative":
            arrays[key] = -arrays[key]
        elif value == "nan":
            arrays[key] = arrays[key].copy()
            arrays[key][0, 0] = np.nan
        elif value == "short":
            arrays[key] = arrays[key][:, :-1]
        else:
            arrays[key] = value
    np.savez(path, **arrays)
    with pytest.raises(InputError, match=message):
        read_splats(path)
