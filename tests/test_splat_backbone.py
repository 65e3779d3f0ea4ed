"""The ``splats`` backbone: spherical harmonics, weights on the simplex from every view,
densification's bounds, and a splat run that trains, saves, loads, renders, bakes and
exports (the rasteriser: ``test_rasterise.py``; the start: ``test_splat_start.py``)."""

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nerf_stage.backbone_settings import SplatConfig  # noqa: E402
from nerf_stage.cli import main  # noqa: E402
from nerf_stage.fields.base import ACTIVATIONS, RGB  # noqa: E402
from nerf_stage.splats import backbone, footprints, read_splats  # noqa: E402
from nerf_stage.splats.rasterise import draw  # noqa: E402
from nerf_stage.splats.run import GEOMETRY, SplatModel  # noqa: E402
from nerf_stage.splats.sh import SH_C0, sh_basis, sh_terms  # noqa: E402
from nerf_stage.splats.strategy import PIXELS_PER_SPLAT, Densification  # noqa: E402
from nerf_stage.train.checkpoint import CHECKPOINT  # noqa: E402
from nerf_stage.train.config import TrainConfig  # noqa: E402
from nerf_stage.train.loading import load_run  # noqa: E402
from palette_core.basis import Basis  # noqa: E402
from palette_core.errors import InputError  # noqa: E402
from palette_core.stack import WeightStack  # noqa: E402

from .helpers import expect_error  # noqa: E402
from .splat_cases import CAMERA, PIXELS, POSE, few_splats  # noqa: E402


def test_spherical_harmonics_are_orthonormal_over_the_sphere():
    """The basis integrates to the identity over the unit sphere (a Fibonacci grid of
    directions): the constants and signs are those of real spherical harmonics."""
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = torch.sqrt(1 - z * z)
    directions = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 1)
    basis = sh_basis(directions, 3)
    gram = basis.T @ basis * (4 * math.pi / n)
    assert basis.shape == (n, sh_terms(3)) and torch.allclose(gram, torch.eye(16, dtype=gram.dtype),
                                                                atol=1e-3)


def _palette_model(n=50, channels=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    tensors = {"means": torch.randn(n, 3, generator=g), "scales": torch.full((n, 3), -2.0),
               "quats": torch.randn(n, 4, generator=g), "opacities": torch.zeros(n),
               "colours": torch.zeros(n, 3), "colours_rest": torch.zeros(n, 15, 3)}
    model = SplatModel(tensors, RGB, 3)
    weights = torch.rand(n, channels, generator=g)
    model.set_output(Basis.ADDITIVE, weights / weights.sum(1, keepdim=True))
    with torch.no_grad():
        model.residual.normal_(0, 0.5, generator=g)  # a strong view dependence
    return model


def test_palette_weights_stay_on_the_simplex_from_every_view():
    model = _palette_model()
    assert not any(getattr(model, name).requires_grad for name in ("means", "scales"))
    for eye in torch.randn(20, 3, generator=torch.Generator().manual_seed(3)) * 5:
        weights = model.values(eye)
        assert torch.isfinite(weights).all() and weights.min() >= 0
        assert torch.allclose(weights.sum(1), torch.ones(len(weights)), atol=1e-5)
    assert torch.allclose(model.values(torch.zeros(3), 0).sum(1), torch.ones(50), atol=1e-5)


def _rgb_model(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    tensors = {"means": torch.randn(n, 3, generator=g), "scales": torch.full((n, 3), -2.0),
               "quats": torch.randn(n, 4, generator=g), "opacities": torch.zeros(n),
               "colours": torch.zeros(n, 3), "colours_rest": torch.zeros(n, 3, 3)}
    return SplatModel(tensors, RGB, 1)


def _optimiser(model):
    return torch.optim.Adam([{"name": name, "params": [p], "lr": 1e-3}
                             for name, p in model.named_parameters()])


def test_densification_clones_splits_and_prunes_within_the_bounds():
    """Ten splats pulled ever harder, room for four more: the four pulled hardest grow (two
    small ones cloned, two large ones split in two smaller halves), and the transparent
    one's halves are pruned."""
    model = _rgb_model(10)
    optimiser = _optimiser(model)
    sum(p.sum() for p in model.parameters()).backward()
    optimiser.step()  # moments exist, of the old row count
    settings = SplatConfig(initial=4, max_splats=14, refine_start=0, refine_every=1,
                           reset_every=1000, grow_scale=0.05)
    with torch.no_grad():
        model.scales[6:8] = -4.0  # small: cloned
        model.opacities[9] = -10.0  # nearly transparent: pruned
    means, scales = model.means.detach().clone(), model.scales.detach().clone()
    info = {"means2d": torch.zeros(10, 2), "front": torch.arange(10), "drawn": torch.arange(10)}
    info["means2d"].grad = torch.arange(1.0, 11.0)[:, None].repeat(1, 2) * 1e-3
    control = Densification.for_stage(settings, 1.0, 200, PIXELS)
    control.after_backward(model, optimiser, info, 1, 0.0, 100, 100)
    assert len(model.means) == 12  # 6 untouched, 2 + 2 clones, 2 halves of splat 8
    assert torch.equal(model.means[:8], means[:8]) and torch.equal(model.means[8:10], means[6:8])
    assert torch.allclose(model.scales[10:], scales[8] - math.log(1.6))
    assert not torch.equal(model.means[10], means[8])  # the halves moved apart
    for group in optimiser.param_groups:
        (p,) = group["params"]
        assert getattr(model, group["name"]) is p and len(p) == 12
        assert optimiser.state[p]["exp_avg"].shape == p.shape
        assert not optimiser.state[p]["exp_avg"][8:].any()  # new rows start without moments
    assert (torch.sigmoid(model.opacities) >= settings.prune_opacity).all()


def test_densification_grows_no_further_than_the_training_pixels_allow():
    """Ten splats pulled hard and room for ten more under ``max_splats``, but training
    pixels for twelve splats: they grow to one for ``PIXELS_PER_SPLAT`` pixels."""
    model = _rgb_model(10)
    optimiser = _optimiser(model)
    settings = SplatConfig(initial=4, max_splats=20, refine_start=0, refine_every=1,
                           reset_every=1000)
    info = {"means2d": torch.zeros(10, 2), "front": torch.arange(10), "drawn": torch.arange(10)}
    info["means2d"].grad = torch.arange(1.0, 11.0)[:, None].repeat(1, 2)
    control = Densification.for_stage(settings, 1.0, 200, 12 * PIXELS_PER_SPLAT + 1)
    assert control.limit == 12
    control.after_backward(model, optimiser, info, 1, 0.0, 100, 100)
    assert len(model.means) == 12


def test_splats_cut_off_at_the_reach_are_split():
    """A splat wider on screen than the rasteriser's reach is drawn cut off square: ``draw``
    reports it, and the next densification splits it though nothing pulls on it."""
    means, cov, values, opacities = few_splats(2)
    cov = cov.clone()
    cov[0] = torch.eye(3, dtype=cov.dtype) * 4.0  # metres wide, a few in front of the camera
    info = {}
    draw(means, cov, values, opacities, POSE, CAMERA, 2, info)
    assert 0 in info["clipped"].tolist()
    aside = means.clone()
    aside[0] = torch.tensor([50.0, 0.0, 0.0])  # as wide, but far outside the view
    draw(aside, cov, values, opacities, POSE, CAMERA, 2, info)
    assert 0 not in info["clipped"].tolist()
    model = _rgb_model(2)
    optimiser = _optimiser(model)
    sum(p.sum() for p in model.parameters()).backward()
    optimiser.step()
    settings = SplatConfig(initial=2, max_splats=10, refine_start=0, refine_every=1,
                           reset_every=1000)
    info = {"means2d": torch.zeros(2, 2), "front": torch.arange(2), "drawn": torch.arange(2),
            "clipped": torch.tensor([0])}
    info["means2d"].grad = torch.zeros(2, 2)  # no pull at all
    scale = model.scales[0].detach().clone()
    control = Densification.for_stage(settings, 1.0, 200, PIXELS)
    control.after_backward(model, optimiser, info, 1, 0.0, 100, 100)
    assert len(model.means) == 3  # splat 1 kept, splat 0 in two halves
    assert torch.allclose(model.scales[1:], scale - math.log(1.6))


def test_a_short_stage_scales_the_densification_schedule_down():
    """``schedule_iters``: 3D Gaussian splatting's schedule (for 30,000 iterations) in
    proportion for a stage of 300; as given without it, or for a longer stage."""
    settings = SplatConfig(schedule_iters=30_000, refine_start=500)  # 3D Gaussian splatting's
    short = Densification.for_stage(settings, 1.0, 300, PIXELS)
    assert (short.start, short.every, short.reset) == (5, 1, 30)
    given = Densification.for_stage(replace(settings, schedule_iters=0), 1.0, 300, PIXELS)
    assert (given.start, given.every, given.reset) == (500, 100, 3000)
    long = Densification.for_stage(settings, 1.0, 60_000, PIXELS)
    assert (long.start, long.every, long.reset) == (500, 100, 3000)


def test_densification_stops_at_refine_stop_of_the_stage():
    """Past ``refine_stop`` of its stage (its iterations' share or its clock's, as
    ``stage_progress`` gives it) the control neither grows, prunes nor resets."""
    settings = SplatConfig(initial=4, max_splats=20, refine_start=0, refine_every=1,
                           reset_every=1, refine_stop=0.5)
    for progress, splats in ((0.49, 11), (0.5, 10)):  # grown by two, one pruned; or as it was
        model = _rgb_model(10)
        with torch.no_grad():
            model.opacities[9] = -10.0  # nearly transparent: pruned while densifying
        info = {"means2d": torch.zeros(10, 2), "front": torch.arange(10),
                "drawn": torch.arange(10)}
        info["means2d"].grad = torch.ones(10, 2)  # every splat pulled hard
        control = Densification.for_stage(settings, 1.0, 200, 12 * PIXELS_PER_SPLAT + 1)
        control.after_backward(model, _optimiser(model), info, 1, progress, 100, 100)
        assert len(model.means) == splats


def test_an_opacity_reset_caps_every_opacity():
    model = _rgb_model(6)
    optimiser = _optimiser(model)
    settings = SplatConfig(initial=4, max_splats=10, reset_every=5, refine_start=100)
    control = Densification.for_stage(settings, 1.0, 200, PIXELS)
    control.after_backward(model, optimiser, {}, 5, 0.0, 10, 10)
    assert torch.sigmoid(model.opacities).max() <= 2 * settings.prune_opacity + 1e-6


def test_splat_settings_are_checked():
    with pytest.raises(InputError, match="initial splats must be at most max_splats"):
        SplatConfig(initial=10, max_splats=5)
    with pytest.raises(InputError, match="sh_degree"):
        SplatConfig(sh_degree=4)
    with pytest.raises(InputError, match="max_splats"):
        SplatConfig(max_splats=10**9)


SPLAT_FLAGS = ["--backbone", "splats", "--pretrain-iters", "30", "--finetune-iters", "10",
               "--splats-initial", "64", "--splats-refine-start", "5",
               "--splats-refine-every", "5", "--splats-sh-every", "10", "--checkpoint-every", "7"]


@pytest.fixture(scope="module")
def splat_run(cornell, tmp_path_factory):
    rundir = tmp_path_factory.mktemp("splat-runs") / "run"
    assert main(["train", str(cornell), "-o", str(rundir), *SPLAT_FLAGS]) == 0
    return rundir


def test_a_splat_run_trains_saves_loads_and_renders_the_same(splat_run, cornell):
    run = load_run(splat_run)
    assert run.kind == Basis.TRANSPORT and run.record.iteration == 40
    assert run.config.backbone == "splats" and run.model.degree == 3
    assert not run.model.means.requires_grad  # the geometry froze for the weights
    log = run.record.log
    assert log[-1]["stage"] == "transport" and log[0]["stage"] == RGB
    assert log[-1]["psnr"] > log[0]["psnr"]  # it learned
    test = run.dataset().indices("test")
    poses = run.dataset().poses[test]
    weights, acc = run.render(poses)
    again = load_run(splat_run).render(poses)  # CUDA's atomic sums differ in their last bits
    assert np.allclose(weights, again[0], rtol=0, atol=1e-6)
    assert np.allclose(acc, again[1], rtol=0, atol=1e-6)
    assert np.isfinite(weights).all() and weights.min() >= 0 and acc.max() <= 1 + 1e-5
    assert 0 <= run.residual_share(poses) < 1


def test_a_splat_run_evaluates_renders_bakes_and_exports(splat_run, tmp_path, capsys):
    assert main(["eval", str(splat_run)]) == 0
    assert "RGB through the weights: PSNR" in capsys.readouterr().out
    assert main(["render", str(splat_run), "-o", str(tmp_path / "render")]) == 0
    assert main(["bake", str(splat_run), "-o", str(tmp_path / "splats.npz")]) == 0
    splats = read_splats(tmp_path / "splats.npz")
    run = load_run(splat_run)
    assert len(splats) == len(run.model.means)  # the model itself, not a bake of it
    assert main(["export", str(tmp_path / "splats.npz"), "-o", str(tmp_path / "s.ply")]) == 0
    assert (tmp_path / "s.ply").stat().st_size > 0


@pytest.mark.parametrize("scene, budget", [("cornell", None), ("still_life", 0)])
def test_a_splat_run_resumes_where_it_stopped(scene, budget, tmp_path, request, monkeypatch):
    """Transport weights, and additive ones whose palette stage recomputes its targets and
    draws its views afresh (no room for their footprints)."""
    if budget is not None:
        monkeypatch.setattr(footprints, "footprint_budget", lambda device: budget)
    root = request.getfixturevalue(scene)
    flags = [*SPLAT_FLAGS[:2], "--pretrain-iters", "8", "--finetune-iters", "4",
             "--splats-initial", "32", "--checkpoint-every", "5", "--splats-patch", "6"]
    assert main(["train", str(root), "-o", str(tmp_path / "a"), *flags]) == 0
    assert main(["train", str(root), "-o", str(tmp_path / "a"), *flags, "--resume"]) == 0
    assert load_run(tmp_path / "a").record.iteration == 12


@pytest.mark.parametrize("stop, budget", [(5, None), (25, None), (25, 1)])
def test_a_splat_run_resumed_gives_the_uninterrupted_result(cornell, tmp_path, monkeypatch,
                                                            stop, budget):
    """Stopped in the RGB stage (densification's totals mid-gather), or in the palette stage
    (its window of footprints part way; one footprint at a time), then resumed: every
    tensor and every logged loss as the uninterrupted run's."""
    if budget is not None:
        monkeypatch.setattr(footprints, "footprint_budget", lambda device: budget)
        monkeypatch.setattr(footprints, "WINDOW_VISITS", 2)
    flags = [*SPLAT_FLAGS[:2], "--pretrain-iters", "20", "--finetune-iters", "10",
             "--splats-initial", "32", "--checkpoint-every", "5", "--splats-patch", "6",
             "--space", "unbounded",  # as auto chooses, without its probe
             "--splats-refine-start", "2", "--splats-refine-every", "7",
             "--splats-grow-grad2d", "2.3e-3"]  # about half the splats grow at step 7
    assert main(["train", str(cornell), "-o", str(tmp_path / "whole"), *flags]) == 0
    save = backbone.save_checkpoint

    def save_then_stop(run, path, *args):
        save(run, path, *args)
        if run.record.iteration == stop:
            raise KeyboardInterrupt

    monkeypatch.setattr(backbone, "save_checkpoint", save_then_stop)
    assert main(["train", str(cornell), "-o", str(tmp_path / "resumed"), *flags]) == 130
    monkeypatch.setattr(backbone, "save_checkpoint", save)
    assert main(["train", str(cornell), "-o", str(tmp_path / "resumed"), *flags,
                 "--resume"]) == 0
    whole, resumed = load_run(tmp_path / "whole"), load_run(tmp_path / "resumed")
    assert [e["loss"] for e in whole.record.log] == [e["loss"] for e in resumed.record.log]
    for a, b in zip(whole.model.state_dict().values(), resumed.model.state_dict().values(),
                    strict=True):
        assert torch.equal(a, b)


def test_the_palette_stage_keeps_the_colour_transforms_of_the_rgb_stage(still_life, tmp_path,
                                                                      monkeypatch):
    """The transforms are frozen with the geometry: every palette-stage checkpoint holds the
    RGB stage's last ones."""
    saved, save = [], backbone.save_checkpoint

    def recorded(run, path, *args):
        saved.append((run.kind, run.appearance.transforms().detach().clone()))
        save(run, path, *args)

    monkeypatch.setattr(backbone, "save_checkpoint", recorded)
    flags = [*SPLAT_FLAGS[:2], "--pretrain-iters", "6", "--finetune-iters", "6",
             "--splats-initial", "32", "--splats-patch", "6", "--checkpoint-every", "3"]
    assert main(["train", str(still_life), "-o", str(tmp_path / "run"), *flags]) == 0
    kinds = [kind for kind, _ in saved]
    assert kinds[0] == RGB and kinds[-1] == Basis.ADDITIVE
    last_rgb = [t for kind, t in saved if kind == RGB][-1]
    assert not torch.equal(last_rgb, torch.eye(3, 4).expand_as(last_rgb))  # they moved
    assert all(torch.equal(t, last_rgb) for kind, t in saved if kind != RGB)


def test_the_palette_stage_moves_its_window_of_footprints_on(cornell, tmp_path, monkeypatch):
    """Footprints that do not all fit: the stage draws from the views whose footprints fit
    (one here) and, after ``WINDOW_VISITS`` steps a view, makes the next views' instead."""
    monkeypatch.setattr(footprints, "footprint_budget", lambda device: 1)
    monkeypatch.setattr(footprints, "WINDOW_VISITS", 2)
    starts, made = [], footprints.make_footprints

    def counted(run, views, budget, start=0):
        starts.append(start)
        return made(run, views, budget, start)

    monkeypatch.setattr(footprints, "make_footprints", counted)
    flags = [*SPLAT_FLAGS[:2], "--pretrain-iters", "4", "--finetune-iters", "6",
             "--splats-initial", "32", "--splats-patch", "6"]
    assert main(["train", str(cornell), "-o", str(tmp_path / "run"), *flags]) == 0
    assert starts == [0, 1, 2]


def test_a_splat_run_takes_the_space_a_grid_probe_finds(still_life, tmp_path, monkeypatch):
    """``--space auto`` on transparent images probes both spaces with the grid NeRF, as a
    grid run does: where the scene ends does not depend on the backbone."""
    from nerf_stage.train import trainer

    probed = []

    def probe(config, box, *args):
        probed.append((box.unbounded, config.backbone))
        return 20.0 + 7.0 * box.unbounded

    monkeypatch.setattr(trainer, "_probe", probe)
    flags = [*SPLAT_FLAGS[:2], "--pretrain-iters", "4", "--finetune-iters", "2",
             "--splats-initial", "32", "--splats-patch", "6"]
    assert main(["train", str(still_life), "-o", str(tmp_path / "run"), *flags]) == 0
    assert probed == [(False, "grid"), (True, "grid")]
    assert load_run(tmp_path / "run").box.unbounded


def _before_the_palette_stage(run):
    """The run with its geometry in an RGB model, as its palette stage found it."""
    tensors = {name: getattr(run.model, name).detach().clone() for name in GEOMETRY}
    n, rest = len(tensors["means"]), sh_terms(run.model.degree) - 1
    zeros = tensors["means"].new_zeros
    tensors.update(colours=zeros(n, 3), colours_rest=zeros(n, rest, 3))
    return replace(run, model=SplatModel(tensors, RGB, run.model.degree))


@pytest.mark.parametrize("at_once", [None, 7], ids=["whole", "parts-of-7-pairs"])
def test_the_palette_stage_draws_views_from_their_footprints(splat_run, at_once, monkeypatch):
    """A view's footprint draws what the rasteriser draws, its matrices sorted whether
    their counting sorts take the pairs at once or in parts; training weights that one
    weight vector makes everywhere start every splat there."""
    if at_once:
        monkeypatch.setattr(backbone, "PAIRS_AT_ONCE", at_once)
        monkeypatch.setattr(footprints, "PAIRS_AT_ONCE", at_once)
    run = load_run(splat_run)
    data = run.dataset()
    ids = data.indices("train")[:6]
    camera, channels = data.camera(ids[0]), run.model.weights.shape[1]
    device = run.model.means.device
    views = footprints.training_views(run, data, ids, np.zeros(
        (len(ids), camera.height, camera.width, channels)), device)
    held = footprints.make_footprints(run, views, 1 << 40)
    values = run.model.values(views[0].pose[:3, 3]).detach()
    covariance, opacity = run.model.gaussians()
    drawn, acc = draw(run.model.means, covariance, values, opacity, views[0].pose, camera,
                      run.config.splats.reach)
    assert torch.allclose(held[0].draw(values), drawn, atol=1e-5)
    assert torch.allclose(held[0].opacity, acc, atol=1e-6)  # a GPU's sums: any order
    values.requires_grad_(True)  # the backward goes through the transposed matrix
    held[0].draw(values).square().sum().backward()
    for m in (held[0].matrix, held[0].transposed):  # sorted, distinct columns
        torch.sparse_csr_tensor(m.crow_indices(), m.col_indices(), m.values(), m.shape,
                                check_invariants=True)
    dense = held[0].matrix.to_dense()
    assert torch.equal(held[0].transposed.to_dense(), dense.T)
    assert torch.allclose(values.grad, 2 * dense.T @ (dense @ values.detach()), atol=1e-5)

    one = 0.1 + 0.9 * torch.rand(channels, generator=torch.Generator().manual_seed(0))
    one = one.to(device)
    views = [replace(v, weights=(f.opacity[:, None] * one).view(v.weights.shape))
             for v, f in zip(views, held)]
    started = _before_the_palette_stage(run)
    backbone._start_palette(started, views, WeightStack(run.palette, [], [], basis=run.basis))
    assert not started.model.means.requires_grad
    weights = ACTIVATIONS[started.kind](started.model.weights.detach())
    for view, footprint in zip(views, held):
        assert torch.allclose(footprint.matrix @ weights, view.weights.view(-1, channels),
                              atol=1e-4)


def test_an_additive_palette_stage_starts_at_the_colours_the_rgb_stage_ended_with():
    """Each splat's weights through the palette give its RGB colour from every direction:
    its own colour's weights, its spherical harmonics through the residual."""
    g = torch.Generator().manual_seed(0)
    n, degree = 50, 3
    tensors = {"means": torch.randn(n, 3, generator=g), "scales": torch.zeros(n, 3),
               "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), "opacities": torch.zeros(n),
               "colours": (0.3 + 0.4 * torch.rand(n, 3, generator=g) - 0.5) / SH_C0,
               "colours_rest": 0.01 * torch.randn(n, sh_terms(degree) - 1, 3, generator=g)}
    model = SplatModel(tensors, RGB, degree)
    eye = torch.tensor([0.0, 0.0, 5.0])
    rgb = model.values(eye).detach()
    palette = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0.1, 0.9)])
    run = SimpleNamespace(model=model, basis=Basis.ADDITIVE)
    backbone._start_palette(run, [], WeightStack(palette.astype(np.float32), [], []))
    assert model.kind == Basis.ADDITIVE and not model.means.requires_grad
    weights = model.values(eye).detach()
    assert torch.allclose(weights.sum(1), torch.ones(n), atol=1e-5)
    assert torch.allclose(weights @ torch.as_tensor(palette, dtype=torch.float32), rgb,
                          atol=1e-3)


def test_a_checkpoint_with_splats_of_the_wrong_shape_is_refused(splat_run, tmp_path, capsys):
    state = torch.load(splat_run / CHECKPOINT, weights_only=True)
    state["field"]["means"] = state["field"]["means"][:-1]
    (tmp_path / "bad").mkdir()
    torch.save(state, tmp_path / "bad" / CHECKPOINT)
    expect_error(main, ["eval", str(tmp_path / "bad")], "wrong names or shapes", capsys)


def test_traditional_training_is_refused_for_splats(cornell, tmp_path, capsys):
    expect_error(main, ["train", str(cornell), "-o", str(tmp_path / "t"), *SPLAT_FLAGS,
                        "--strategy", "traditional"], "two-stage or rgb", capsys)


def test_a_splat_run_recolours_inside_a_region_only(splat_run, tmp_path, capsys):
    """A region's pixels take the edit through the splats inside it (their centres), the
    rest keep the run's palette."""
    from nerf_stage.edit.editing import RENDER_FILE, read_render

    palette = tmp_path / "teal.json"
    palette.write_text('{"palette": ' + str([[0.1, 0.6, 0.55]] * 4) + "}")
    out = tmp_path / "local"
    assert main(["render", str(splat_run), "--palette", str(palette), "--region",
                 "box:-5,-5,2.5,5,6,6", "-o", str(out)]) == 0
    saved = read_render(out / RENDER_FILE)
    assert saved.samples is not None and len(saved.samples.pixel) > 0
    teal = np.full((4, 3), [0.1, 0.6, 0.55])
    local, everywhere, untouched = saved.recolor(None, teal), saved.recolor(teal), saved.recolor()
    assert (np.abs(local - untouched).max(-1) > 1e-3).any()  # the region's pixels change
    assert (np.abs(local - everywhere).max(-1) > 1e-3).any()  # but not as everywhere


def test_the_studio_draws_a_splat_runs_own_splats(splat_run):
    from studio.scene import SceneTarget

    target = SceneTarget.open(splat_run)
    run = load_run(splat_run)
    assert len(target.splats) == len(run.model.means)
    assert np.all(target.bounds[0] <= target.bounds[1])
    view = target.render(target.home_pose(), target.intrinsics(1.0, 8))
    assert view.weights.shape[1:3] == (8, 8) and view.samples is not None


def test_a_splat_runs_file_draws_what_the_run_renders_from_every_camera(splat_run):
    """The splats the studio and ``render_splats`` draw, their weights evaluated for the
    camera (``Splats.view_weights``), make the run's own render: no view dependence lost."""
    from nerf_stage.splats import render_splats

    run = load_run(splat_run)
    splats = run.splats({})
    poses = run.dataset().poses[:2]
    rendered, _ = run.render(poses)
    drawn, _ = render_splats(splats, poses, run.intrinsics)
    assert splats.residual is not None and np.abs(splats.residual).max() > 1e-4
    assert np.abs(drawn - rendered).max() < 1e-4
    diffuse, _ = render_splats(replace(splats, residual=None), poses, run.intrinsics)
    assert np.abs(diffuse - rendered).max() > 1e-3  # the residual is there to lose


def test_the_ply_of_a_splat_run_carries_its_view_dependence(splat_run, tmp_path):
    """What a PLY viewer computes from f_dc and f_rest for a direction is what the run
    draws from that direction (where no weight is clipped at zero or colour at one)."""
    import trimesh

    from nerf_stage.splats import export_splats, write_splats

    run = load_run(splat_run)
    splats = run.splats({})
    assert splats.residual.shape == (len(splats), 15, splats.weights.shape[1])
    write_splats(splats, tmp_path / "s.npz")
    again = read_splats(tmp_path / "s.npz")
    assert np.array_equal(again.residual, splats.residual)
    export_splats(again, tmp_path / "s.ply")
    table = trimesh.load(tmp_path / "s.ply").metadata["_ply_raw"]["vertex"]["data"]
    dc = np.stack([table[f"f_dc_{c}"] for c in range(3)], 1)
    rest = np.stack([table[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15)
    eye = run.box.centre + np.array([0.3, 0.2, 2.0]) * run.box.scale
    directions = splats.centres - eye
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    basis = sh_basis(torch.as_tensor(directions), 3).numpy()
    viewer = 0.28209479177387814 * dc + 0.5 + np.einsum("sb,scb->sc", basis[:, 1:], rest)
    eye_box = torch.as_tensor((eye - run.box.centre) / run.box.scale, dtype=torch.float32)
    model = run.model.to("cpu")
    with torch.no_grad():
        raw = torch.nn.functional.softplus(model.weights) + torch.einsum(
            "sb,sbm->sm", torch.as_tensor(basis[:, 1:], dtype=torch.float32), model.residual)
        drawn = (model.values(eye_box) @ torch.as_tensor(run.terms, dtype=torch.float32))
    plain = ((raw >= 0).all(1) & (torch.as_tensor(splats.colours()) < 1).all(1)).numpy()
    assert plain.sum() >= 20
    assert np.allclose(viewer[plain], drawn.numpy()[plain], atol=1e-4)


def test_the_spz_holds_the_ply_fields_to_its_precision(splat_run, tmp_path, capsys):
    """SPZ, read back by gsply (which keeps SPZ's RUB axes) and by our reader, keeps what
    the PLY writes to within its quantisation: positions to 2^-12, colours and opacities
    to about a 255th, log scales to a 16th, rotations up to sign; the spherical harmonics
    to a few bits."""
    gsply = pytest.importorskip("gsply")
    from nerf_stage.splats import splat_fields
    from splat_files import read_splat_file
    from splat_files.fields import from_gsdata
    from splat_files.spz import flip_axes

    run = load_run(splat_run)
    fields = splat_fields(run.splats({}))
    assert main(["export", str(splat_run), "-o", str(tmp_path / "s.spz")]) == 0
    for read in (flip_axes(from_gsdata(gsply.read_spz(tmp_path / "s.spz"))),
                 read_splat_file(tmp_path / "s.spz")):
        assert len(read) == len(fields) and read.shN.shape == fields.shN.shape
        assert np.abs(read.means - fields.means).max() <= 2.0 ** -12
        assert np.abs((read.sh0 - fields.sh0) * SH_C0).max() < 0.01
        opacity = [1 / (1 + np.exp(-o)) for o in (read.opacities, fields.opacities)]
        assert np.abs(opacity[0] - opacity[1]).max() < 0.01
        assert np.abs(read.scales - fields.scales).max() <= 1 / 32 + 1e-6
        assert np.abs(np.sum(read.quats * fields.quats, 1)).min() > 0.99
        assert np.abs(read.shN - fields.shN).max() < 0.1
    expect_error(main, ["export", str(splat_run), "-o", str(tmp_path / "s.obj")],
                 "splats are written as", capsys)


def test_a_splat_file_with_a_residual_of_the_wrong_shape_is_refused(splat_run, tmp_path):
    from nerf_stage.splats import write_splats

    splats = load_run(splat_run).splats({})
    splats.residual = splats.residual[:, :4]
    write_splats(splats, tmp_path / "s.npz")
    with pytest.raises(InputError, match="residual must have shape"):
        read_splats(tmp_path / "s.npz")


def test_the_palette_stage_decays_every_rate_to_lr_decay():
    """Over the RGB stage only the centres' rate decays (to a hundredth, 3D Gaussian
    splatting's); over the palette stage every rate decays to ``lr_decay`` of its start."""
    from nerf_stage.splats.backbone import _rates, _set_rates
    from nerf_stage.train.schedule import stage_progress

    config = TrainConfig(backbone="splats", pretrain_iters=10, finetune_iters=10, lr_decay=0.25)
    names = ("means", "colours", "weights", "residual")
    optimiser = torch.optim.Adam([{"name": name, "params": [torch.zeros(1, requires_grad=True)],
                                   "lr": 1.0} for name in names])
    start = _rates(config.splats, 2.0)
    rates = {}
    for it in (5, 15, 20):
        _set_rates(optimiser, config, 2.0, it, stage_progress(config, it, [], 20))
        rates[it] = {group["name"]: group["lr"] for group in optimiser.param_groups}
    assert rates[5]["means"] == pytest.approx(start["means"] * 0.01 ** 0.5)
    assert rates[5]["colours"] == 1.0  # as the optimiser had it
    assert rates[15]["weights"] == pytest.approx(start["weights"] * 0.25 ** 0.5)
    assert rates[20]["residual"] == pytest.approx(start["residual"] * 0.25)
