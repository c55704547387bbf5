"""The line-of-sight mixture with a fitted local kurtosis (``velocity_law =
"line_of_sight_kurtosis"``, :mod:`mavispm.dynamics.line_of_sight_kurtosis`): kappa = 0 is
the line-of-sight law, the compiled sums equal the numpy reference, the density integrates
to one with the mixture's analytic second and fourth moments; the settings."""

import numpy as np
import pytest

from mavispm.dynamics.anisotropy import Anisotropy
from mavispm.dynamics.fit import make_likelihood, parameter_space
from mavispm.dynamics.jeans import JeansProjector
from mavispm.dynamics.likelihood import DiscreteLikelihood, StarSample
from mavispm.dynamics.line_of_sight import mixture_star_sums
from mavispm.dynamics.line_of_sight_kurtosis import (
    kurtosis_mixture_ln_densities,
    kurtosis_mixture_star_sums,
    kurtosis_mixture_star_sums_about,
    kurtosis_mixture_star_sums_numpy,
)
from mavispm.dynamics.settings import DynamicsSettings
from mavispm.dynamics.star_sums import stars_about
from mavispm.dynamics.tracers import make_tracer

KAPPAS = (-1.9, -0.7, -0.05, 0.0, 0.3, 1.4, 2.9)


def _mixture(bh=0.05, beta=0.2):
    X = np.geomspace(1e-3, 5.0, 24)
    proj = JeansProjector(X, n_panels=24, n_gl=6)
    tracer = make_tracer("plummer", 0.8, 1.5, cusp_radius=0.1)
    mix = proj.line_of_sight(tracer, Anisotropy(beta, beta, 1.0), None, np.array([1.0, bh, 0.05]))
    return np.log(proj.X), mix


def _random_stars(lnx, n, seed):
    rng = np.random.default_rng(seed)
    u = rng.uniform(lnx[0] - 1, lnx[-1] + 1, n)
    v2 = rng.gamma(1.0, 0.05, (2, n))
    e2 = rng.uniform(1e-4, 1e-2, (2, n))
    return u, v2, e2


def test_kappa_zero_is_the_line_of_sight_law_on_random_tables():
    """Random (positive) component tables and stars: kappa = 0 gives the line-of-sight law's
    compiled sums (:func:`mixture_star_sums`, an independent kernel) to rounding."""
    rng = np.random.default_rng(5)
    m, k, n = 20, 16, 700
    w, s2r, s2t = rng.random((m, k)), rng.uniform(0.05, 3, (m, k)), rng.uniform(0.05, 3, (m, k))
    ln_sig = rng.normal(size=m)
    u = rng.uniform(-1.7, 2.5, n)
    v2 = rng.normal(size=(2, n)) ** 2 * 2
    e2 = rng.uniform(0.01, 0.5, (2, n))
    args = (u, -1.5, 0.2, w, s2r, s2t, ln_sig, v2, e2)
    got = kurtosis_mixture_star_sums(*args, 0.0)
    ref = mixture_star_sums(*args)
    np.testing.assert_allclose(got, ref, rtol=1e-13)
    assert kurtosis_mixture_star_sums(*args, -0.5)[0] != pytest.approx(ref[0], rel=1e-6)


def _stars(seed, n=300):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-8, 8, (2, n))
    R = np.hypot(x, y)
    e = rng.uniform(0.02, 0.06, n)
    return StarSample(R, rng.normal(0, 0.3, n), rng.normal(0, 0.3, n), e, e * 1.2, 12.0, x=x, y=y)


@pytest.mark.parametrize("moving", [False, True])
def test_likelihood_at_kappa_zero_is_the_line_of_sight_likelihood(moving):
    """DiscreteLikelihood(velocity_law="line_of_sight_kurtosis") at kappa = 0 equals the
    line-of-sight law's ln L (star counts included) to rounding; kappa != 0 changes it,
    kappa outside (-2, 3) is -inf."""
    stars = _stars(1)
    base = ["log_mass", "log_scale_radius", "bh_mass", "beta"]
    theta = [5.2, 1.9, 1500.0, 0.1]
    if moving:
        base += ["x0", "y0", "pm_x0", "pm_y0"]
        theta += [0.3, -0.2, 0.01, -0.02]
    kw = dict(tracer="plummer", distance=4.6, scale_radius_range=(10.0, 1000.0), grid_size=32)
    los = DiscreteLikelihood(stars, base, velocity_law="line_of_sight", **kw)
    kur = DiscreteLikelihood(stars, [*base, "kappa"], velocity_law="line_of_sight_kurtosis", **kw)
    ref = los(np.array(theta))
    assert np.isfinite(ref)
    assert kur(np.array([*theta, 0.0])) == pytest.approx(ref, rel=1e-12, abs=1e-9)
    assert abs(kur(np.array([*theta, -0.8])) - ref) > 1e-3
    assert kur(np.array([*theta, 3.0])) == -np.inf


@pytest.mark.parametrize("kappa", KAPPAS)
def test_compiled_sums_equal_numpy_reference(kappa):
    """Compiled sums == the numpy reference (shape_law.shape_density per node, log-sum-exp)
    to 1e-10 on a Jeans model's mixture, and the about-the-centre form == stars_about then
    the sums."""
    lnx, (w, s2r, s2t, ln_sig, _) = _mixture()
    u, v2, e2 = _random_stars(lnx, 400, 3)
    args = (u, lnx[0], lnx[1] - lnx[0], w, s2r, s2t, ln_sig, v2, e2)
    got = kurtosis_mixture_star_sums(*args, kappa)
    np.testing.assert_allclose(got, kurtosis_mixture_star_sums_numpy(*args, kappa), rtol=1e-10)
    rng = np.random.default_rng(4)
    n = 300
    x, y = rng.uniform(-3, 3, (2, n))
    pmx, pmy = rng.normal(0, 0.3, (2, n))
    er2, et2 = rng.uniform(1e-4, 1e-2, (2, n))
    cx, sy = x / np.hypot(x, y), y / np.hypot(x, y)
    centre = (0.2, -0.1, 0.01, -0.02, 1e-3)
    ln_a = 0.3
    ln_r, v2a, e2a = stars_about(x, y, pmx, pmy, cx, sy, er2, et2, *centre)
    about = kurtosis_mixture_star_sums_about(
        x, y, pmx, pmy, cx, sy, er2, et2, *centre, ln_a, lnx[0], lnx[1] - lnx[0],
        w, s2r, s2t, ln_sig, kappa,
    )  # fmt: skip
    direct = kurtosis_mixture_star_sums_numpy(
        ln_r - ln_a, lnx[0], lnx[1] - lnx[0], w, s2r, s2t, ln_sig, v2a, e2a, kappa
    )
    np.testing.assert_allclose(about, direct, rtol=1e-10)


@pytest.mark.parametrize("kappa", [-1.5, -0.4, 0.0, 0.8, 2.5])
def test_density_integrates_to_one_with_the_mixture_moments(kappa):
    """One star's density summed over a fine (v_R, v_T) grid: 1 to 1e-7, variance
    sum_k W_k (s_R,k^2 + e^2) and fourth moment sum_k W_k [3 (s_R,k^2 + e^2)^2 + kappa s_R,k^4]
    (each node's component: variance s^2 + e^2, fourth cumulant kappa s^4) to 1e-5."""
    lnx, (w, s2r, s2t, _, _) = _mixture()
    j = 8
    uj = lnx[j]  # on a grid point: the components are the table's row
    sd = np.sqrt(np.max(s2r[j]))
    e2 = 1e-3 * np.sum(w[j] * s2r[j])
    v = np.linspace(-12 * sd, 12 * sd, 1201)
    vr, vt = (g.ravel() for g in np.meshgrid(v, v, indexing="ij"))
    u = np.full(vr.size, uj)
    v2 = np.stack([vr * vr, vt * vt])
    ln_p = kurtosis_mixture_ln_densities(
        u, lnx[0], lnx[1] - lnx[0], w, s2r, s2t, v2, np.full_like(v2, e2), kappa
    )
    p = np.exp(ln_p)
    dv2 = (v[1] - v[0]) ** 2
    assert np.sum(p) * dv2 == pytest.approx(1.0, abs=1e-7)
    wn = w[j] / w[j].sum()
    m2 = np.sum(wn * (s2r[j] + e2))
    m4 = np.sum(wn * (3 * (s2r[j] + e2) ** 2 + kappa * s2r[j] ** 2))
    assert np.sum(p * vr**2) * dv2 == pytest.approx(m2, rel=1e-5)
    assert np.sum(p * vr**4) * dv2 == pytest.approx(m4, rel=1e-5)
    m2t = np.sum(wn * (s2t[j] + e2))
    assert np.sum(p * vt**2) * dv2 == pytest.approx(m2t, rel=1e-5)


def test_settings_put_kappa_in_the_parameter_space():
    """velocity_law "line_of_sight_kurtosis": one kappa, uniform on kappa_range, in the
    parameter space and the likelihood; a radial kappa profile and bad ranges rejected."""
    s = DynamicsSettings(velocity_law="line_of_sight_kurtosis", kappa_range=(-1.0, 2.0))
    space = parameter_space(s, 4.6, "imbh")
    p = space.params[space.index("kappa")]
    assert (p.prior, p.lo, p.hi) == ("uniform", -1.0, 2.0)
    assert not any(n.startswith("kappa_") for n in space.names)
    like = make_likelihood(_stars(2), space, s, 4.6)
    assert like.velocity_law == "line_of_sight_kurtosis"
    for bad in [
        dict(kappa_profile="radial"),
        dict(kappa_range=(-2.0, 1.0)),
        dict(kappa_range=(0.5, 0.2)),
    ]:
        with pytest.raises(ValueError):
            DynamicsSettings(velocity_law="line_of_sight_kurtosis", **bad)
