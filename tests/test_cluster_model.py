"""Mass models and the Eddington DF against analytic results."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.simulate.cluster.eddington import NoIsotropicDFError, eddington_df
from mavispm.simulate.cluster.field_sampler import build_field_sampler
from mavispm.simulate.cluster.profiles import (
    G_PC,
    TracerProfile,
    build_mass_model,
    influence_radius,
    projected_radii,
)


def test_plummer_df_matches_analytic():
    a, mass = 2.0, 1e5
    model = build_mass_model(TracerProfile("plummer", a), mass)
    df = eddington_df(model)
    shift = G_PC * mass / model.r_max  # Psi is measured from the truncation radius
    e = df.energy
    analytic = 24 * np.sqrt(2) / (7 * np.pi**3) * a**2 / (G_PC**5 * mass**4) * (e + shift) ** 3.5
    sel = e > 0.01 * G_PC * mass / a
    np.testing.assert_allclose(df.f[sel], analytic[sel], rtol=1e-3)


@pytest.mark.parametrize("w0", [3.0, 6.3, 9.0])
def test_king_df_is_the_lowered_isothermal(w0):
    """Eddington inversion of King's density recovers f ~ exp(E / sigma^2) - 1."""
    model = build_mass_model(TracerProfile("king", 2.0, w0), 1e5)
    df = eddington_df(model)
    sigma2 = model.psi.max() / w0
    e = df.energy
    sel = e > 1e-3 * model.psi.max()
    ratio = df.f[sel] / np.expm1(e[sel] / sigma2)
    np.testing.assert_allclose(ratio / np.median(ratio), 1.0, rtol=5e-3)


def test_plummer_mass_and_potential_match_analytic():
    a, mass = 3.0, 2e4
    model = build_mass_model(TracerProfile("plummer", a), mass)
    r = np.geomspace(0.01, 100, 20)
    np.testing.assert_allclose(
        model.enclosed_stellar_mass(r), mass * r**3 / (r**2 + a**2) ** 1.5, rtol=1e-4
    )
    psi_inf = G_PC * mass / np.sqrt(r**2 + a**2) - G_PC * mass / model.r_max
    np.testing.assert_allclose(model.relative_potential(r), psi_inf, rtol=1e-4)


def test_plummer_projected_radii():
    core, half = projected_radii(TracerProfile("plummer", 1.0))
    assert core == pytest.approx(np.sqrt(np.sqrt(2) - 1), rel=2e-3)
    assert half == pytest.approx(1.0, rel=2e-3)


def test_point_mass_potential_dominates_inside_influence_radius():
    tracer = TracerProfile("king", 2.0, 6.0, 1.55, 0.2)
    model = build_mass_model(tracer, 1e5, 1500.0)
    r = 1e-4
    assert model.relative_potential(r) == pytest.approx(G_PC * 1500 / r, rel=1e-2)


@pytest.mark.parametrize("gamma", [0.0, 0.3, 0.49])
def test_cored_tracer_around_black_hole_is_refused(gamma):
    tracer = TracerProfile("plummer", 1.0, cusp_gamma=gamma, cusp_radius=0.1 if gamma else 0.0)
    model = build_mass_model(tracer, 1e5, 1000.0)
    with pytest.raises(NoIsotropicDFError, match="An & Evans"):
        eddington_df(model)


@pytest.mark.parametrize("gamma", [0.6, 1.0, 1.55, 2.0])
def test_cusp_around_black_hole_has_positive_df(gamma):
    base = TracerProfile("king", 1.5, 7.0)
    rc = influence_radius(base, 1e5, 1000.0)
    model = build_mass_model(TracerProfile("king", 1.5, 7.0, gamma, rc), 1e5, 1000.0)
    df = eddington_df(model)
    assert np.all(df.f >= 0) and df.min_raw >= -1e-6
    # deep in the cusp f(E) ~ E^(gamma - 3/2)
    e = df.energy[-40:]
    slope = np.polyfit(np.log(e), np.log(df.f[-40:]), 1)[0]
    assert slope == pytest.approx(gamma - 1.5, abs=0.08)


@settings(max_examples=30, deadline=None)
@given(
    log_mass=st.floats(2, 7),
    bh_fraction=st.floats(0, 0.1),
    log_scale=st.floats(-2, 2),
    kind=st.sampled_from(["plummer", "king"]),
    w0=st.floats(2, 9),
    seed=st.integers(0, 2**32 - 1),
)
def test_stress_models_are_finite_nonnegative_and_reproducible(
    log_mass, bh_fraction, log_scale, kind, w0, seed
):
    mass, scale = 10**log_mass, 10**log_scale
    bh = bh_fraction * mass
    tracer = TracerProfile(kind, scale, w0)
    if bh > 0:
        tracer = TracerProfile(kind, scale, w0, 1.55, influence_radius(tracer, mass, bh))
    model = build_mass_model(tracer, mass, bh)
    df = eddington_df(model)
    assert np.all(np.isfinite(df.f)) and np.all(df.f >= 0)
    sampler = build_field_sampler(model, df, half_size=0.33, margin=0.02)
    draws = []
    for _ in range(2):
        rng = np.random.default_rng(seed)
        stars = sampler.sample("field", rng.random((300, 4)), rng.random((300, 3)))
        draws.append(stars)
        for key, value in stars.items():
            assert np.all(np.isfinite(value)), key
        energy = stars["psi"] - 0.5 * (stars["vx"] ** 2 + stars["vy"] ** 2 + stars["vz"] ** 2)
        assert np.all(energy >= 0)
        assert np.all(np.abs(stars["x"]) <= 0.33 * (1 + 1e-9))
    for key in draws[0]:
        np.testing.assert_array_equal(draws[0][key], draws[1][key])
