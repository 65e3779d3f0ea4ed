"""Training weight NeRFs: the frozen density part, supersampling, bakes, losses, the output
layer fitted before fine-tuning, learning-rate decay, resume, the config's checks, the
colour-corrected score."""

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage.data.cameras import Intrinsics  # noqa: E402
from nerf_stage.data.dataset import join_weights, load_dataset  # noqa: E402
from nerf_stage.train import field_steps, losses, schedule  # noqa: E402
from nerf_stage.train import trainer as trainer_module  # noqa: E402
from nerf_stage.train.checkpoint import CHECKPOINT  # noqa: E402
from nerf_stage.train.config import TrainConfig  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402
from nerf_stage.train.metrics import image_scores, psnr  # noqa: E402
from palette_core.basis import Basis  # noqa: E402
from palette_core.errors import InputError  # noqa: E402
from palette_core.stack import read_stack  # noqa: E402

from .nerf_runs import PER_SAMPLE, TINY, tiny_config, trained  # noqa: E402


@pytest.mark.parametrize("backbone", ["grid", "mlp", "hash"])
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


def test_a_hash_run_learns_saves_and_renders_as_trained(still_life, tmp_path):
    config = tiny_config(backbone="hash", strategy="rgb", pretrain_iters=30, finetune_iters=0,
                         batch_rays=256)
    run = trained(still_life, config, tmp_path / "run")
    psnrs = [entry["psnr"] for entry in run.record.log]
    assert np.mean(psnrs[-5:]) > np.mean(psnrs[:5]) + 1
    poses = load_dataset(still_life).poses[:1]
    loaded = load_run(tmp_path / "run", torch.device("cpu"))
    assert all(np.array_equal(a, b) for a, b in zip(run.render(poses), loaded.render(poses)))


def test_additive_renders_sum_to_the_opacity(still_life, tmp_path):
    run = trained(still_life, tiny_config(strategy="traditional"), tmp_path / "run")
    data = load_dataset(still_life)
    weights, opacity = run.render(data.poses[data.indices("test")])
    assert weights.shape == (2, 16, 16, 4) and np.all(weights >= 0)
    assert np.allclose(weights.sum(-1), opacity, atol=1e-5)


def test_a_render_is_the_same_in_any_chunk_of_rays(still_life, tmp_path, monkeypatch):
    """``RENDER_CHUNK`` (rays a forward pass, by device) changes how a view is cut up,
    not what it shows: a chunk of 37 rays (a view's 256 in seven, the last short) renders
    what one chunk does, samples included."""
    from nerf_stage.train import run as run_module

    run = trained(still_life, tiny_config(), tmp_path / "run")
    poses = load_dataset(still_life).poses[:2]
    whole = run.render(poses, samples=True)
    monkeypatch.setitem(run_module.RENDER_CHUNK, "cpu", 37)
    cut = run.render(poses, samples=True)
    assert np.allclose(whole[0], cut[0], atol=1e-6) and np.allclose(whole[1], cut[1], atol=1e-6)
    for name in ("pixel", "point", "weight"):
        assert np.allclose(getattr(whole[2], name), getattr(cut[2], name), atol=1e-6)


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

    field_steps.start_palette_stage(run)
    fresh = batch_loss()
    field_steps.fit_output(run, rays, torch.Generator().manual_seed(0))
    assert batch_loss() < 0.75 * fresh


@pytest.mark.parametrize("scene, appearance", [("cornell", False), ("cornell", True),
                                               ("still_life", True)])
def test_resume_gives_the_uninterrupted_result(scene, appearance, tmp_path, monkeypatch,
                                               request):
    """Transport weights, and additive ones whose palette stage recomputes its targets."""
    root = request.getfixturevalue(scene)
    config = tiny_config(pretrain_iters=3, finetune_iters=3, appearance=appearance)
    whole = trained(root, config, tmp_path / "whole")
    save = field_steps.save_checkpoint

    def save_then_stop(run, path, optimisers, generator):
        save(run, path, optimisers, generator)
        if run.record.iteration == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(field_steps, "save_checkpoint", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        trained(root, config, tmp_path / "resumed")
    monkeypatch.setattr(field_steps, "save_checkpoint", save)
    resumed = trained(root, config, tmp_path / "resumed", resume=True)
    for a, b in zip(whole.field.state_dict().values(), resumed.field.state_dict().values()):
        assert torch.equal(a, b)
    assert [e["loss"] for e in whole.record.log] == [e["loss"] for e in resumed.record.log]
    saved = torch.load(tmp_path / "whole" / CHECKPOINT, weights_only=True)
    assert ("appearance" in saved) == appearance
    if appearance:
        assert torch.equal(whole.appearance.affine, resumed.appearance.affine)
        assert saved["appearance"]["affine"].shape[1:] == (3, 4)


def test_colour_transforms_learn_each_images_exposure_around_the_average():
    from nerf_stage.train.appearance import Appearance

    torch.manual_seed(0)
    gains = torch.tensor([0.7, 1.0, 1.3])  # their mean is the identity's
    appearance = Appearance(3)
    optimiser = torch.optim.Adam(appearance.parameters(), lr=0.01)
    for _ in range(300):
        rgb, image = torch.rand(256, 3), torch.randint(3, (256,))
        loss = torch.mean((appearance(rgb, image) - gains[image, None] * rgb) ** 2)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    learnt = appearance(torch.eye(3).repeat(3, 1), torch.arange(3).repeat_interleave(3))
    assert torch.allclose(learnt.view(3, 3, 3), gains[:, None, None] * torch.eye(3), atol=0.02)


def test_the_palette_stage_fits_the_weights_of_colours_with_their_exposure_undone(still_life):
    """Two photos of one scene, one at 1.25 and one at 0.75 of the exposure: the palette
    stage's targets are the weights of the scene's own colours, and a transport stack (whose
    weights are not a function of colour) keeps its own."""
    from nerf_stage.train.appearance import Appearance, exposure_free_weights
    from palette_core.weights import palette_weights

    stack = read_stack(still_life / "weights.npz")
    appearance = Appearance(2)
    with torch.no_grad():
        appearance.affine[:, :, :3] *= torch.tensor([1.25, 0.75])[:, None, None]
    colours = torch.tensor(stack.palette).mean(0) + 0.1 * torch.rand(64, 3) - 0.05
    image, alpha = torch.arange(2).repeat(32), torch.ones(64)
    recorded = appearance(colours, image).detach()
    assert torch.allclose(appearance.undo(recorded, image), colours, atol=1e-6)
    weights = exposure_free_weights(appearance, stack, recorded, image, alpha)
    truth = palette_weights(colours.double().numpy(), stack.palette, stack.hull_faces)
    assert np.allclose(weights.numpy(), truth, atol=1e-5)
    transport = replace(stack, basis=Basis.TRANSPORT)
    assert exposure_free_weights(appearance, transport, recorded, image, alpha) is None


def test_a_run_with_other_optimisers_does_not_resume(cornell, tmp_path):
    config = tiny_config(pretrain_iters=1, finetune_iters=1)
    trained(cornell, config, tmp_path / "run")
    path = tmp_path / "run" / CHECKPOINT
    state = torch.load(path, weights_only=True)
    state["optimisers"].append(state["optimisers"][0])  # grids had a SparseAdam of their own
    torch.save(state, path)
    with pytest.raises(InputError, match="other optimisers"):
        trained(cornell, config, tmp_path / "run", resume=True)


def test_a_wall_clock_limit_ends_each_stage_at_its_share(cornell, tmp_path):
    config = tiny_config(pretrain_iters=50, finetune_iters=50, minutes=1e-9, fill_minutes=False)
    run = trained(cornell, config, tmp_path / "run")  # each stage's first iteration only
    assert [entry["iteration"] for entry in run.record.log] == [1, 51]
    assert run.record.iteration == 100 and run.field.kind == "transport"
    assert schedule.next_iteration(config, 7, 0.0) == 7  # within the limit
    assert schedule.next_iteration(replace(config, minutes=0.0), 7, 1e9) == 7
    with pytest.raises(InputError, match="minutes"):
        TrainConfig(minutes=-1.0)
    # subnormals, flushed to zero while training, are back after it
    assert float(torch.tensor(1e-40) * torch.tensor(1.0)) > 0


def test_minutes_plan_the_iterations_and_the_clock_ends_the_run(cornell, tmp_path):
    """Under ``--minutes`` a fresh run plans its iterations from a probe of its first stage
    (``budget``): the clock, not the iterations, ends it, at the budget; the run's config is
    the plan, which ``--resume`` with the config asked for accepts."""
    from nerf_stage.train import budget

    config = tiny_config(backbone="grid", minutes=0.02)
    run = trained(cornell, config, tmp_path / "run")
    assert not run.config.fill_minutes and run.config.total_iters > 10 * budget.PROBE_ITERS
    assert run.record.log[-1]["seconds"] >= 60 * config.minutes
    assert len(run.record.log) < run.config.total_iters  # the clock ended both stages
    assert budget.plans_like(run.config, config)
    assert not budget.plans_like(run.config, replace(config, seed=1))
    resumed = trained(cornell, config, tmp_path / "run", resume=True)
    assert resumed.record.log == run.record.log
    share = budget.planned(config, 10.0)
    assert share.pretrain_iters / share.total_iters == pytest.approx(0.5, abs=0.01)
    assert share.pretrain_minutes == pytest.approx(0.01)


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
        schedule.set_rates([optimiser], schedule.stage_progress(config, it, []),
                           lambda g: g.setdefault("initial_lr", g["lr"]), lambda g: 0.25)
        rates.append(optimiser.param_groups[0]["lr"])
    assert rates == pytest.approx([0.1, 0.1 * 0.25**0.25, 0.05, 0.1 * 0.25**0.75, 0.1, 0.05])
    with pytest.raises(InputError, match="lr_decay"):
        TrainConfig(lr_decay=0)


def test_under_a_wall_clock_limit_a_stage_progresses_with_its_time_too():
    """Two stages of 10 iterations in a minute: pretraining's share is 30 s; it ended by the
    clock after 5 iterations (31 s), and fine-tuning has the 29 s left."""
    config = tiny_config(pretrain_iters=10, finetune_iters=10, minutes=1.0)
    log = [{"iteration": i, "seconds": 6.2 * i} for i in range(1, 6)]
    progress = schedule.stage_progress
    assert progress(config, 2, log[:1]) == pytest.approx(6.2 / 30)  # time ahead of 2 / 10
    assert progress(config, 4, log[:1]) == pytest.approx(0.4)  # iterations ahead of time
    log += [{"iteration": 11, "seconds": 38.25}, {"iteration": 12, "seconds": 45.5}]
    assert progress(config, 12, log) == pytest.approx((45.5 - 31) / 29)
    assert progress(config, 12, log + [{"iteration": 13, "seconds": 99.0}]) == 1.0
    assert progress(replace(config, minutes=0.0), 12, log) == pytest.approx(0.2)


def test_pretraining_may_have_a_time_limit_of_its_own():
    """Pretraining limited to 15 s of a minute ends then, whatever P / (P + F) is, and
    fine-tuning planned far longer than it can run has the rest and is ended by the clock."""
    config = tiny_config(pretrain_iters=10, finetune_iters=1000, minutes=1.0,
                         pretrain_minutes=0.25)
    step = schedule.next_iteration
    assert step(config, 3, 14.9) == 3 and step(config, 3, 15.0) == 10  # pretraining's end
    assert step(config, 12, 59.9) == 12 and step(config, 12, 60.0) == 1010
    log = [{"iteration": i, "seconds": 5.0 * i} for i in range(1, 4)]  # ended by the clock
    assert schedule.stage_progress(config, 2, log[:1]) == pytest.approx(5 / 15)
    log.append({"iteration": 11, "seconds": 37.5})
    assert schedule.stage_progress(config, 11, log) == pytest.approx(22.5 / 45)
    untimed = replace(config, minutes=0.0)  # pretraining's limit alone
    assert step(untimed, 3, 15.0) == 10 and step(untimed, 12, 1e9) == 12
    with pytest.raises(InputError, match="pretrain_minutes"):
        TrainConfig(minutes=1.0, pretrain_minutes=2.0)


def test_a_backbones_table_entry_gives_its_config_section_and_flags():
    """``TrainConfig`` and ``nerf-stage train`` follow ``BACKBONES``: a section of the entry's
    settings per backbone, its flags, and in ``config.json`` the chosen backbone's only."""
    import argparse
    from dataclasses import fields

    from nerf_stage.backbones import BACKBONES
    from palette_core.cli import add_config_arguments

    parser = argparse.ArgumentParser()
    add_config_arguments(parser, TrainConfig())
    flags = set(vars(parser.parse_args([])))
    for name, spec in BACKBONES.items():
        assert isinstance(getattr(TrainConfig(), name), spec.settings)
        assert {f"{name}_{f.name}" for f in fields(spec.settings)} <= flags
        assert set(TrainConfig(backbone=name).to_dict()) & set(BACKBONES) == {name}


def test_the_auto_backbone_is_the_splats_for_views_finer_than_the_grid(monkeypatch):
    """``--backbone auto`` chooses the splats for views at least twice as many pixels across
    as the grid has voxels, with points to start from, and the grid otherwise."""
    from types import SimpleNamespace

    from nerf_stage.train.trainer import choose_backbone

    def chosen(width, points=None, **changes):
        views = SimpleNamespace(images=np.zeros((2, width // 2, width, 3)), points=points)
        return choose_backbone(TrainConfig(**changes), views).backbone

    assert TrainConfig().backbone == "auto"
    assert chosen(191) == "grid" and chosen(192) == "splats"  # 96^3 voxels by default
    assert chosen(50, grid=TINY["grid"]) == "splats"  # 12 voxels across
    assert chosen(192, strategy="traditional") == "grid"
    assert chosen(100, backbone="hash") == "hash"
    monkeypatch.setattr(trainer_module.importlib.util, "find_spec", lambda name: None)
    assert chosen(192) == "grid"  # no pycolmap: nothing to start the splats from
    assert chosen(192, points=object()) == "splats"
    with pytest.raises(InputError, match="auto"):
        _ = TrainConfig().backbone_config


def test_a_run_of_the_auto_backbone_saves_the_one_chosen(cornell, tmp_path):
    run = trained(cornell, tiny_config(), tmp_path / "run")
    assert run.config.backbone == "grid"  # 16 x 16 views
    assert TrainConfig.load(tmp_path / "run" / "config.json").backbone == "grid"
    assert load_run(tmp_path / "run").config.backbone == "grid"
    resumed = trained(cornell, tiny_config(), tmp_path / "run", resume=True)  # auto again
    assert resumed.record.log == run.record.log


def test_a_config_saved_before_a_field_existed_reads_as_that_run_trained():
    """Runs saved before per-image appearance and the depth loss trained without them."""
    old = TrainConfig().to_dict()
    del old["appearance"], old["depth_weight"]
    config = TrainConfig.from_dict(old)
    assert config.appearance is False and config.depth_weight == 0
    assert TrainConfig.from_dict(TrainConfig().to_dict()).appearance is True


def test_deferred_is_a_boolean():
    assert TrainConfig.from_dict(TrainConfig().to_dict()) == TrainConfig()
    with pytest.raises(InputError, match="deferred must be true or false"):
        TrainConfig.from_dict({"grid": {"deferred": "yes"}})


def test_the_sparsity_prior_is_steep_for_fog_and_flat_for_surfaces():
    optical = torch.tensor([0.0, 0.005, 0.01, 3.0, 30.0], requires_grad=True)
    losses.sparsity_loss(optical).backward()
    fog, surface = optical.grad[1:3], optical.grad[3:]
    assert optical.grad[0] == 0 and fog.min() > 20 * surface.max() > 0
    assert losses.sparsity_loss(torch.zeros(0)) == 0


def test_a_ray_bank_that_cannot_fit_is_refused_up_front():
    from nerf_stage.train.trainer import _check_fits

    huge = np.broadcast_to(np.zeros(1, np.float32), (10**4, 10**4, 10**3, 4))  # no memory
    with pytest.raises(InputError, match="more than the"):
        _check_fits(huge, 1, torch.device("cpu"))
    _check_fits(np.zeros((2, 4, 4, 4), np.float32), 2, torch.device("cpu"))


def test_sparse_points_give_the_depth_of_the_pixels_that_see_them():
    """A camera at z = 3 looking down -z: a point at the centre is seen by the middle pixel
    at distance 3 (normalised by the box's scale), the one straight behind it is hidden,
    one behind the camera and one outside the view are not seen."""
    from nerf_stage.render.scene_box import SceneBox
    from nerf_stage.train.point_depth import point_targets

    camera = Intrinsics(8, 8, 4.0, 4.0, 4.0, 4.0)
    pose = np.eye(4)
    pose[2, 3] = 3.0
    points = np.array([[0.1, 0.1, 0.0], [0.1, 0.1, -1.0], [0.0, 0.0, 5.0], [9.0, 0.0, 0.0]])
    box = SceneBox(np.zeros(3), np.full(3, 1.5))
    pixels, targets = point_targets(points, pose[None], [camera], box)
    assert pixels.tolist() == [3 * 8 + 4]  # row 3 (y up is row down), column 4
    assert targets == pytest.approx([np.sqrt(0.02 + 9) / box.scale])
    far = SceneBox(np.zeros(3), np.full(3, 0.5), unbounded=True)
    beyond = np.array([[0.1, 0.1, -2.0]])  # past the box: the contracted parameter
    pixels, targets = point_targets(beyond, np.stack([pose, pose]), [camera] * 2, far)
    assert pixels.tolist() == [28, 64 + 28]
    offset = beyond[0] - pose[:3, 3]
    distance = np.linalg.norm(offset) / far.scale
    bend = (-1 - pose[2, 3] / far.scale) / (offset[2] / np.linalg.norm(offset))  # z = -1 exit
    assert distance > bend
    assert targets == pytest.approx([2 * bend - bend**2 / distance] * 2, rel=1e-5)


def test_the_depth_loss_is_zero_only_where_a_ray_ends_at_its_target():
    ray, t = torch.tensor([0, 0, 1, 1]), torch.tensor([1.0, 2.0, 1.0, 2.0])
    targets = torch.tensor([2.0, 2.0])
    assert losses.depth_loss(ray, t, torch.tensor([0.0, 1.0, 0.0, 1.0]), targets) == 0
    floater = losses.depth_loss(ray, t, torch.tensor([0.5, 0.5, 0.0, 1.0]), targets)
    assert floater == pytest.approx(0.25)


def test_a_depth_loss_run_trains_where_points_are_seen(cornell, tmp_path):
    """With points on the scene's surfaces and ``depth_weight``, the density trains on their
    depth too (another run than without); without points the setting changes nothing."""
    from nerf_stage.data.points import Points

    dataset = load_dataset(cornell)
    rng = np.random.default_rng(0)
    points = Points(rng.uniform(-1, 1, (200, 3)) * np.array([1, 1, 0.01]) - [0, 0, 0.9],
                    np.zeros((200, 3), np.float32))
    config = tiny_config(pretrain_iters=3, finetune_iters=1)
    stack = read_stack(cornell / "weights.npz")

    def density(data, settings, name):
        run = trainer_module.train(settings, data, stack, tmp_path / name, progress=False,
                                   device=torch.device("cpu"))
        return torch.cat([p.detach().flatten() for p in run.field.density_parameters()])

    plain = density(dataset, config, "plain")
    assert torch.equal(plain, density(dataset, replace(config, depth_weight=1.0), "none"))
    with_points = replace(dataset, points=points)
    assert not torch.equal(plain, density(with_points, replace(config, depth_weight=1.0), "d"))


def test_the_colour_corrected_score_forgives_exposure_not_content():
    truth = np.random.default_rng(0).random((1, 16, 16, 3))
    exposed = 0.6 * truth + 0.05  # darker, the same content
    shuffled = truth.reshape(-1, 3)[np.random.default_rng(1).permutation(256)].reshape(truth.shape)
    assert image_scores(exposed, truth, corrected=True)["psnr_cc"] > 60
    assert image_scores(exposed, truth)["psnr"] < 20
    assert image_scores(shuffled, truth, corrected=True)["psnr_cc"] < 12
