"""The splat rasteriser (``splats/rasterise.py``) against a brute-force sum over every pixel
and finite differences: through the tile kernels of a CPU (``splats/tiles.py``) and through
pairs in PyTorch (whole views and bands of rows), and the two against each other on many
random splats."""

import pytest

torch = pytest.importorskip("torch")

from nerf_stage.splats import pairs, rasterise  # noqa: E402
from nerf_stage.splats.model import covariances  # noqa: E402
from nerf_stage.splats.rasterise import LOW_PASS, MAX_ALPHA, MIN_TRANSMITTANCE, draw  # noqa: E402

from .splat_cases import CAMERA, POSE, few_splats  # noqa: E402


def brute_force(means, cov, values, opacities, pose, camera):
    """Every pixel: the splats sorted by depth, alpha from each one's projected Gaussian,
    blended front to back (3D Gaussian splatting's image formation), in float64."""
    pose = pose.double()
    rotation, origin = pose[:3, :3], pose[:3, 3]
    out = torch.zeros(camera.height * camera.width, values.shape[1], dtype=torch.float64)
    acc = torch.zeros(camera.height * camera.width, dtype=torch.float64)
    local = (means - origin) @ rotation
    depth = -local[:, 2]
    order = torch.argsort(depth)
    for py in range(camera.height):
        for px in range(camera.width):
            light = 1.0
            for s in order.tolist():
                x, y, z = local[s]
                d = -z
                u, v = camera.cx + camera.fx * x / d, camera.cy - camera.fy * y / d
                j = torch.tensor([[camera.fx / d, 0, camera.fx * x / d**2],
                                  [0, -camera.fy / d, -camera.fy * y / d**2]], dtype=torch.float64)
                t = j @ rotation.T
                sigma = t @ cov[s] @ t.T + LOW_PASS * torch.eye(2, dtype=torch.float64)
                delta = torch.tensor([px + 0.5 - u, py + 0.5 - v], dtype=torch.float64)
                alpha = min(MAX_ALPHA, float(opacities[s] * torch.exp(
                    -0.5 * delta @ torch.linalg.inv(sigma) @ delta)))
                if alpha < 1 / 255 or light < MIN_TRANSMITTANCE:
                    continue
                out[py * camera.width + px] += light * alpha * values[s]
                acc[py * camera.width + px] += light * alpha
                light *= 1 - alpha
    return out, acc


@pytest.fixture(params=["tiles", "pairs", "pairs-in-bands-of-3-rows"])
def bands(request, monkeypatch):
    """The tile kernels, or the view's pairs found at once, or a band of 3 rows at a time
    (``BAND_PIXELS``)."""
    monkeypatch.setattr(rasterise, "TILED", request.param == "tiles")
    if request.param.endswith("rows"):
        monkeypatch.setattr(pairs, "BAND_PIXELS", 3 * CAMERA.width)


def test_the_rasteriser_matches_a_brute_force_sum_over_every_pixel(bands):
    splats = few_splats()
    drawn, acc = draw(*splats, POSE, CAMERA, reach=64)
    out, want = brute_force(*splats, POSE, CAMERA)
    assert acc.max() > 0.3  # the splats are in view
    assert torch.allclose(drawn, out, atol=1e-9) and torch.allclose(acc, want, atol=1e-9)


def test_without_a_reach_a_splat_near_the_camera_is_drawn_whole():
    """Cut off at a reach (training's bound on a view's pairs), a splat wider than it on
    screen is drawn square and reported clipped; without one (renders), it is drawn whole."""
    means, cov, values, opacities = few_splats()
    means[0] = torch.tensor([0.0, 0.0, 2.2], dtype=means.dtype)  # 0.8 from the camera
    info = {}
    cut, _ = draw(means, cov, values, opacities, POSE, CAMERA, 2, info)
    whole, acc = draw(means, cov, values, opacities, POSE, CAMERA, None)
    out, want = brute_force(means, cov, values, opacities, POSE, CAMERA)
    assert torch.allclose(whole, out, atol=1e-9) and torch.allclose(acc, want, atol=1e-9)
    assert 0 in info["clipped"].tolist() and not torch.allclose(cut, out, atol=1e-3)


def test_a_window_of_a_view_is_that_part_of_the_whole_view():
    splats = few_splats()
    whole, acc = draw(*splats, POSE, CAMERA, reach=64)
    part, part_acc = draw(*splats, POSE, CAMERA, reach=64, window=(3, 2, 5, 4))
    whole = whole.view(CAMERA.height, CAMERA.width, -1)[2:6, 3:8]
    assert torch.allclose(part.view(4, 5, -1), whole, atol=1e-12)
    assert torch.allclose(part_acc.view(4, 5), acc.view(CAMERA.height, CAMERA.width)[2:6, 3:8],
                          atol=1e-12)


def test_the_rasterisers_gradients_match_finite_differences(bands):
    means, cov, values, opacities = few_splats(3, seed=1)
    quats = torch.randn(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    scales = torch.full((3, 3), 0.15, dtype=torch.float64)
    weights = torch.rand(CAMERA.height * CAMERA.width, 4, dtype=torch.float64)

    def loss(means, scales, values, opacities):
        drawn, acc = draw(means, covariances(quats, scales), values, opacities, POSE, CAMERA,
                          reach=64)
        return (drawn * weights).sum() + acc.square().sum()

    inputs = [t.clone().requires_grad_(True) for t in (means, scales, values, opacities)]
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_draw_reports_the_screen_positions_densification_reads():
    means, cov, values, opacities = few_splats()
    means.requires_grad_(True)
    info = {}
    drawn, _ = draw(means, cov, values, opacities, POSE, CAMERA, 64, info)
    drawn.sum().backward()
    assert info["means2d"].shape == (5, 2) and info["means2d"].grad is not None
    assert set(info["drawn"].tolist()) <= set(info["front"].tolist())


def test_the_reported_pairs_make_up_the_view():
    """``info['pairs']`` (pixel, splat, contribution) sums to the drawn values: what the
    palette stage's start and the regions read; the first splat behind the camera, so
    that the drawn projections' indices are not the splats'."""
    means, cov, values, opacities = few_splats()
    means[0] = torch.tensor([0.0, 0.0, 4.0], dtype=means.dtype)
    info = {}
    drawn, acc = draw(means, cov, values, opacities, POSE, CAMERA, 64, info, keep_pairs=True)
    pixel, splat, contribution = info["pairs"]
    rebuilt = torch.zeros_like(drawn).index_add(0, pixel, contribution[:, None] * values[splat])
    assert torch.allclose(rebuilt, drawn, atol=1e-12)
    assert torch.allclose(torch.zeros_like(acc).index_add(0, pixel, contribution), acc)
    assert 0 not in splat.tolist() and len(set(splat.tolist())) > 1


def _random_scene(n=300, seed=1):
    """``n`` float32 splats about a 64 x 48 view: some behind the camera, some wider than
    the image, some nearly transparent, some nearly opaque; their parameters as leaves."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([1.2, 1.0, 1.5])
    means[: n // 10, 2] = 3.5 + torch.rand(n // 10, generator=g)  # behind the camera at z 3
    log_scales = torch.randn(n, 3, generator=g) * 0.5 - 3.2
    log_scales[n // 10: n // 10 + 3] = 1.5  # wider than the image
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g)
    opacities[n // 10: n // 10 + 3] = 0.2
    values = torch.rand(n, 3, generator=g)
    return [t.requires_grad_() for t in (means, log_scales, quats, opacities, values)]


def _drawn_and_gradients(tiled, monkeypatch, reach):
    from nerf_stage.data.cameras import Intrinsics

    monkeypatch.setattr(rasterise, "TILED", tiled)
    camera = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
    means, log_scales, quats, opacities, values = leaves = _random_scene()
    info = {}
    drawn, acc = draw(means, covariances(quats, log_scales.exp()), values, opacities,
                      POSE.float(), camera, reach, info)
    g = torch.Generator().manual_seed(2)
    loss = ((drawn * torch.rand(drawn.shape, generator=g)).sum()
            + (acc * torch.rand(acc.shape, generator=g)).sum())
    loss.backward()
    return drawn, acc, [leaf.grad for leaf in leaves], info


@pytest.mark.parametrize("reach", [None, 8])
def test_the_tile_kernels_match_the_pairs_in_pytorch(monkeypatch, reach):
    """On 300 random splats, in front of and behind the camera, wider than the image, cut
    off at a reach or not: the tile kernels' values, opacity and every gradient against
    the PyTorch pairs' within 1e-4 (of the largest), and the same splats drawn."""
    tiles = _drawn_and_gradients(True, monkeypatch, reach)
    pairs = _drawn_and_gradients(False, monkeypatch, reach)
    assert tiles[1].max() > 0.9 and tiles[1].min() < 0.5  # dense and sparser parts
    for a, b in [*zip(tiles[:2], pairs[:2]), *zip(tiles[2], pairs[2])]:
        assert torch.isfinite(a).all()
        assert (a - b).abs().max() <= 1e-4 * max(1.0, float(b.detach().abs().max()))
    assert torch.equal(torch.sort(tiles[3]["drawn"]).values, torch.sort(pairs[3]["drawn"]).values)
    assert torch.allclose(tiles[3]["means2d"].grad, pairs[3]["means2d"].grad, atol=1e-4)



@pytest.mark.parametrize("reach", [None, 8])
def test_the_tile_kernels_keep_the_pairs_in_pytorchs_order(monkeypatch, reach):
    """The pairs a footprint is made of (``draw(..., keep_pairs=True)``) through the tile
    kernels (``tiles.walk_pairs``) and through PyTorch, on 300 random splats: both by pixel,
    then front to back, the same pairs (those of a contribution above 1e-3 at least) with
    the same contributions within 1e-5, and the same values and opacity."""
    from nerf_stage.data.cameras import Intrinsics

    camera = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
    means, log_scales, quats, opacities, values = (t.detach() for t in _random_scene())
    kept = []
    for tiled in (True, False):
        monkeypatch.setattr(rasterise, "TILED", tiled)
        info = {}
        drawn = draw(means, covariances(quats, log_scales.exp()), values, opacities,
                     POSE.float(), camera, reach, info, keep_pairs=True)
        kept.append((drawn, info["pairs"], info["drawn"]))
    (tile_drawn, tile_pairs, tile_splats), (torch_drawn, torch_pairs, torch_splats) = kept
    for a, b in zip(tile_drawn, torch_drawn):
        assert (a - b).abs().max() <= 1e-4
    pairs_of = []
    for pixel, splat, contribution in (tile_pairs, torch_pairs):
        assert (torch.diff(pixel.long()) >= 0).all()
        pairs_of.append({(int(p), int(q)): float(c) for p, q, c in zip(pixel, splat, contribution)})
    tiles_kept, torch_kept = pairs_of
    for one, other in ((tiles_kept, torch_kept), (torch_kept, tiles_kept)):
        assert all(pair in other for pair, c in one.items() if c > 1e-3)
    common = tiles_kept.keys() & torch_kept.keys()
    assert len(common) > 1000
    assert max(abs(tiles_kept[pair] - torch_kept[pair]) for pair in common) <= 1e-5
    order = {}  # front to back within each pixel: the same sequence of splats
    for pixel, splat, _ in (tile_pairs, torch_pairs):
        for p, q in zip(pixel.tolist(), splat.tolist()):
            order.setdefault(p, ([], []))[pixel is tile_pairs[0] and 0 or 1].append(q)
    assert all(a[:len(b)] == b[:len(a)] for a, b in order.values())
    assert set(tile_splats.tolist()) == set(torch_splats.tolist())


def test_the_cpu_projection_matches_pytorchs():
    """The numba projection of a CPU (``projection._CpuProjection``) against PyTorch's
    (``_projected``, as on CUDA) from a turned camera, on splats in front of and behind it
    and far outside the view (the Jacobian's clamp): the same splats, boxes and depths,
    and the centres, inverse covariances and every gradient within 1e-4."""
    from nerf_stage.data.cameras import Intrinsics
    from nerf_stage.splats import projection

    camera = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
    turn = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.4],
                                                 [-0.2, 0.4, 0]]))
    pose = POSE.clone().float()
    pose[:3, :3] = turn @ pose[:3, :3]
    results = []
    for make in (projection._CpuProjection.apply, projection._projected):
        means, log_scales, quats, opacities, _ = leaves = _random_scene()
        means2d, rest, box, index, depth, wide = make(
            means, covariances(quats, log_scales.exp()), opacities, pose, camera, 8,
            (0, 0, 64, 48))
        g = torch.Generator().manual_seed(3)
        (torch.cat([means2d, rest], 1) * torch.randn(len(index), 6, generator=g)).sum().backward()
        results.append([means2d, rest, box, index, depth, wide,
                        *[leaf.grad for leaf in leaves[:4]]])
    clamped = ((results[0][0][:, 0] < -0.3 * 64) | (results[0][0][:, 0] > 1.3 * 64)).sum()
    assert len(results[0][3]) < 300 and clamped > 0  # some behind, some clamped
    for a, b in zip(*results):
        if a.dtype == torch.bool or not a.is_floating_point():
            assert torch.equal(a, b)
        else:
            assert torch.isfinite(a).all()
            assert (a - b).abs().max() <= 1e-4 * max(1.0, float(b.detach().abs().max()))


def test_the_cpu_covariances_and_sh_values_match_pytorchs():
    """The numba covariances (``model._CpuCovariances``) and spherical-harmonic values
    (``sh._CpuContraction``) of a CPU against PyTorch's products, values and gradients,
    on quaternions of any length."""
    from nerf_stage.splats.model import rotation_matrices
    from nerf_stage.splats.sh import sh_basis, sh_values

    g = torch.Generator().manual_seed(4)
    quats = (torch.randn(200, 4, generator=g) * 3).requires_grad_()
    scales = torch.rand(200, 3, generator=g).requires_grad_()
    coefficients = torch.randn(200, 15, 3, generator=g).requires_grad_()
    directions = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=1)
    basis = sh_basis(directions, 2)[:, 1:].requires_grad_()
    upstream = torch.randn(200, 3, 3, generator=g), torch.randn(200, 3, generator=g)

    def results(cpu):
        leaves = (quats, scales, coefficients, basis)
        for leaf in leaves:
            leaf.grad = None
        if cpu:
            cov, values = covariances(quats, scales), sh_values(basis, coefficients)
        else:
            rotation = rotation_matrices(quats)
            cov = (rotation * scales[:, None, :] ** 2) @ rotation.transpose(1, 2)
            values = torch.einsum("sb,sbc->sc", basis, coefficients[:, :8])
        ((cov * upstream[0]).sum() + (values * upstream[1]).sum()).backward()
        return [cov, values, *[leaf.grad for leaf in leaves]]

    for a, b in zip(results(True), results(False)):
        assert (a - b).abs().max() <= 1e-5 * max(1.0, float(b.detach().abs().max()))
