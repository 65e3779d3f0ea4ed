"""harmonize: HCL conversion, template fitting, projection, shares and pictures."""

import colour
import numpy as np
import pytest

from harmonize import (
    TEMPLATES,
    contact_sheet,
    fit_template,
    get_template,
    harmonize_palette,
    hcl_to_srgb,
    hcl_to_srgb_in_gamut,
    hue_wheel,
    in_srgb_gamut,
    palette_shares,
    project_palette,
    srgb_to_hcl,
    template_cost,
)
from harmonize.fit import TemplateFit, hue_offset
from palette_core.constants import ACHROMATIC_CHROMA
from palette_core.errors import InputError
from palette_core.stack import WeightStack


def random_palette(rng, k):
    return rng.random((k, 3))


def circular_gap(a, b, period=360.0):
    return np.abs(np.mod(np.asarray(a) - b + period / 2, period) - period / 2)


# --- HCL ---------------------------------------------------------------------------


def test_srgb_to_hcl_matches_colour_science(rng):
    rgb = rng.random((500, 3))
    srgb = colour.RGB_COLOURSPACES["sRGB"]
    matrix = colour.normalised_primary_matrix(srgb.primaries, srgb.whitepoint)
    with colour.domain_range_scale("reference"):
        xyz = colour.models.eotf_sRGB(rgb) @ matrix.T
        lch = colour.Lab_to_LCHab(colour.XYZ_to_Lab(xyz))
        standard = colour.Lab_to_LCHab(colour.XYZ_to_Lab(colour.sRGB_to_XYZ(rgb)))
    hcl = srgb_to_hcl(rgb)
    np.testing.assert_allclose(hcl[:, [2, 1]], lch[:, :2], atol=1e-9)
    chromatic = lch[:, 1] > 1
    assert circular_gap(hcl[chromatic, 0], lch[chromatic, 2]).max() < 1e-9
    # colour-science's standard sRGB matrix (rounded in IEC 61966-2-1) differs invisibly.
    assert np.abs(hcl[:, [2, 1]] - standard[:, :2]).max() < 0.05


def test_hcl_round_trip_any_shape(rng):
    rgb = rng.random((2, 3, 4, 3))
    hcl = srgb_to_hcl(rgb)
    assert hcl.shape == rgb.shape
    assert (hcl[..., 0] >= 0).all() and (hcl[..., 0] < 360).all()
    assert np.abs(hcl_to_srgb(hcl) - rgb).max() < 1e-10


def test_greys_black_and_white_are_achromatic():
    greys = np.linspace(0, 1, 11)[:, None].repeat(3, axis=1)
    hcl = srgb_to_hcl(greys)
    assert hcl[:, 1].max() < 1e-9
    np.testing.assert_allclose(hcl[[0, -1], 2], [0, 100], atol=1e-9)


def test_gamut_mapping_lowers_chroma_only(rng):
    hcl = np.stack([rng.uniform(0, 360, 400), rng.uniform(0, 200, 400),
                    rng.uniform(1, 99, 400)], axis=-1)
    rgb = hcl_to_srgb_in_gamut(hcl)
    assert in_srgb_gamut(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1
    back = srgb_to_hcl(rgb)
    np.testing.assert_allclose(back[:, 2], hcl[:, 2], atol=1e-6)
    assert (back[:, 1] <= hcl[:, 1] + 1e-6).all()
    coloured = back[:, 1] > 1
    assert circular_gap(back[coloured, 0], hcl[coloured, 0]).max() < 1e-5
    # The chroma found is the largest in gamut: a little more leaves the gamut.
    reduced = back[:, 1] < hcl[:, 1] - 1e-6
    assert reduced.any()
    wider = hcl[reduced].copy()
    wider[:, 1] = back[reduced, 1] + 1e-3
    assert not in_srgb_gamut(hcl_to_srgb(wider)).any()


# --- templates and fitting -----------------------------------------------------------


def test_registry_has_the_seven_templates():
    assert list(TEMPLATES) == ["monochrome", "complementary", "single-split", "double-split",
                               "triad", "square", "analogous"]
    periods = {name: t.period for name, t in TEMPLATES.items()}
    assert periods == {"monochrome": 360, "complementary": 180, "single-split": 360,
                       "double-split": 180, "triad": 120, "square": 90, "analogous": 360}


def test_unknown_template_lists_the_names():
    with pytest.raises(InputError, match="unknown template 'tetrad'; choose one of monochrome"):
        get_template("tetrad")


def test_hue_offset_is_signed_and_circular():
    np.testing.assert_allclose(hue_offset([350, 10, 0, 90], [10, 350, 180, 80]),
                               [20, -20, -180, -10])


def template_palette(rng, template, alpha, noise, per_axis=3):
    """Colours on the template's axes at ``alpha`` with hue noise up to +-noise degrees."""
    hues = np.repeat(template.axes(alpha), per_axis)
    hues = hues + rng.uniform(-noise, noise, len(hues))
    hcl = np.stack([np.mod(hues, 360), np.full(len(hues), 45.0),
                    rng.uniform(35, 85, len(hues))], axis=-1)
    return hcl_to_srgb_in_gamut(hcl)


@pytest.mark.parametrize("name", list(TEMPLATES))
def test_fit_recovers_a_known_alpha(rng, name):
    template = TEMPLATES[name]
    for _ in range(10):
        alpha = rng.uniform(0, 360)
        palette = template_palette(rng, template, alpha, noise=0.5)
        shares = rng.dirichlet(np.ones(len(palette)))
        fit = fit_template(srgb_to_hcl(palette), shares, template)
        assert 0 <= fit.alpha < template.period
        assert circular_gap(fit.alpha, alpha, template.period) < 0.5


@pytest.mark.parametrize("name", list(TEMPLATES))
def test_fit_is_the_global_minimum_of_a_fine_sweep(rng, name):
    template = TEMPLATES[name]
    sweep = np.arange(0, 360, 0.01)
    for k in range(1, 11):
        hcl = srgb_to_hcl(random_palette(rng, k))
        shares = rng.dirichlet(np.ones(k))
        fit = fit_template(hcl, shares, template)
        costs = template_cost(hcl, shares, template, sweep)
        assert fit.cost <= costs.min() + 1e-9 * costs.min()
        # The sweep comes within its step of the exact minimum.
        slope = (shares * hcl[:, 1] * hcl[:, 2]).sum()
        assert costs.min() <= fit.cost + slope * 0.005 + 1e-9
        assert fit.cost == pytest.approx(template_cost(hcl, shares, template, fit.alpha))


def test_noisy_template_fits_at_least_as_well_as_the_truth(rng):
    template = TEMPLATES["triad"]
    palette = template_palette(rng, template, 77.0, noise=4.0)
    hcl, shares = srgb_to_hcl(palette), np.full(len(palette), 1 / len(palette))
    fit = fit_template(hcl, shares, template)
    assert fit.cost <= template_cost(hcl, shares, template, 77.0)
    assert circular_gap(fit.alpha, 77.0, template.period) < 4.0


def test_achromatic_colours_neither_steer_nor_move(rng):
    template = TEMPLATES["complementary"]
    chromatic = template_palette(rng, template, 20.0, noise=10.0, per_axis=2)
    greys = np.array([[0.0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5], [0.3, 0.3, 0.302]])
    assert (srgb_to_hcl(greys)[:, 1] < ACHROMATIC_CHROMA).all()
    mixed = np.concatenate([chromatic, greys])
    fit_alone = fit_template(srgb_to_hcl(chromatic), np.full(4, 0.25), template)
    fit_mixed = fit_template(srgb_to_hcl(mixed), np.full(8, 0.125), template)
    assert fit_mixed.alpha == pytest.approx(fit_alone.alpha, abs=1e-9)
    result = harmonize_palette(mixed, np.full(8, 0.125), "complementary")
    np.testing.assert_array_equal(result.palette[4:], greys)


def test_grey_palette_stays_put():
    greys = np.array([[0.1, 0.1, 0.1], [0.6, 0.6, 0.6], [1.0, 1.0, 1.0]])
    for name in TEMPLATES:
        result = harmonize_palette(greys, np.full(3, 1 / 3), name)
        assert result.fit.alpha == 0.0 and result.fit.cost == 0.0
        np.testing.assert_array_equal(result.palette, greys)


# --- projection ----------------------------------------------------------------------


@pytest.mark.parametrize("k", range(1, 11))
def test_projection_puts_hues_on_axes_in_gamut(rng, k):
    palette = random_palette(rng, k)
    shares = rng.dirichlet(np.ones(k))
    before = srgb_to_hcl(palette)
    for name in [*TEMPLATES, "best"]:
        result = harmonize_palette(palette, shares, name)
        assert result.palette.shape == (k, 3)
        assert in_srgb_gamut(result.palette).all()
        assert result.palette.min() >= 0 and result.palette.max() <= 1
        after = srgb_to_hcl(result.palette)
        np.testing.assert_allclose(after[:, 2], before[:, 2], atol=1e-6)
        assert (after[:, 1] <= before[:, 1] + 1e-6).all()
        moved = (before[:, 1] >= ACHROMATIC_CHROMA) & (after[:, 1] > 1e-3)
        gaps = circular_gap(after[moved, 0][:, None], result.fit.axes[None, :]).min(axis=1)
        assert (gaps < 1e-5).all()


def test_best_has_the_least_cost(rng):
    palette, shares = random_palette(rng, 7), rng.dirichlet(np.ones(7))
    best = harmonize_palette(palette, shares, "best")
    costs = [harmonize_palette(palette, shares, name).fit.cost for name in TEMPLATES]
    assert best.fit.cost == min(costs)


@pytest.mark.parametrize("name", list(TEMPLATES))
def test_harmonizing_twice_changes_nothing(rng, name):
    for k in (3, 6, 9):
        palette, shares = random_palette(rng, k), rng.dirichlet(np.ones(k))
        once = harmonize_palette(palette, shares, name).palette.astype(np.float32)
        twice = harmonize_palette(once, shares, name).palette
        np.testing.assert_allclose(twice, once, atol=1e-5)


def test_strength_zero_is_identity_and_half_goes_halfway(rng):
    palette = np.array([[0.7, 0.35, 0.3], [0.3, 0.5, 0.7]])
    fit = TemplateFit(TEMPLATES["monochrome"], 60.0, 0.0)
    np.testing.assert_array_equal(project_palette(palette, fit, 0.0), palette)
    before = srgb_to_hcl(palette)
    half = srgb_to_hcl(project_palette(palette, fit, 0.5))
    full = srgb_to_hcl(project_palette(palette, fit, 1.0))
    step = hue_offset(before[:, 0], 60.0)
    np.testing.assert_allclose(hue_offset(before[:, 0], half[:, 0]), step / 2, atol=1e-6)
    np.testing.assert_allclose(full[:, 0], 60.0, atol=1e-6)


def test_harmonize_palette_validates():
    palette, shares = np.full((2, 3), 0.5), np.array([0.5, 0.5])
    with pytest.raises(InputError, match="strength must lie in"):
        harmonize_palette(palette, shares, "triad", 1.5)
    with pytest.raises(InputError, match="palette must have shape"):
        harmonize_palette(np.zeros(3), shares, "triad")
    with pytest.raises(InputError, match="shares must have shape"):
        harmonize_palette(palette, np.ones(3), "triad")
    with pytest.raises(InputError, match="unknown template"):
        harmonize_palette(palette, shares, "pentad")


# --- shares and pictures -----------------------------------------------------------


def test_palette_shares_of_additive_and_transport_stacks():
    weights = [np.array([[[0.5, 0.5, 0.0]], [[1.0, 0.0, 0.0]]], np.float32),
               np.array([[[0.0, 0.5, 0.5]]], np.float32)]
    stack = WeightStack(np.eye(3), weights, ["a", "b"])
    np.testing.assert_allclose(palette_shares(stack), [1.5 / 3, 1 / 3, 0.5 / 3])
    # K = 2, order 2 terms: 1, v0, v1, v0*v0, v0*v1, v1*v1.
    transport = WeightStack(np.eye(3)[:2], [np.array([[[9, 1, 0, 1, 1, 0]]], np.float32)],
                            ["a"], "simulated", "transport", 2)
    np.testing.assert_allclose(palette_shares(transport), [4 / 5, 1 / 5])


def test_hue_wheel_and_contact_sheet(rng):
    palette, shares = random_palette(rng, 5), rng.dirichlet(np.ones(5))
    result = harmonize_palette(palette, shares, "square")
    wheel = hue_wheel(result.hcl_before, shares, result.hcl_after, result.fit.axes, "square")
    assert wheel.size == (320, 320)
    pixels = np.asarray(wheel)
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 100  # rim, dots and axes drawn
    image = rng.random((30, 50, 3))
    sheet = contact_sheet([("a", image, wheel)] * 5, width=100, columns=4)
    assert sheet.width == 400 and sheet.height > 2 * 100
