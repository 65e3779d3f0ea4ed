"""The project card's three commands, exactly as written, in one nerfstudio-layout folder."""

import json

import pytest

pytest.importorskip("torch")

from harmonize.cli import main as harmonize  # noqa: E402
from nerf_stage.cli import main as nerf_stage  # noqa: E402
from nerf_stage.data.dataset import join_weights, load_dataset  # noqa: E402
from nerf_stage.train.checkpoint import CHECKPOINT  # noqa: E402
from nerf_stage.train.config import CONFIG_ENV  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402
from palette_core import read_stack  # noqa: E402
from palette_core.cli.decompose import main as decompose  # noqa: E402

from .helpers import expect_error  # noqa: E402

TINY_TRAINING = {"pretrain_iters": 2, "finetune_iters": 2, "batch_rays": 64, "head_width": 16,
                 "occupancy_voxels": 216, "grid": {"voxels": 1728}}


@pytest.fixture
def scene(tmp_path, monkeypatch):
    """A capture folder (images/, transforms.json) of 8 simulated 16x16 views, as cwd."""
    folder = tmp_path / "scene"
    assert nerf_stage(["simulate", "still-life", str(folder), "--layout", "nerfstudio",
                       "--resolution", "16", "--spp", "2", "--views", "6", "1", "1"]) == 0
    budget = tmp_path / "budget.json"
    budget.write_text(json.dumps(TINY_TRAINING))
    monkeypatch.setenv(CONFIG_ENV, str(budget))
    monkeypatch.chdir(folder)
    return folder


def test_the_three_commands_of_the_card(scene, capsys):
    assert sorted(p.name for p in scene.iterdir()) == ["images", "transforms.json"]
    assert decompose(["images/", "-k", "5"]) == 0
    assert harmonize(["--template", "double-split"]) == 0
    capsys.readouterr()
    assert nerf_stage(["train"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith(f"dataset: {scene} (nerfstudio layout, 8 frames")
    assert printed[1] == f"weights: {scene / 'weights.npz'}"

    stack = read_stack(scene / "weights.npz")
    assert stack.names[0] == "frame_00001.png" and len(stack.palette) == 5
    # frame 8 is a test view (every eighth nerfstudio frame is held out)
    assert join_weights(load_dataset(scene), stack).shape == (7, 16, 16, 5)
    harmonized = read_stack(scene / "weights_double-split.npz")
    assert harmonized.meta["harmonize"]["template"] == "double-split"
    run = load_run(scene.parent / "scene-grid")
    assert run.record.iteration == 4 and run.config.grid.voxels == 1728
    assert (scene.parent / "scene-grid" / CHECKPOINT).is_file()


def test_the_card_says_what_is_missing(scene, capsys):
    expect_error(harmonize, ["--template", "double-split"],
                 "weights.npz does not exist: palette-decompose of the images writes it", capsys)
    expect_error(nerf_stage, ["train"], "weights.npz does not exist: palette-decompose of the "
                 "images writes it", capsys)
    (scene / "transforms.json").unlink()
    expect_error(nerf_stage, ["train"], "a COLMAP model (sparse/0) (colmap layout): make one "
                 "from photos with nerf-stage poses", capsys)


def test_harmonize_says_which_stack_it_took(scene, capsys):
    assert decompose(["images/", "-k", "5"]) == 0
    capsys.readouterr()
    assert harmonize(["--template", "double-split"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == "using ./weights.npz"
