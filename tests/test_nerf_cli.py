"""nerf-stage train, render and eval through main([...]): recolouring without the network,
baked renders, CPU/CUDA agreement, one-line errors, run folders from elsewhere."""

import json
import shutil

import numpy as np
import pytest

from nerf_stage.cli import main as nerf_stage
from nerf_stage.data.dataset import load_dataset
from palette_core.cli import decompose

from .helpers import expect_error

torch = pytest.importorskip("torch")

from nerf_stage.cli import main  # noqa: E402
from nerf_stage.edit.editing import read_render  # noqa: E402
from nerf_stage.train.checkpoint import CHECKPOINT  # noqa: E402
from nerf_stage.train.config import BAKE_FACTOR  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402

from .nerf_runs import tiny_config, trained  # noqa: E402


def test_train_render_recolour_eval(cornell_run, tmp_path, capsys):
    rundir, _ = cornell_run
    palette = tmp_path / "edit.json"
    palette.write_text(json.dumps({"palette": [[0.1, 0.2, 0.9]] * 4}))
    out = tmp_path / "renders"
    assert main(["render", str(rundir), "-o", str(out)]) == 0
    saved = read_render(out / "render.npz")
    assert saved.weights.shape == (2, 16, 16, 15)
    capsys.readouterr()
    assert main(["render", str(rundir), "--palette", str(palette), "--harmonize", "triad",
                 "-o", str(out)]) == 0
    assert "does not run" in capsys.readouterr().out
    for label in ("original", "edit", "harmonized-triad"):
        assert sorted(p.name for p in (out / label).iterdir()) == [
            "palette.png", "r_000.png", "r_001.png"]
    expect_error(main, ["render", str(rundir), "--palette", str(palette), "-o", str(out)],
                 "edit already exists", capsys)
    expect_error(main, ["render", str(rundir), "--orbit", "2", "-o", str(out)],
                 "holds another render", capsys)
    assert main(["render", str(rundir), "--orbit", "3", "-o", str(tmp_path / "orbit")]) == 0
    assert (tmp_path / "orbit" / "original.gif").stat().st_size > 0
    assert main(["eval", str(rundir)]) == 0
    printed = capsys.readouterr().out
    assert "RGB through the weights: PSNR" in printed and "re-simulated scene: PSNR" in printed
    expect_error(main, ["render", str(rundir), "--baked", "-o", str(tmp_path / "baked")],
                 "per-sample diffuse colours", capsys)


def test_per_sample_runs_render_and_score_baked(per_sample_run, tmp_path, capsys):
    out = tmp_path / "baked"
    assert main(["render", str(per_sample_run), "--baked", "-o", str(out)]) == 0
    assert read_render(out / "render.npz").source["baked"] == BAKE_FACTOR
    capsys.readouterr()
    expect_error(main, ["render", str(per_sample_run), "-o", str(out)], "holds another render",
                 capsys)
    expect_error(main, ["eval", str(per_sample_run), "--baked", "9"], "must be in [1, 4], got 9",
                 capsys)
    assert main(["eval", str(per_sample_run), "--baked", "3"]) == 0
    assert "RGB through the weights: PSNR" in capsys.readouterr().out


def test_a_run_trained_again_is_rendered_again(cornell_run, tmp_path, capsys):
    _, args = cornell_run
    rundir, out = tmp_path / "run", tmp_path / "renders"
    args = [*args[:args.index("-o") + 1], str(rundir), *args[args.index("-o") + 2:]]
    assert main(args) == 0
    assert main(["render", str(rundir), "-o", str(out)]) == 0
    assert main(["render", str(rundir), "-o", str(out), "--force"]) == 0
    assert "recoloured the saved weight render" in capsys.readouterr().out
    assert main([*args, "--force"]) == 0  # same folder, same iterations, a new training
    assert main(["render", str(rundir), "-o", str(out), "--force"]) == 0
    assert "recoloured the saved weight render" not in capsys.readouterr().out


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cpu_and_cuda_agree(cornell, cornell_run, per_sample_run, tmp_path):
    """The same checkpoints render alike on both devices, deferred, per sample and baked,
    and training runs on CUDA."""
    poses = load_dataset(cornell).poses[:2]
    deferred, per_sample = ([load_run(rundir, torch.device(d)) for d in ("cpu", "cuda")]
                            for rundir in (cornell_run[0], per_sample_run))
    for on_cpu, on_cuda in (deferred, per_sample, [run.baked() for run in per_sample]):
        for a, b in zip(on_cpu.render(poses), on_cuda.render(poses)):
            assert np.abs(a - b).max() < 1e-4
    run = trained(cornell, tiny_config(), tmp_path / "cuda", device=torch.device("cuda"))
    weights, opacity = run.render(poses)
    assert np.isfinite(weights).all() and opacity.max() <= 1 + 1e-5


def test_cli_errors(cornell, cornell_run, still_life, tmp_path, capsys):
    rundir, train_args = cornell_run
    expect_error(main, ["render", str(tmp_path), "-o", str(tmp_path / "x")],
                 "holds no checkpoint", capsys)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps({"palette": [[0.1, 0.2, 0.9]] * 3}))
    expect_error(main, ["render", str(rundir), "--palette", str(wrong), "-o", str(tmp_path / "x")],
                 "has 3 colours, expected 4", capsys)
    partial = tmp_path / "partial.npz"  # weights of two views only
    assert decompose.main([str(still_life / "test"), "-k", "4", "-o", str(partial)]) == 0
    expect_error(main, ["train", str(cornell), "--weights", str(partial), "-o",
                        str(tmp_path / "r")], "train frames without weights", capsys)
    expect_error(main, ["train", str(cornell), "--weights", str(cornell / "weights.npz"),
                        "--backbone", "octree"], "invalid choice: 'octree'", capsys)
    expect_error(main, train_args, "already holds a run", capsys)
    expect_error(main, ["train", str(cornell), "--weights", str(cornell / "weights.npz"),
                        "-o", str(tmp_path / "new"), "--resume"], "holds no checkpoint", capsys)
    copy = tmp_path / "copy"
    shutil.copytree(rundir, copy)
    expect_error(main, train_args[:5] + [str(copy), "--resume"], "another config", capsys)
    assert not (tmp_path / "x").exists()
    assert load_run(rundir).record.iteration == 4 and (rundir / CHECKPOINT).is_file()


def test_render_checks_every_argument_first(cornell_run, tmp_path, capsys):
    rundir, _ = cornell_run
    out = tmp_path / "out"
    expect_error(main, ["render", str(rundir), "--harmonize", "nope", "-o", str(out)],
                 "unknown template 'nope'", capsys)
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "x.json").write_text(json.dumps({"palette": ["#102030"] * 4}))
    expect_error(main, ["render", str(rundir), "--palette", str(tmp_path / "a" / "x.json"),
                        "--palette", str(tmp_path / "b" / "x.json"), "-o", str(out)],
                 "outputs collide", capsys)
    assert not out.exists()


class _Payload:
    """Unpickling this would create a marker file."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def test_a_crafted_checkpoint_runs_no_code(cornell_run, tmp_path, capsys):
    rundir, _ = cornell_run
    crafted = tmp_path / "crafted"
    shutil.copytree(rundir, crafted)
    marker = tmp_path / "pwned"
    state = torch.load(crafted / CHECKPOINT, weights_only=True)
    torch.save(dict(state, log=_Payload(marker)), crafted / CHECKPOINT)
    for args in (["render", str(crafted), "-o", str(tmp_path / "r")], ["eval", str(crafted)]):
        expect_error(main, args, "cannot read checkpoint", capsys)
    assert not marker.exists()
    state.pop("occupancy")
    torch.save(state, crafted / CHECKPOINT)
    expect_error(main, ["eval", str(crafted)], "lacks occupancy", capsys)


@pytest.mark.parametrize("config, message", [
    ({"grid": [1, 2]}, "grid must be an object"),
    ({"grid": {"voxels": "many"}}, "voxels must be an integer"),
    ({"seed": 1.5}, "seed must be an integer"),
    ({"grid": {"voxels": 10**12}}, "voxels must be an integer in [1, 33554432]"),
    ({"supersampling": 100_000}, "supersampling must be an integer in [1, 8]"),
    ({"batch_rays": True}, "batch_rays must be an integer"),
    ({"background": ["white", 0, 0]}, "background must be three numbers"),
    ({"lr_decay": "0.3"}, "lr_decay must be a finite number"),
])
def test_bad_training_configs_are_one_line(tmp_path, capsys, monkeypatch, config, message):
    path = tmp_path / "config.json"
    path.write_text(json.dumps(config))
    monkeypatch.setenv("NERF_STAGE_CONFIG", str(path))
    expect_error(nerf_stage, ["train", str(tmp_path)], message, capsys)
    # only train reads it: the other commands are not broken by it
    expect_error(nerf_stage, ["simulate", "no-such-scene", str(tmp_path / "o")],
                 "no-such-scene", capsys)


def _crafted_run(scene_run, tmp_path, change):
    import shutil

    import torch

    run = tmp_path / "run"
    shutil.copytree(scene_run, run)
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    change(state)
    torch.save(state, run / "checkpoint.pt")
    return run


@pytest.mark.parametrize("change, message", [
    (lambda s: s["intrinsics"].update(width=10**6, height=10**6), "a camera of 1000000x1000000"),
    (lambda s: s["intrinsics"].update(fx=float("nan")), "focal lengths finite"),
    (lambda s: s.update(basis="transport", order=1000), "channels, more than 4096"),
    (lambda s: s.update(palette=[[2.0, 0.0, 0.0]] * 4), "palette must have shape"),
    (lambda s: s["box"].update(half=[0.0, 1.0, 1.0]), "positive extent"),
    (lambda s: s["config"]["grid"].update(voxels=10**12), "voxels must be an integer"),
])
def test_crafted_run_folders_are_refused_before_allocating(scene_run, tmp_path, capsys, change,
                                                           message):
    pytest.importorskip("torch")
    run = _crafted_run(scene_run, tmp_path, change)
    expect_error(nerf_stage, ["render", str(run), "--orbit", "2", "-o", str(tmp_path / "out")],
                 message, capsys)
    assert not (tmp_path / "out").exists()


def test_a_downscaled_run_renders_and_scores_at_its_size(still_life, tmp_path, capsys):
    from .nerf_runs import TINY_FLAGS

    rundir = tmp_path / "run"
    assert main(["train", str(still_life), "-o", str(rundir), "--downscale", "2",
                 *TINY_FLAGS]) == 0
    run = load_run(rundir)
    assert run.record.downscale == 2 and run.intrinsics.width == 8
    assert main(["eval", str(rundir)]) == 0
    assert main(["render", str(rundir), "-o", str(tmp_path / "r")]) == 0
    assert read_render(tmp_path / "r" / "render.npz").weights.shape[1:3] == (8, 8)


def test_eval_scores_views_off_the_rig_apart(tmp_path, capsys):
    from .nerf_runs import TINY_FLAGS

    scene = tmp_path / "cb"
    assert nerf_stage(["simulate", "cornell-box", str(scene), "--resolution", "12", "--spp", "2",
                       "--views", "4", "0", "2", "--off-ring", "2"]) == 0
    rundir = tmp_path / "run"
    assert main(["train", str(scene), "--weights", str(scene / "weights.npz"), "-o", str(rundir),
                 *TINY_FLAGS]) == 0
    capsys.readouterr()
    assert main(["eval", str(rundir)]) == 0
    printed = capsys.readouterr().out
    assert "2 test views, " in printed and "2 test views off the training rig: PSNR" in printed
    assert "re-simulated scene: PSNR" in printed
