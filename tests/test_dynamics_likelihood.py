"""Discrete likelihood: brute-force check, edge cases, bad input."""

import astropy.units as u
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.errors import InputError
from mavispm.dynamics.jeans import projected_dispersion
from mavispm.dynamics.likelihood import DiscreteLikelihood, StarSample
from mavispm.dynamics.parameters import Parameter, ParameterSpace
from mavispm.dynamics.tracers import Plummer

NAMES = ["log_mass", "log_scale_radius", "bh_mass", "beta"]


def _stars(n=50, seed=0, R=None, err=0.05):
    rng = np.random.default_rng(seed)
    R = rng.uniform(0.0, 17.0, n) if R is None else np.asarray(R, float)
    v = rng.normal(0, 0.3, (2, R.size))
    e = np.broadcast_to(np.asarray(err, float), R.shape).copy()
    return StarSample(R, v[0], v[1], e, e, 17.0)


def test_likelihood_matches_brute_force():
    """Per-star sum written out directly with the unit-aware model and analytic Plummer counts."""
    s = _stars(40, R=np.linspace(0.2, 16.9, 40))
    like = DiscreteLikelihood(s, NAMES, distance=4.6)
    theta = np.array([5.0, 1.6, 2000.0, 0.2])
    a = 10**1.6
    sr, st_ = projected_dispersion(
        s.R * u.arcsec,
        1e5 * u.Msun,
        a * u.arcsec,
        bh_mass=2000 * u.Msun,
        beta=0.2,
        distance=4.6 * u.kpc,
    )
    var_r = sr.value**2 + s.e_r**2
    var_t = st_.value**2 + s.e_t**2
    kin = -0.5 * np.sum(
        s.v_r**2 / var_r + np.log(2 * np.pi * var_r) + s.v_t**2 / var_t + np.log(2 * np.pi * var_t)
    )
    pl = Plummer()
    counts = np.sum(np.log(pl.surface_density(s.R / a) / a**2 / pl.projected_enclosed(17.0 / a)))
    assert like(theta) == pytest.approx(kin + counts, abs=2e-3)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 30),
    err=st.sampled_from([0.0, 1e-9, 0.05, 1e4]),
    centre=st.booleans(),
    bh=st.sampled_from([0.0, 1e-12, 1e4, 1e7]),
    beta=st.sampled_from([-0.5, 0.0, 0.5, 0.95]),
    log_a=st.sampled_from([0.0, 1.5, 3.0]),
)
def test_likelihood_finite_at_edges(n, err, centre, bh, beta, log_a):
    """Single stars, zero/huge errors, stars at R = 0, M_bh at the prior edge: finite ln L."""
    s = _stars(n, seed=n, R=np.zeros(n) if centre else None, err=err)
    like = DiscreteLikelihood(s, NAMES, distance=4.6)
    val = like(np.array([5.0, log_a, bh, beta]))
    assert np.isfinite(val)


def test_invalid_parameters_give_minus_inf_not_errors():
    like = DiscreteLikelihood(_stars(), NAMES, distance=4.6)
    assert like(np.array([5.0, 1.0, -1.0, 0.0])) == -np.inf
    assert like(np.array([5.0, 1.0, 0.0, 1.0])) == -np.inf


def test_star_counts_constrain_scale_radius():
    """With kinematics uninformative (huge errors), counts alone peak near the true a."""
    rng = np.random.default_rng(3)
    a_true, n = 10.0, 4000
    q = rng.uniform(0, 1, 40 * n)
    R = a_true * np.sqrt(q / (1 - q))  # inverse CDF of the projected Plummer
    R = R[R < 17.0][:n]
    s = StarSample(
        R, np.zeros(R.size), np.zeros(R.size), np.full(R.size, 1e3), np.full(R.size, 1e3), 17.0
    )
    like = DiscreteLikelihood(s, NAMES, distance=4.6)
    grid = np.linspace(0.6, 1.5, 91)
    vals = [like(np.array([5.0, g, 0.0, 0.0])) for g in grid]
    best = 10 ** grid[int(np.argmax(vals))]
    assert 7.0 < best < 14.0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"e_r": -np.ones(3)}, "negative"),
        ({"v_r": np.array([np.nan, 0, 0])}, "non-finite"),
        ({"R": np.ones(2)}, "expected 2 values"),
    ],
)
def test_bad_star_samples_raise(kwargs, match):
    base = {
        "R": np.ones(3),
        "v_r": np.zeros(3),
        "v_t": np.zeros(3),
        "e_r": np.ones(3),
        "e_t": np.ones(3),
        "field_radius": 17.0,
    }
    with pytest.raises(InputError, match=match):
        StarSample(**{**base, **kwargs})


def test_parameter_scaling_round_trip_and_priors():
    sp = ParameterSpace(
        [Parameter("a", lo=2.0, hi=6.0), Parameter("d", prior="gaussian", mean=4.6, sd=0.2)]
    )
    v = np.array([3.0, 4.9])
    np.testing.assert_allclose(sp.from_scaled(sp.to_scaled(v)), v)
    np.testing.assert_allclose(sp.from_unit(np.array([0.5, 0.5])), [4.0, 4.6])
    assert sp.log_prior_scaled(np.array([1.5, 0.0])) == -np.inf
    with pytest.raises(ValueError):
        Parameter("x", lo=1.0, hi=1.0)


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 300),
    shift=st.floats(-8.0, 8.0),
    err_scale=st.sampled_from([0.0, 1e-3, 0.05, 1e3]),
    seed=st.integers(0, 10_000),
)
def test_fused_star_sums_match_numpy_reference(n, shift, err_scale, seed):
    """The numba star loop equals the vectorised numpy path, also for stars off the grid ends."""
    from mavispm.dynamics.star_sums import star_sums, star_sums_numpy

    rng = np.random.default_rng(seed)
    grid = np.linspace(-6.0, 2.0, 40)
    ln_s2 = np.stack([np.log(0.1 + np.exp(-grid)), np.log(0.2 + 0.5 * np.exp(-grid))])
    ln_sig = -2.0 * np.log1p(np.exp(grid))
    u_ = rng.uniform(-7.0, 3.0, n) + shift
    v2 = rng.normal(0, 0.4, (2, n)) ** 2
    e2 = (err_scale * rng.uniform(0.5, 1.5, (2, n))) ** 2
    step = grid[1] - grid[0]
    fused = star_sums(u_, grid[0], step, ln_s2, ln_sig, v2, e2)
    ref = star_sums_numpy(u_, grid[0], step, ln_s2, ln_sig, v2, e2)
    np.testing.assert_allclose(fused, ref, rtol=1e-10, atol=1e-9)


def test_influence_linked_cusp():
    """cusp_link = "influence": the cusp radius encloses 2 M_bh of the cored King62 profile,
    the no-IMBH model is the plain King62 profile (no cusp parameters), and M_bh = 0 in the
    IMBH model gives the no-IMBH likelihood."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings
    from mavispm.dynamics.tracers import Cusped, King62

    s = DynamicsSettings(tracer="king", king_concentration=1.33, cusp=True, cusp_link="influence")
    sp1, sp0 = parameter_space(s, 4.6, True), parameter_space(s, 4.6, False)
    assert sp1.names == ["log_mass", "log_scale_radius", "bh_mass", "beta", "gamma"]
    assert sp0.names == ["log_mass", "log_scale_radius", "beta"]
    stars = _stars(200, seed=4)
    l1, l0 = make_likelihood(stars, sp1, s, 4.6), make_likelihood(stars, sp0, s, 4.6)
    theta = np.array([5.2, 1.9, 3000.0, 0.1, 1.55])
    tracer = l1._influence_cusp(theta, 3000.0, 10**5.2)
    assert isinstance(tracer, Cusped) and tracer.gamma == 1.55
    assert King62(1.33).enclosed(tracer.cusp_radius) == pytest.approx(6000.0 / 10**5.2, rel=1e-4)
    no_bh = theta.copy()
    no_bh[2] = 0.0
    assert l1(no_bh) == pytest.approx(l0(theta[[0, 1, 3]]), rel=1e-12)
    assert np.isfinite(l1(theta)) and l1(theta) != l1(no_bh)
