"""Shared fixtures: seeded generators and tiny images written to disk."""

import numpy as np
import pytest
from PIL import Image


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def photo_dir(tmp_path, rng):
    """A folder of three small colourful images of different sizes, one in a subfolder."""
    folder = tmp_path / "photos"
    (folder / "sub").mkdir(parents=True)
    for name, (h, w) in [("a.png", (12, 16)), ("b.jpg", (10, 9)), ("sub/c.png", (7, 11))]:
        yy, xx = np.mgrid[0:h, 0:w]
        img = np.stack([xx / w, yy / h, rng.random((h, w))], -1)
        Image.fromarray((img * 255).astype(np.uint8)).save(folder / name)
    return folder


def _simulated(tmp_path_factory, scene: str, spp: int):
    """A built-in scene path traced at 16x16 with 4 training, 1 val and 2 test views."""
    from nerf_stage.cli import main as nerf

    out = tmp_path_factory.mktemp("nerf") / scene
    assert nerf(["simulate", scene, str(out), "--resolution", "16", "--spp", str(spp),
                 "--views", "4", "1", "2"]) == 0
    return out


@pytest.fixture(scope="session")
def cornell(tmp_path_factory):
    """16x16 Cornell box (transport weights, order 2, 15 terms), simulated once a session."""
    return _simulated(tmp_path_factory, "cornell-box", spp=4)


@pytest.fixture(scope="session")
def still_life(tmp_path_factory):
    """16x16 still life with an additive stack decomposed from its training views."""
    from palette_core.cli.decompose import main as decompose

    out = _simulated(tmp_path_factory, "still-life", spp=2)
    assert decompose([str(out / "train"), "-k", "4", "-o", str(out / "weights.npz")]) == 0
    return out


@pytest.fixture(scope="session")
def cornell_run(cornell, tmp_path_factory):
    """A tiny run on ``cornell`` through ``nerf-stage train``, and the flags that made it."""
    pytest.importorskip("torch")
    from nerf_stage.cli import main as nerf

    from .nerf_runs import TINY_FLAGS

    rundir = tmp_path_factory.mktemp("runs") / "cb"
    args = ["train", str(cornell), "--weights", str(cornell / "weights.npz"), "-o", str(rundir),
            *TINY_FLAGS]
    assert nerf(args) == 0
    return rundir, args


@pytest.fixture(scope="session")
def per_sample_run(cornell_run, tmp_path_factory):
    """``cornell_run`` with the paper's per-sample diffuse colours."""
    from nerf_stage.cli import main as nerf
    from nerf_stage.train.loading import load_run

    from .nerf_runs import PER_SAMPLE_FLAGS

    _, args = cornell_run
    rundir = tmp_path_factory.mktemp("runs") / "per-sample"
    args = [*args[:args.index("-o") + 1], str(rundir), *args[args.index("-o") + 2:]]
    assert nerf([*args, *PER_SAMPLE_FLAGS]) == 0
    config = load_run(rundir).config.grid
    assert not config.deferred and config.view_frequencies is None
    return rundir


@pytest.fixture(scope="session")
def scene_run(tmp_path_factory):
    """A tiny weight NeRF of a 16x16 still life."""
    pytest.importorskip("torch")
    from nerf_stage.cli import main as nerf
    from palette_core.cli.decompose import main as decompose

    root = tmp_path_factory.mktemp("studio")
    scene = root / "sl"
    assert nerf(["simulate", "still-life", str(scene), "--resolution", "16", "--spp", "2",
                 "--views", "4", "1", "1"]) == 0
    assert decompose([str(scene / "train"), "-k", "4", "-o", str(scene / "weights.npz")]) == 0
    assert nerf(["train", str(scene), "-o", str(root / "run"), "--pretrain-iters", "2",
                 "--finetune-iters", "2", "--batch-rays", "64", "--grid-voxels", str(12**3),
                 "--head-width", "16"]) == 0
    return root / "run"


@pytest.fixture(scope="session")
def splat_scene_run(scene_run):
    """A tiny splat run of ``scene_run``'s still life."""
    from nerf_stage.cli import main as nerf

    rundir = scene_run.parent / "splat-run"
    assert nerf(["train", str(scene_run.parent / "sl"), "-o", str(rundir), "--backbone",
                 "splats", "--pretrain-iters", "4", "--finetune-iters", "2",
                 "--splats-initial", "64"]) == 0
    return rundir
