"""Radiance-field backbones: output activations, grid interpolation and its gradient,
ray steps, and the row-major copy that renders read."""


import pytest

torch = pytest.importorskip("torch")

from nerf_stage.backbone_settings import GridConfig, HashConfig, MLPConfig  # noqa: E402
from nerf_stage.fields import GridField, MLPField  # noqa: E402
from nerf_stage.fields.grid import _corners, _Trilinear  # noqa: E402
from nerf_stage.fields.hashgrid import HashEncoding, HashField  # noqa: E402

#: A hash encoding whose two coarse levels index their vertices directly and whose finer
#: two share hashed tables of 2^7 rows.
SMALL_HASH = HashConfig(levels=4, features=2, log2_entries=7, coarsest=2, finest=16,
                        density_width=8, geometry_features=3, head_layers=1)


def small_grid(extent, voxels: int, features: int, head_width: int, kind="rgb", channels=3):
    """A per-sample, diffuse grid field of one hidden layer."""
    settings = GridConfig(voxels=voxels, features=features, view_frequencies=None,
                          deferred=False, head_layers=1)
    return GridField(extent, settings, head_width, kind, channels)


@pytest.mark.parametrize("kind", ["additive", "transport"])
@pytest.mark.parametrize("make", [lambda k, c: MLPField(None, MLPConfig(), 16, k, c),
                                  lambda k, c: small_grid([1, 1, 0.5], 6**3, 4, 16, k, c),
                                  lambda k, c: HashField(torch.ones(3), SMALL_HASH, 16, k, c)])


def test_output_activations(make, kind, rng):
    field = make(kind, 6)
    x = torch.as_tensor(rng.uniform(-1, 1, (50, 3)), dtype=torch.float32)
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    sigma, h = field.density(x)
    values = field.colour(h, d)
    assert values.shape == (50, 6) and torch.all(values >= 0) and torch.all(sigma >= 0)
    if kind == "additive":
        assert torch.allclose(values.sum(-1), torch.ones(50), atol=1e-6)


@pytest.mark.parametrize("kind", ["additive", "transport"])
def test_a_new_output_layer_starts_at_the_mean_weights_everywhere(kind, rng):
    """``field_steps.fit_output`` starts here, so that a rare channel is neither dead nor
    saturated before the fit: every point gives the given outputs (normalised, for
    additive weights)."""
    field = small_grid([1, 1, 1], 6**3, 4, 16, kind, 4)
    mean = torch.tensor([0.5, 0.3, 1e-4, 0.2]) * (2.0 if kind == "transport" else 1.0)
    field.start_output(mean)
    _, h = field.density(torch.as_tensor(rng.uniform(-1, 1, (30, 3)), dtype=torch.float32))
    values = field.colour(h, torch.nn.functional.normalize(torch.randn(30, 3), dim=-1))
    want = mean / mean.sum() if kind == "additive" else mean
    assert torch.allclose(values, want.expand(30, 4), rtol=1e-4, atol=1e-7)


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



def test_a_hash_level_interpolates_its_vertices_trilinearly():
    encoding = HashEncoding(torch.ones(3), SMALL_HASH)
    assert encoding.direct_levels == 2
    with torch.no_grad():
        encoding.table.copy_(torch.randn_like(encoding.table))
    n = int(encoding.resolution[0])  # the coarsest level: vertex (i, j, k) is row i n1^2 + j n1 + k
    vertex = torch.tensor([[1, 0, 2], [2, 2, 1]])
    x = vertex / n * 2 - 1
    rows = vertex @ torch.tensor([(n + 1) ** 2, n + 1, 1])
    assert torch.allclose(encoding(x)[:, :2], encoding.table[:, rows].t(), atol=1e-6)
    boundary = torch.tensor([[0.0, 0.3, -0.2]])  # a cell face of every level
    step = torch.tensor([[1e-4, 0.0, 0.0]])
    assert torch.allclose(encoding(boundary - step), encoding(boundary + step), atol=1e-2)


def test_hashed_levels_stay_in_their_own_rows():
    encoding = HashEncoding(torch.ones(3), SMALL_HASH)
    x = torch.rand(4096, 3) * 2 - 1
    with torch.no_grad():
        encoding.table.zero_()
    encoding(x).sum().backward()
    touched = torch.nonzero(encoding.table.grad.abs().sum(0)).flatten()
    assert int(touched.max()) < encoding.table.shape[1]
    last = int(encoding.offset[-1])
    assert int((touched >= last).sum()) > 0 and int(touched[touched >= last].max()) < last + 128
