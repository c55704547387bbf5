"""Sampled kinematics and positions against independent Jeans / projection integrals."""

import numpy as np
import pytest
from cluster_helpers import JeansReference, binned_dispersion_chi2, sigma2_interpolator

from mavispm.simulate.cluster.field_sampler import arc_measure
from mavispm.simulate.cluster.generator import build_cluster_model, sample_stars
from mavispm.simulate.cluster.projection import arcsec_to_pc
from mavispm.simulate.cluster.settings import ClusterSettings

N_STARS = 100_000
N_BINS = 20


def _sky_components(stars):
    R = np.hypot(stars["x"], stars["y"])
    v_rad = (stars["x"] * stars["vx"] + stars["y"] * stars["vy"]) / R
    v_tan = (stars["x"] * stars["vy"] - stars["y"] * stars["vx"]) / R
    return R, v_rad, v_tan


@pytest.fixture(scope="module", params=[0.0, 1500.0], ids=["no_imbh", "imbh_1500"])
def sampled(request):
    settings = ClusterSettings(imbh_mass=request.param, n_stars=N_STARS, include_remnants=False)
    model = build_cluster_model(settings)
    stars, _ = sample_stars(settings, seed=3, model=model)
    m = model.mass
    ref = JeansReference(m.density, m.bh_mass, m.r[0], m.r_max)
    return settings, model, stars, ref


def test_projected_dispersion_matches_isotropic_jeans(sampled):
    _, _, stars, ref = sampled
    R, v_rad, v_tan = _sky_components(stars)
    sigma2 = sigma2_interpolator(ref, R.min(), R.max())
    for v in (v_rad, v_tan, stars["vz"]):
        chi2, dof = binned_dispersion_chi2(R, v, sigma2, N_BINS, min_per_bin=4000)
        assert chi2 / dof < 2.0, (chi2, dof)


def test_jeans_test_detects_the_wrong_black_hole(sampled):
    """The same statistic rejects the other model (IMBH vs none): the test has power."""
    settings, model, stars, _ = sampled
    other_bh = 0.0 if model.mass.bh_mass > 0 else 1500.0
    m = model.mass
    wrong = JeansReference(m.density, other_bh, m.r[0], m.r_max)
    R, v_rad, _ = _sky_components(stars)
    chi2, dof = binned_dispersion_chi2(
        R, v_rad, sigma2_interpolator(wrong, R.min(), R.max()), N_BINS, 4000
    )
    assert chi2 / dof > 5.0


def test_surface_density_matches_projection(sampled):
    settings, model, stars, ref = sampled
    R = np.hypot(stars["x"], stars["y"])
    field = stars["region"] == 0
    half = arcsec_to_pc(settings.field_size / 2, model.params["distance"])
    edges = np.quantile(R[field], np.linspace(0, 1, 26))
    counts, _ = np.histogram(R[field], edges)
    grid = np.linspace(edges[0], edges[-1], 3000)
    nodes = np.geomspace(grid[1], grid[-1], 50)
    sig = np.array([ref.surface_density(r) for r in nodes])
    sig_grid = np.exp(np.interp(np.log(np.maximum(grid, grid[1])), np.log(nodes), np.log(sig)))
    weight = sig_grid * grid * arc_measure(grid, half, half, "field")
    cum = np.concatenate([[0], np.cumsum(0.5 * (weight[1:] + weight[:-1]) * np.diff(grid))])
    expected = np.diff(np.interp(edges, grid, cum)) / cum[-1] * field.sum()
    chi2 = np.sum((counts - expected) ** 2 / expected)
    assert chi2 / (len(counts) - 1) < 2.0


def test_every_star_is_bound_and_df_nonnegative(sampled):
    _, model, stars, _ = sampled
    psi = model.mass.relative_potential(stars["r3d"])
    energy = psi - 0.5 * (stars["vx"] ** 2 + stars["vy"] ** 2 + stars["vz"] ** 2)
    assert np.all(energy > 0)
    assert np.all(model.df(energy) >= 0)
    assert np.all(model.df.f >= 0)
    assert model.df.min_raw >= -1e-6


def test_field_holds_requested_luminous_count(sampled):
    settings, _, stars, _ = sampled
    assert np.count_nonzero((stars["region"] == 0) & stars["luminous"]) == settings.n_stars


@pytest.mark.slow
@pytest.mark.parametrize("tracer", ["plummer", "king"])
@pytest.mark.parametrize("imbh", [0.0, 1500.0])
def test_million_star_dispersion_profiles_match_jeans(tracer, imbh):
    """Science-grade version: 1e6 field stars, 30 bins, both tracers."""
    settings = ClusterSettings(
        imbh_mass=imbh, n_stars=1_000_000, tracer=tracer, include_remnants=False
    )
    model = build_cluster_model(settings)
    stars, _ = sample_stars(settings, seed=21, model=model)
    m = model.mass
    ref = JeansReference(m.density, m.bh_mass, m.r[0], m.r_max)
    R, v_rad, v_tan = _sky_components(stars)
    sigma2 = sigma2_interpolator(ref, R.min(), R.max(), n=60)
    for v in (v_rad, v_tan):
        chi2, dof = binned_dispersion_chi2(R, v, sigma2, 30, min_per_bin=30_000)
        assert chi2 / dof < 2.0, (chi2, dof)
