"""Weight NeRFs: compositing, the frozen density part, output activations, resume, the CLI."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage import losses, rendering  # noqa: E402
from nerf_stage import occupancy as occupancy_module  # noqa: E402
from nerf_stage import trainer as trainer_module  # noqa: E402
from nerf_stage.cameras import Intrinsics, orbit_poses, rig_poses  # noqa: E402
from nerf_stage.cli import main  # noqa: E402
from nerf_stage.config import BAKE_FACTOR, GridConfig, MLPConfig, TrainConfig  # noqa: E402
from nerf_stage.data import join_weights, load_dataset  # noqa: E402
from nerf_stage.editing import read_render  # noqa: E402
from nerf_stage.fields import GridField, MLPField  # noqa: E402
from nerf_stage.fields.base import RaySampling  # noqa: E402
from nerf_stage.fields.grid import _corners, _Trilinear  # noqa: E402
from nerf_stage.metrics import psnr  # noqa: E402
from nerf_stage.occupancy import OccupancyGrid  # noqa: E402
from nerf_stage.rendering import composite, render_rays  # noqa: E402
from nerf_stage.run import CHECKPOINT, load_run  # noqa: E402
from nerf_stage.scene_box import scene_box, visual_hull  # noqa: E402
from nerf_stage.trainer import train  # noqa: E402
from palette_core.cli.decompose import main as decompose  # noqa: E402
from palette_core.errors import InputError  # noqa: E402
from palette_core.stack import read_stack  # noqa: E402

from .helpers import expect_error  # noqa: E402

TINY = {"occupancy_voxels": 6**3, "batch_rays": 64, "head_width": 16, "checkpoint_every": 2,
        "grid": GridConfig(voxels=12**3, warmup_iters=1, occupancy_every=1),
        "mlp": MLPConfig(samples=8)}


#: The paper's per-sample diffuse colours, which bake.
PER_SAMPLE = replace(TINY["grid"], deferred=False, view_frequencies=None)
PER_SAMPLE_FLAGS = ["--no-grid-deferred", "--grid-view-frequencies", "none"]


def tiny_config(**changes) -> TrainConfig:
    return TrainConfig(**(TINY | {"pretrain_iters": 2, "finetune_iters": 2} | changes))


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    """16x16 Cornell box (transport weights, order 2, 15 terms)."""
    out = tmp_path_factory.mktemp("nerf") / "cb"
    assert main(["simulate", "cornell-box", str(out), "--resolution", "16", "--spp", "4",
                 "--views", "4", "1", "2"]) == 0
    return out


@pytest.fixture(scope="module")
def still_life(tmp_path_factory):
    """16x16 still life with an additive stack decomposed from its training views."""
    out = tmp_path_factory.mktemp("nerf") / "sl"
    assert main(["simulate", "still-life", str(out), "--resolution", "16", "--spp", "2",
                 "--views", "4", "1", "2"]) == 0
    assert decompose([str(out / "train"), "-k", "4", "-o", str(out / "weights.npz")]) == 0
    return out


def trained(root, config, rundir, **kwargs):
    """Train on the CPU unless ``device`` says otherwise: bit-for-bit comparisons between
    runs need its deterministic kernels (CUDA's atomic adds reorder sums)."""
    dataset = load_dataset(root, config.background)
    return train(config, dataset, read_stack(root / "weights.npz"), rundir, progress=False,
                 **({"device": torch.device("cpu")} | kwargs))


# --- compositing and fields ------------------------------------------------------------------

def test_m_channel_compositing_equals_rgb_compositing_for_one_hot_weights(rng):
    sigma = torch.as_tensor(rng.uniform(0, 3, (5, 7)))
    deltas = torch.as_tensor(rng.uniform(0.05, 0.3, (5, 7)))
    palette = torch.as_tensor(rng.uniform(0, 1, (4, 3)))
    one_hot = torch.nn.functional.one_hot(torch.as_tensor(rng.integers(0, 4, (5, 7))), 4)
    weights, _ = composite(sigma, deltas)
    composited_weights = (weights[..., None] * one_hot).sum(1)
    composited_rgb = (weights[..., None] * (one_hot.double() @ palette)).sum(1)
    assert torch.allclose(composited_weights.double() @ palette, composited_rgb)
    assert torch.all(weights.sum(1) <= 1)


def small_grid(extent, voxels: int, features: int, head_width: int, kind="rgb", channels=3):
    """A per-sample, diffuse grid field of one hidden layer."""
    settings = GridConfig(voxels=voxels, features=features, view_frequencies=None,
                          deferred=False, head_layers=1)
    return GridField(extent, settings, head_width, kind, channels)


@pytest.mark.parametrize("kind", ["additive", "transport"])
@pytest.mark.parametrize("make", [lambda k, c: MLPField(None, MLPConfig(), 16, k, c),
                                  lambda k, c: small_grid([1, 1, 0.5], 6**3, 4, 16, k, c)])
def test_output_activations(make, kind, rng):
    field = make(kind, 6)
    x = torch.as_tensor(rng.uniform(-1, 1, (50, 3)), dtype=torch.float32)
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    sigma, h = field.density(x)
    values = field.colour(h, d)
    assert values.shape == (50, 6) and torch.all(values >= 0) and torch.all(sigma >= 0)
    if kind == "additive":
        assert torch.allclose(values.sum(-1), torch.ones(50), atol=1e-6)


def test_grid_interpolation_has_the_gradient_of_a_weighted_gather(rng):
    field = small_grid([1, 1, 0.5], 5**3, 3, 8).double()
    table = field.feature_grid  # (C, N)
    x = torch.as_tensor(rng.uniform(-1, 1, (40, 3)))
    index, weight = _corners(x, field.extent, field.resolution, field.CORNERS)
    assert torch.autograd.gradcheck(lambda t: _Trilinear.apply(t, index, weight), (table,))
    expected = (table.t()[index] * weight[..., None]).sum(1)
    assert torch.allclose(_Trilinear.apply(table, index, weight), expected)


def test_renders_march_at_half_the_training_step():
    field = GridField([1, 1, 1], GridConfig(voxels=8**3, features=3), 8)
    assert field.sampling(render=True).step == pytest.approx(field.sampling().step / 2)


def test_visual_hull_keeps_the_objects(still_life):
    data = load_dataset(still_life)
    train_ids = data.indices("train")
    box = scene_box(data.poses[train_ids], data.intrinsics, data.alpha[train_ids])
    hull = visual_hull(box, np.array([16, 16, 16]), data.poses[train_ids], data.intrinsics,
                       data.alpha[train_ids])
    for centre in ([0.7, 0.5, -0.4], [-0.7, 0.4, -0.5], [1.1, 0.25, 0.7]):  # globe, box, ball
        cell = np.floor((np.array(centre) - box.centre + box.half) / (2 * box.half) * 16)
        assert hull[tuple(cell.astype(int))]
    assert 0 < hull.mean() < 1


def test_occupancy_bounds_frame_the_occupied_cells():
    grid = OccupancyGrid(torch.tensor([1.0, 0.5, 1.0]), 8 * 4 * 8)
    assert np.allclose(grid.bounds(), [[-1, -0.5, -1], [1, 0.5, 1]])  # all occupied
    grid.occupied.zero_()
    grid.occupied[2, 1, 7] = True
    assert np.allclose(grid.bounds(), [[-0.5, -0.25, 0.75], [-0.25, 0.0, 1.0]])


def test_orbit_sweeps_the_front_arc_and_looks_at_the_centre():
    poses = rig_poses("front-arc", 10, [0, 1, 0], 4.0, (0, 10), 60)
    orbit = orbit_poses(poses, 12, [0, 1, 0])
    eyes = orbit[:, :3, 3] - [0, 1, 0]
    azimuth = np.degrees(np.arctan2(eyes[:, 0], eyes[:, 2]))
    assert azimuth.min() >= -27.5 and azimuth.max() <= 27.5 and np.ptp(azimuth) > 50
    assert np.allclose(np.linalg.norm(eyes, axis=1), 4.0)
    assert np.allclose(np.einsum("ni,ni->n", -orbit[:, :3, 2], -eyes / 4.0), 1)


# --- training --------------------------------------------------------------------------------

@pytest.mark.parametrize("backbone", ["grid", "mlp"])
def test_fine_tuning_leaves_the_density_part_bit_identical(cornell, tmp_path, backbone):
    two_stage = trained(cornell, tiny_config(backbone=backbone), tmp_path / "a")
    pretrained = trained(cornell, tiny_config(backbone=backbone, strategy="rgb",
                                              pretrain_iters=2, finetune_iters=0), tmp_path / "b")
    for after, before in zip(two_stage.field.density_parameters(),
                             pretrained.field.density_parameters()):
        assert torch.equal(after, before)
    assert not torch.equal(two_stage.field.colour_parameters()[0],
                           pretrained.field.colour_parameters()[0])
    assert two_stage.field.kind == "transport" and two_stage.field.output.out_features == 15


def test_additive_renders_sum_to_the_opacity(still_life, tmp_path):
    run = trained(still_life, tiny_config(strategy="traditional"), tmp_path / "run")
    data = load_dataset(still_life)
    weights, opacity = run.render(data.poses[data.indices("test")])
    assert weights.shape == (2, 16, 16, 4) and np.all(weights >= 0)
    assert np.allclose(weights.sum(-1), opacity, atol=1e-5)


def test_a_supersampled_pixel_is_the_mean_of_a_finer_cameras_pixels(still_life, tmp_path):
    """With n = 2 a pixel averages the rays a camera of twice the resolution has through the
    centres of its 2 x 2 sub-pixels; additive weights still sum to the opacity."""
    run = trained(still_life, tiny_config(supersampling=2), tmp_path / "run")
    poses = load_dataset(still_life).poses[:2]
    weights, opacity = run.render(poses)
    k = run.intrinsics
    finer = Intrinsics(2 * k.width, 2 * k.height, 2 * k.fx, 2 * k.fy, 2 * k.cx, 2 * k.cy)
    one_ray = replace(run, config=replace(run.config, supersampling=1))
    fine_weights, fine_opacity = one_ray.render(poses, intrinsics=finer)
    blocks = fine_weights.reshape(2, 16, 2, 16, 2, -1).mean((2, 4))
    assert weights.shape == (2, 16, 16, 4) and np.allclose(weights, blocks, atol=1e-6)
    assert np.allclose(opacity, fine_opacity.reshape(2, 16, 2, 16, 2).mean((2, 4)), atol=1e-6)
    assert np.allclose(weights.sum(-1), opacity, atol=1e-5)


@pytest.mark.parametrize("scene", ["cornell", "still_life"])
def test_baked_renders_approach_the_network_as_the_bake_gets_finer(scene, request, tmp_path):
    """Same opacity at every factor (the baked grid divides the field's cells), weights
    non-negative (summing to the opacity for additive stacks), colours closer to the
    network's the finer the bake."""
    root = request.getfixturevalue(scene)
    run = trained(root, tiny_config(pretrain_iters=20, finetune_iters=20, grid=PER_SAMPLE),
                  tmp_path / "run")
    poses = load_dataset(root).poses[:2]
    weights, opacity = run.render(poses)
    agreement = []
    for factor in (1, 2, 4):
        baked_weights, baked_opacity = run.baked(factor).render(poses)
        assert np.abs(baked_opacity - opacity).max() < 1e-5 and np.all(baked_weights >= 0)
        if run.basis == "additive":
            assert np.allclose(baked_weights.sum(-1), baked_opacity, atol=1e-5)
        agreement.append(psnr(*(np.clip(w @ run.terms, 0, 1) for w in (baked_weights, weights))))
    assert agreement == sorted(agreement) and agreement[-1] > 22


def test_only_per_sample_diffuse_grids_bake(cornell, tmp_path):
    for name, backbone, grid in (("mlp", "mlp", PER_SAMPLE), ("deferred", "grid", TINY["grid"]),
                                 ("view", "grid", replace(PER_SAMPLE, view_frequencies=2))):
        run = trained(cornell, tiny_config(backbone=backbone, grid=grid, pretrain_iters=1,
                                           finetune_iters=1), tmp_path / name)
        with pytest.raises(InputError, match="be baked"):
            run.baked()


def test_transport_loss_tone_maps_emitters():
    loss = losses.weight_loss
    lamp, twice = torch.tensor([[30.0, 0.2]]), torch.tensor([[60.0, 0.2]])
    assert loss("transport", twice, lamp) < 2e-4  # a lamp at twice its radiance: both white
    assert loss("transport", torch.tensor([[1.0, 0.0]]), torch.zeros(1, 2)) == 0.125
    assert loss("additive", twice, lamp) == 450.0


def test_colours_through_the_weights_are_compared_as_recorded():
    images = torch.tensor([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    lamp = torch.tensor([[30.0, 30.0, 30.0], [0.5, 0.5, 0.5]], requires_grad=True)
    loss = losses.recorded_rgb_loss(lamp, images)
    loss.backward()
    assert loss == 0 and not lamp.grad.any()  # a saturated pixel is matched by any radiance
    assert losses.recorded_rgb_loss(torch.full((1, 3), 0.25), images[1:]) == 0.0625


@pytest.mark.parametrize("scene", ["cornell", "still_life"])
def test_the_new_output_layer_is_fitted_before_fine_tuning(scene, request, tmp_path):
    root = request.getfixturevalue(scene)
    config = tiny_config(strategy="rgb", pretrain_iters=4, finetune_iters=0, batch_rays=1024)
    run = trained(root, config, tmp_path / "run")
    dataset, stack = load_dataset(root), read_stack(root / "weights.npz")
    train_ids = dataset.indices("train")
    weights = join_weights(dataset, stack)
    if stack.basis == "additive":
        weights = weights * dataset.alpha[train_ids, ..., None]
    rays = trainer_module._ray_bank(run, dataset, train_ids, weights, torch.device("cpu"))

    def batch_loss():
        with torch.no_grad():
            values, _, _ = run.render_pixels(rays["origins"], rays["directions"])
            return float(losses.weight_loss(run.field.kind, values, rays["weights"]))

    trainer_module._start_finetune(run)
    fresh = batch_loss()
    trainer_module._fit_output(run, rays, torch.Generator().manual_seed(0))
    assert batch_loss() < 0.75 * fresh


def test_resume_gives_the_uninterrupted_result(cornell, tmp_path, monkeypatch):
    config = tiny_config(pretrain_iters=3, finetune_iters=3)
    whole = trained(cornell, config, tmp_path / "whole")
    save = trainer_module.save_checkpoint

    def save_then_stop(run, path, optimisers, generator):
        save(run, path, optimisers, generator)
        if run.record.iteration == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(trainer_module, "save_checkpoint", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        trained(cornell, config, tmp_path / "resumed")
    monkeypatch.setattr(trainer_module, "save_checkpoint", save)
    resumed = trained(cornell, config, tmp_path / "resumed", resume=True)
    for a, b in zip(whole.field.state_dict().values(), resumed.field.state_dict().values()):
        assert torch.equal(a, b)
    assert [e["loss"] for e in whole.record.log] == [e["loss"] for e in resumed.record.log]


def test_a_run_with_other_optimisers_does_not_resume(cornell, tmp_path):
    config = tiny_config(pretrain_iters=1, finetune_iters=1)
    trained(cornell, config, tmp_path / "run")
    path = tmp_path / "run" / CHECKPOINT
    state = torch.load(path, weights_only=True)
    state["optimisers"].append(state["optimisers"][0])  # grids had a SparseAdam of their own
    torch.save(state, path)
    with pytest.raises(InputError, match="other optimisers"):
        trained(cornell, config, tmp_path / "run", resume=True)


# --- command line ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cornell_run(cornell, tmp_path_factory):
    rundir = tmp_path_factory.mktemp("runs") / "cb"
    args = ["train", str(cornell), "--weights", str(cornell / "weights.npz"), "-o", str(rundir),
            "--pretrain-iters", "2", "--finetune-iters", "2", "--batch-rays", "64",
            "--grid-voxels", str(12**3), "--head-width", "16"]
    assert main(args) == 0
    return rundir, args


@pytest.fixture(scope="module")
def per_sample_run(cornell_run, tmp_path_factory):
    """``cornell_run`` with the paper's per-sample diffuse colours."""
    _, args = cornell_run
    rundir = tmp_path_factory.mktemp("runs") / "per-sample"
    args = [*args[:args.index("-o") + 1], str(rundir), *args[args.index("-o") + 2:]]
    assert main([*args, *PER_SAMPLE_FLAGS]) == 0
    config = load_run(rundir).config.grid
    assert not config.deferred and config.view_frequencies is None
    return rundir


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
    assert decompose([str(still_life / "test"), "-k", "4", "-o", str(partial)]) == 0
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


# --- hostile run folders ---------------------------------------------------------------------

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


@pytest.mark.parametrize("loss", ["rgb_weight", "sparsity_weight"])
def test_loss_weights_are_non_negative(loss):
    assert getattr(TrainConfig(), loss) > 0
    with pytest.raises(InputError, match=loss):
        TrainConfig(**{loss: -1.0})


def test_learning_rates_decay_to_lr_decay_over_each_stage():
    config = tiny_config(pretrain_iters=4, finetune_iters=2, lr_decay=0.25)
    rates = []
    for it in range(6):
        if it in (0, 4):  # each stage starts with new optimisers
            optimiser = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=0.1)
        trainer_module._decay_learning_rates([optimiser], config, it)
        rates.append(optimiser.param_groups[0]["lr"])
    assert rates == pytest.approx([0.1, 0.1 * 0.25**0.25, 0.05, 0.1 * 0.25**0.75, 0.1, 0.05])
    with pytest.raises(InputError, match="lr_decay"):
        TrainConfig(lr_decay=0)


def test_deferred_is_a_boolean():
    assert TrainConfig.from_dict(TrainConfig().to_dict()) == TrainConfig()
    with pytest.raises(InputError, match="deferred must be true or false"):
        TrainConfig.from_dict({"grid": {"deferred": "yes"}})


def test_renders_read_the_feature_grid_as_it_is_after_each_step(rng):
    """Reads in eval mode without gradients gather from a row-major copy of the grid
    (``GridField._feature_rows``): it must follow optimiser steps and loading."""
    field = small_grid([1, 1, 0.5], 5**3, 3, 8)
    x = torch.as_tensor(rng.uniform(-1, 1, (40, 3)), dtype=torch.float32)
    optimiser = torch.optim.Adam(field.parameters(), lr=0.1, fused=True)
    before = []
    for _ in range(2):
        field.train()
        expected = field.read(x)[1]
        expected.sum().backward()
        field.eval()
        with torch.no_grad():
            before.append(field.read(x)[1])
        assert torch.allclose(before[-1], expected)
        optimiser.step()
    assert not torch.equal(*before)
    field.load_state_dict({key: value + 1 for key, value in field.state_dict().items()
                           if key.endswith("grid")}, strict=False)
    with torch.no_grad():
        assert torch.allclose(field.read(x)[1], field.train().read(x)[1])


def test_the_sparsity_prior_is_steep_for_fog_and_flat_for_surfaces():
    optical = torch.tensor([0.0, 0.005, 0.01, 3.0, 30.0], requires_grad=True)
    losses.sparsity_loss(optical).backward()
    fog, surface = optical.grad[1:3], optical.grad[3:]
    assert optical.grad[0] == 0 and fog.min() > 20 * surface.max() > 0
    assert losses.sparsity_loss(torch.zeros(0)) == 0


class _Sphere:
    """An opaque ball of radius 0.5 that shows its positions as colours."""

    deferred = False

    def __init__(self, radius: float = 0.5, density: float = 1e3):
        self.radius, self.sigma = radius, density
        self.shaded = 0  # points the colour part ran at

    def density(self, x):
        return self.sigma * (x.norm(dim=-1) < self.radius).float(), x

    def colour(self, h, d):
        self.shaded += len(h)
        return h


def test_deferred_shading_runs_the_colour_part_once_a_ray():
    """A linear colour part shades alike per sample and deferred, also through fog that
    leaves rays part transparent; deferred shading runs it once a ray."""
    occupancy = OccupancyGrid(torch.ones(3), 8**3)
    origins = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.3, 0.1], [-3.0, 0.9, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    per_sample, deferred = _Sphere(0.6, 0.5), _Sphere(0.6, 0.5)
    deferred.deferred = True
    with torch.no_grad():
        expected, samples = render_rays(per_sample, occupancy, origins, directions,
                                        RaySampling(step=0.01))
        values, _ = render_rays(deferred, occupancy, origins, directions, RaySampling(step=0.01))
    assert 0.1 < samples.opacity[0] < 0.9 and samples.opacity[2] == 0
    assert torch.allclose(values, expected, atol=1e-5)
    assert deferred.shaded == 3 and per_sample.shaded > 100


def test_rendering_stops_rays_at_surfaces_and_keeps_their_values():
    occupancy = OccupancyGrid(torch.ones(3), 8**3)
    origins = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.2, 0.1], [-3.0, 0.9, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    sampling = RaySampling(step=0.01)
    with torch.no_grad():
        values, samples = render_rays(_Sphere(), occupancy, origins, directions, sampling)
    unstopped, all_samples = render_rays(_Sphere(), occupancy, origins, directions, sampling)
    assert torch.allclose(values, unstopped, atol=1e-4)
    assert torch.allclose(samples.opacity, torch.tensor([1.0, 1.0, 0.0]), atol=1e-4)
    marched, unstopped_marched = (torch.bincount(s.ray, minlength=3).tolist()
                                  for s in (samples, all_samples))
    assert unstopped_marched == [200] * 3  # 2 units of box at steps of 0.01
    assert marched[0] < 100 and marched[1] < 100 and marched[2] == 200


def test_empty_space_is_skipped_in_whole_steps_and_renders_stay_the_same(monkeypatch, rng):
    occupancy = OccupancyGrid(torch.ones(3), 16**3)
    centres = -1 + (torch.nonzero(torch.ones(16, 16, 16)) + 0.5) / 8
    occupancy.occupied = (centres.norm(dim=-1) < 0.6).reshape(16, 16, 16)
    ahead = torch.as_tensor(rng.normal(size=(64, 3)), dtype=torch.float32)
    origins = -3 * ahead / ahead.norm(dim=-1, keepdim=True)
    targets = torch.as_tensor(rng.uniform(-0.8, 0.8, (64, 3)), dtype=torch.float32)
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far = rendering.box_intersection(origins, directions, occupancy.extent)
    moved = occupancy.skip_empty(origins, directions, near, far, 0.01)
    steps = ((moved - near) / 0.01)[moved < far]  # the others get no samples at all
    assert torch.allclose(steps, steps.round(), atol=1e-3) and (steps >= 0).all()
    t = torch.arange(0, 5, 1e-3)
    inside = torch.stack([occupancy.lookup(o + t[:, None] * d)
                          for o, d in zip(origins, directions)])
    meets = inside.any(1)  # rays that cross an occupied cell, and where they first do
    first = t[inside.int().argmax(1)]
    assert meets.any() and (~meets).any()
    assert (moved[meets] <= first[meets]).all()
    stop = origins + torch.minimum(moved, far - 1e-4)[:, None] * directions
    u = ((stop + 1) * 8).long().clamp(0, 15)
    beside = occupancy.free_distance()[u[:, 0], u[:, 1], u[:, 2]] <= 1
    assert ((moved == far) | beside).all()  # rays stop skipping only beside an occupied cell
    corner, x = torch.tensor([[-3.0, 0.95, 0.95]]), torch.tensor([[1.0, 0.0, 0.0]])
    entry, exit_ = rendering.box_intersection(corner, x, occupancy.extent)
    assert occupancy.skip_empty(corner, x, entry, exit_, 0.01) == exit_  # far from every cell
    with torch.no_grad():
        skipped = render_rays(_Sphere(), occupancy, origins, directions, RaySampling(step=0.01))
        monkeypatch.setattr(occupancy_module, "MAX_SKIPS", 0)
        marched = render_rays(_Sphere(), occupancy, origins, directions, RaySampling(step=0.01))
    assert torch.allclose(skipped[0], marched[0], atol=1e-4)
    assert torch.allclose(skipped[1].opacity, marched[1].opacity, atol=1e-4)


def test_the_free_distance_follows_the_occupied_cells():
    occupancy = OccupancyGrid(torch.ones(3), 8**3)
    occupancy.occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    assert (occupancy.free_distance() > 8 * 3**0.5).all()  # nothing occupied: rays skip the box
    occupancy.occupied[0, 0, 0] = True
    assert occupancy.free_distance()[7, 7, 7] == 7 and occupancy.free_distance()[0, 0, 0] == 0
