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
    """Per-star sum written out directly with the unit-aware model and analytic Plummer counts
    (the Gaussian velocity law)."""
    s = _stars(40, R=np.linspace(0.2, 16.9, 40))
    like = DiscreteLikelihood(s, NAMES, distance=4.6, velocity_law="gaussian")
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


@pytest.mark.parametrize("law", ["line_of_sight", "gaussian"])
def test_non_finite_parameters_give_minus_inf(law):
    """A NaN or infinite entry anywhere in the vector of the richest model (cusp, dark
    component, centre, distance, systemic motion) gives -inf, never an exception."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample(n=200)
    s = DynamicsSettings(velocity_law=law)
    sp = parameter_space(s, 4.6, "imbh_dark")
    lk = make_likelihood(stars, sp, s, 4.6)
    theta = sp.from_scaled(np.full(len(sp), 0.1))
    assert np.isfinite(lk(theta))
    for i in range(len(sp)):
        for bad in (np.nan, np.inf, -np.inf):
            t = theta.copy()
            t[i] = bad
            assert lk(t) == -np.inf, (sp.names[i], bad)


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
    # the vectorised unit-cube transform: uniform quantile and the Gaussian 97.5% point
    np.testing.assert_allclose(sp.from_unit([0.25, 0.975]), [3.0, 4.6 + 0.2 * 1.959963984540054])
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


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 400),
    ln_s2_shift=st.sampled_from([0.0, -300.0, -700.0, 250.0, 690.0]),
    err_scale=st.sampled_from([0.0, 1e-60, 1e-3, 1e3, 1e80]),
    seed=st.integers(0, 10_000),
)
def test_star_log_products_never_overflow(n, ln_s2_shift, err_scale, seed):
    """ln var summed through running products equals the plain sum of logarithms, also for
    variances far outside [1e-100, 1e100] and products that would under- or overflow."""
    from mavispm.dynamics.star_sums import star_sums, star_sums_numpy

    rng = np.random.default_rng(seed)
    grid = np.linspace(-6.0, 2.0, 40)
    ln_s2 = np.stack([-grid, 0.3 - grid]) + ln_s2_shift
    ln_sig = -2.0 * np.log1p(np.exp(grid))
    u_ = rng.uniform(-7.0, 3.0, n)
    v2 = rng.normal(0, 0.4, (2, n)) ** 2
    e2 = (err_scale * rng.uniform(0.5, 1.5, (2, n))) ** 2
    fused = star_sums(u_, grid[0], grid[1] - grid[0], ln_s2, ln_sig, v2, e2)
    ref = star_sums_numpy(u_, grid[0], grid[1] - grid[0], ln_s2, ln_sig, v2, e2)
    if np.isfinite(ref[0]):
        np.testing.assert_allclose(fused, ref, rtol=1e-12)
    else:
        assert fused[0] == ref[0]


def test_star_sums_refuse_grids_too_short_for_cubic_weights():
    from mavispm.dynamics.star_sums import star_sums

    grid = np.linspace(0.0, 1.0, 3)
    with pytest.raises(ValueError, match="n >= 4"):
        star_sums(np.zeros(2), 0.0, 0.5, np.zeros((2, 3)), grid, np.ones((2, 2)), np.ones((2, 2)))


def test_star_sums_about_equal_moved_stars_then_numpy_sums():
    """The one-pass moved-star sums equal the numpy star move followed by the numpy sums."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings
    from mavispm.dynamics.star_sums import star_sums_numpy

    _, stars = _mock_sample(n=300)
    s = DynamicsSettings(velocity_law="free_kurtosis")
    sp = parameter_space(s, 4.6, "imbh")
    like = make_likelihood(stars, sp, s, 4.6)
    rng = np.random.default_rng(3)
    for _ in range(5):
        theta = sp.from_unit(rng.uniform(0.01, 0.99, len(sp)))
        ln_s2, ln_sig, _ = like.log_model_on_grid(theta)
        ln_a = np.log(10.0) * theta[sp.index("log_scale_radius")]
        lnR, v2, e2 = like._stars_about_numpy(theta)
        ref = star_sums_numpy(lnR - ln_a, like.lnX_grid[0], like.step, ln_s2, ln_sig, v2, e2)
        np.testing.assert_allclose(like._star_sums(theta, ln_a, ln_s2, ln_sig), ref, rtol=1e-12)


@pytest.mark.parametrize("aniso", ["constant", "osipkov-merritt", "general"])
@pytest.mark.parametrize("tracer", ["plummer", "king62"])
def test_compiled_grid_model_equals_numpy_model(aniso, tracer):
    """The likelihood's compiled grid model equals the numpy one (Jeans moments weighted by
    the masses) for every dark-centre model, at random prior draws."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample(n=50)
    s = DynamicsSettings(
        tracer=tracer, king_concentration=1.33, anisotropy=aniso, velocity_law="free_kurtosis"
    )
    rng = np.random.default_rng(11)
    for model in ("none", "imbh", "dark", "imbh_dark"):
        sp = parameter_space(s, 4.6, model)
        like = make_likelihood(stars, sp, s, 4.6)
        for _ in range(3):
            theta = sp.from_unit(rng.uniform(0.01, 0.99, len(sp)))
            _, s2, ln_sig, ln_proj = like.model_on_grid(theta)
            got = like.log_model_on_grid(theta)
            np.testing.assert_allclose(got[0], np.log(s2), rtol=0, atol=1e-11)
            np.testing.assert_allclose(got[1], ln_sig, rtol=0, atol=1e-11)
            np.testing.assert_allclose(got[2], ln_proj, rtol=0, atol=1e-11)


def _mock_sample(n=400, seed=4):
    from dynamics_helpers import mock_pm_stars

    d = mock_pm_stars(seed, n_field=n, mass=5e4, a_arcsec=25.0, bh_mass=1500.0, distance=4.6)
    return d, StarSample(
        d["R"], d["pm_r"], d["pm_t"], d["pm_r_err"], d["pm_t_err"], 17.0, x=d["x"], y=d["y"]
    )


def test_nested_models_reduce_to_no_dark_centre():
    """Every model has the free cusp; M_bh = 0 and M_dark = 0 give the no-dark-centre ln L."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample()
    for aniso in ("constant", "osipkov-merritt"):
        s = DynamicsSettings(
            tracer="king62", king_concentration=1.33, anisotropy=aniso, velocity_law="free_kurtosis"
        )
        base = parameter_space(s, 4.6, "none")
        assert {"gamma", "log_cusp_radius"} <= set(base.names)
        v0 = base.as_dict(base.from_scaled(np.full(len(base), 0.1)))
        ref = make_likelihood(stars, base, s, 4.6)(np.array(list(v0.values())))
        for model in ("imbh", "dark", "imbh_dark"):
            sp = parameter_space(s, 4.6, model)
            assert {"gamma", "log_cusp_radius"} <= set(sp.names)
            v = {**v0, "bh_mass": 0.0, "dark_mass": 0.0, "log_dark_radius": 0.3}
            val = make_likelihood(stars, sp, s, 4.6)(np.array([v[n] for n in sp.names]))
            assert val == pytest.approx(ref, abs=1e-8)
            v["dark_mass" if "dark_mass" in sp.names else "bh_mass"] = 2000.0
            assert make_likelihood(stars, sp, s, 4.6)(np.array([v[n] for n in sp.names])) != ref


def test_centre_and_systemic_motion_are_nuisances_of_the_frame():
    """Shifting every star and the model centre (or every PM and the systemic motion) by the
    same amount leaves ln L unchanged: the fitted centre and mean motion act exactly."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.profiles import radial_tangential
    from mavispm.dynamics.settings import DynamicsSettings

    d, stars = _mock_sample()
    s = DynamicsSettings(
        star_counts=False, velocity_law="free_kurtosis"
    )  # the field circle does not move with the stars
    sp = parameter_space(s, 4.6, "imbh")
    v = sp.as_dict(sp.from_scaled(np.zeros(len(sp))))
    v.update(x0=0.0, y0=0.0, pm_x0=0.0, pm_y0=0.0)
    like = make_likelihood(stars, sp, s, 4.6)
    ref = like(np.array([v[n] for n in sp.names]))
    dx, dy, mx, my = 0.7, -0.4, 0.03, -0.02
    x, y = d["x"] + dx, d["y"] + dy
    pmx = d["pm_r"] * d["x"] / d["R"] - d["pm_t"] * d["y"] / d["R"] + mx
    pmy = d["pm_r"] * d["y"] / d["R"] + d["pm_t"] * d["x"] / d["R"] + my
    R, vr, vt = radial_tangential(x, y, pmx, pmy)
    err = d["pm_r_err"]  # isotropic errors: e_r = e_t per star in the mock? use one value
    moved = StarSample(R, vr, vt, err, err, 17.0, x=x, y=y)
    same = StarSample(d["R"], d["pm_r"], d["pm_t"], err, err, 17.0, x=d["x"], y=d["y"])
    ref = make_likelihood(same, sp, s, 4.6)(np.array([v[n] for n in sp.names]))
    v.update(x0=dx, y0=dy, pm_x0=mx, pm_y0=my)
    got = make_likelihood(moved, sp, s, 4.6)(np.array([v[n] for n in sp.names]))
    assert got == pytest.approx(ref, abs=1e-6)
    assert like(np.array([v[n] for n in sp.names])) < ref - 1.0  # the offset matters


@pytest.mark.parametrize("offset", [0.0, 2.0])
def test_field_normalisation_with_offset_centre_and_completeness(offset):
    """N_field for a centre offset and a radial completeness vs scipy dblquad over the disc."""
    from scipy import integrate

    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample(n=50)
    radii, comp = (0.0, 5.0, 17.0, 30.0), (0.4, 0.8, 1.0, 1.0)
    s = DynamicsSettings(
        cusp=False,
        completeness_radius=radii,
        completeness=comp,
        systemic_error=0.0,
        velocity_law="free_kurtosis",
    )
    sp = parameter_space(s, 4.6, "none")
    like = make_likelihood(stars, sp, s, 4.6)
    a = 25.0
    v = sp.as_dict(sp.from_scaled(np.zeros(len(sp))))
    v.update(log_scale_radius=np.log10(a), x0=offset, y0=0.0)
    _, _, ln_sig, ln_proj = like.model_on_grid(np.array([v[n] for n in sp.names]))
    got = like.ln_field_norm(np.log(a), offset, ln_sig, ln_proj)

    def f(r, phi):  # field-centred polar coordinates; Plummer Sigma about the model centre
        Rm = np.hypot(r * np.cos(phi) - offset, r * np.sin(phi))
        return r * (1 / np.pi / a**2) * (1 + (Rm / a) ** 2) ** -2 * np.interp(Rm, radii, comp)

    ref = integrate.dblquad(f, 0, 2 * np.pi, 0, 17.0, epsrel=1e-9)[0]
    assert got == pytest.approx(np.log(ref), abs=2e-4)


def test_fused_stars_about_matches_numpy_reference():
    """The numba kernel that moves the stars to the model centre equals the numpy path."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample(n=300)
    s = DynamicsSettings(velocity_law="free_kurtosis")
    sp = parameter_space(s, 4.6, "none")
    like = make_likelihood(stars, sp, s, 4.6)
    v = sp.as_dict(sp.from_scaled(np.zeros(len(sp))))
    v.update(x0=0.8, y0=-1.3, pm_x0=0.02, pm_y0=-0.04)
    theta = np.array([v[n] for n in sp.names])
    for a, b in zip(like._stars_about(theta), like._stars_about_numpy(theta)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


def test_likelihood_does_not_depend_on_the_order_of_the_stars():
    """The same stars in another order give the same ln L (the line-of-sight sums group
    the stars by grid interval; line-of-sight and Gaussian laws, centre and systemic
    motion fitted)."""

    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample(n=400)
    order = np.random.default_rng(4).permutation(400)
    names = ("R", "v_r", "v_t", "e_r", "e_t", "x", "y")
    shuffled = StarSample(
        field_radius=stars.field_radius, **{k: getattr(stars, k)[order] for k in names}
    )
    for law in ("line_of_sight", "gaussian"):
        s = DynamicsSettings(velocity_law=law)
        sp = parameter_space(s, 4.6, "imbh")
        v = sp.as_dict(sp.from_scaled(np.zeros(len(sp))))
        v.update(x0=0.8, y0=-1.3, pm_x0=0.02, pm_y0=-0.04)
        theta = np.array([v[n] for n in sp.names])
        a = make_likelihood(stars, sp, s, 4.6)(theta)
        b = make_likelihood(shuffled, sp, s, 4.6)(theta)
        assert np.isfinite(a) and b == pytest.approx(a, rel=1e-13)


def test_general_anisotropy_contains_constant_and_osipkov_merritt():
    """anisotropy = "general" (beta_0, beta_inf, r_a): beta_0 = beta_inf is the constant-beta
    likelihood, (0, 1) the Osipkov-Merritt one; an invalid beta_inf gives -inf."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    _, stars = _mock_sample(n=200)
    gen = DynamicsSettings(
        anisotropy="general", beta_inf_range=(-0.5, 1.0), velocity_law="free_kurtosis"
    )
    sp = parameter_space(gen, 4.6, "imbh")
    assert {"beta_0", "beta_inf", "log_anisotropy_radius"} <= set(sp.names)
    lk = make_likelihood(stars, sp, gen, 4.6)
    v = sp.as_dict(sp.from_scaled(np.full(len(sp), 0.1)))

    def other(aniso, **vals):
        s = DynamicsSettings(anisotropy=aniso, velocity_law="free_kurtosis")
        sp2 = parameter_space(s, 4.6, "imbh")
        w = {**v, **vals}
        return make_likelihood(stars, sp2, s, 4.6)(np.array([w[n] for n in sp2.names]))

    const = lk(np.array([{**v, "beta_0": 0.2, "beta_inf": 0.2}[n] for n in sp.names]))
    assert const == pytest.approx(other("constant", beta=0.2), abs=1e-9)
    om = lk(np.array([{**v, "beta_0": 0.0, "beta_inf": 1.0}[n] for n in sp.names]))
    assert om == pytest.approx(other("osipkov-merritt"), abs=1e-9)
    assert lk(np.array([{**v, "beta_inf": 1.2}[n] for n in sp.names])) == -np.inf
    with pytest.raises(ValueError, match="beta_inf_range"):
        DynamicsSettings(anisotropy="general", beta_inf_range=(0.0, 1.5))
