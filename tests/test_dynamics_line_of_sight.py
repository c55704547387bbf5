"""Line-of-sight velocity mixture: against an independent dense integral, its limits and edges."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.dynamics.anisotropy import Anisotropy
from mavispm.dynamics.jeans import JeansProjector
from mavispm.dynamics.likelihood import DiscreteLikelihood, StarSample
from mavispm.dynamics.line_of_sight import (
    mixture_ln_densities,
    mixture_star_sums,
    mixture_star_sums_numpy,
)
from mavispm.dynamics.tracers import Plummer, make_tracer

NAMES = ["log_mass", "log_scale_radius", "bh_mass", "beta"]


def _ln_likelihood_against_forward_model(space, s, p, rng, nodes):
    """Kinematic ln L of 300 stars with 3-D Gaussian velocities drawn from ``p`` by the SBC
    forward model: its dense 4000-depth sum, and the likelihood's with each number of
    line-of-sight ``nodes``."""
    from sbc_helpers import SBC_DISTANCE, draw_sample, independent_line_of_sight_ln_likelihood

    from mavispm.dynamics.fit import make_likelihood

    stars = draw_sample(p, 300, rng, "3d")
    theta = np.array([p[n] for n in space.names])
    ref = independent_line_of_sight_ln_likelihood(p, stars)
    kin = [
        make_likelihood(
            stars,
            space,
            dataclasses.replace(s, line_of_sight_nodes=n),
            SBC_DISTANCE,
            star_counts=False,
        )(theta)
        for n in nodes
    ]
    return ref, kin


@pytest.mark.parametrize("model", ["imbh", "imbh_dark"])
def test_ln_likelihood_matches_independent_line_of_sight_integral(model):
    """Kinematic ln L of the full model (cusp, IMBH, dark component, beta, distance, centre
    and systemic motion off zero) for 300 stars with 3-D Gaussian velocities, against the
    SBC forward model's dense trapezoid sum over 4000 depths per star (written apart from
    the package): within 2e-3 with 24 nodes and 0.05 with the default 16. The Gaussian
    law misses by 2-60 on the same stars."""
    from sbc_helpers import draw_prior, sbc_space

    space, s = sbc_space(model)
    assert s.line_of_sight_nodes == 16
    for seed in range(2):
        rng = np.random.default_rng([seed, 7])
        p = draw_prior(space, rng)
        ref, (kin, kin16) = _ln_likelihood_against_forward_model(space, s, p, rng, (24, 16))
        assert kin == pytest.approx(ref, abs=2e-3)
        assert kin16 == pytest.approx(ref, abs=0.05)


@pytest.mark.parametrize("profile", [(-0.4, 0.9, 0.5), (0.0, 0.95, 1.5), (0.5, -0.5, 0.7)])
def test_general_anisotropy_ln_likelihood_matches_independent_line_of_sight_integral(profile):
    """The default general anisotropy profile (beta_0, beta_inf, log10 r_a [arcsec]) turning
    inside the field, 300 stars with 3-D Gaussian velocities, ``imbh_dark``: kinematic ln L
    within 5e-3 of the SBC forward model's 4000-depth sum with 32 line-of-sight nodes
    (measured 3.5e-3), and within 2e-3 per star with the default 16 (measured up to 0.50
    on 300 stars where beta climbs to 0.9-0.95 inside the field, 0.015 with |beta| <= 0.5;
    24 nodes: 0.09; two Gauss-Legendre panels split at t = 1.5-3 are worse)."""
    from sbc_helpers import draw_prior, sbc_space

    space, s = sbc_space("imbh_dark", anisotropy="general")
    rng = np.random.default_rng([2, 7])
    p = draw_prior(space, rng)
    p.update(zip(("beta_0", "beta_inf", "log_anisotropy_radius"), profile))
    ref, (kin, kin16) = _ln_likelihood_against_forward_model(space, s, p, rng, (32, 16))
    assert kin == pytest.approx(ref, abs=5e-3)
    assert kin16 == pytest.approx(ref, abs=2e-3 * 300)


def _projector_and_mixture(beta=0.2, bh=0.02, dark=None, n_nodes=16, tracer=None):
    X = np.geomspace(1e-3, 5.0, 24)
    proj = JeansProjector(X, n_panels=24, n_gl=6)
    tracer = tracer or make_tracer("plummer", 0.8, 1.5, cusp_radius=0.1)
    weights = np.array([1.0, bh, 0.05])
    aniso = Anisotropy(beta, beta, 1.0) if np.isscalar(beta) else beta
    mix = proj.line_of_sight(tracer, aniso, dark, weights, n_nodes)
    ln_s2, _, _ = proj.log_dispersions(tracer, aniso, dark, weights)
    return proj, mix, ln_s2


@pytest.mark.parametrize("beta", [0.0, 0.4, -0.5, Anisotropy(0.0, 0.8, 0.5)])
def test_mixture_second_moments_are_the_projected_dispersions(beta):
    """The mixture's variance is the projected second moment (Gauss-Legendre panels in the
    projector, a separate 32-node rule on the line of sight here): agree to 5e-5 (measured 7e-6)."""
    _, (w, s2r, s2t, _, _), ln_s2 = _projector_and_mixture(beta, dark=0.3, n_nodes=32)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.sum(w * s2r, axis=1), np.exp(ln_s2[0]), rtol=5e-5)
    np.testing.assert_allclose(np.sum(w * s2t, axis=1), np.exp(ln_s2[1]), rtol=5e-5)


@pytest.mark.parametrize(
    "name, gamma, tol",
    [("king62", 0.0, 1e-5), ("king62", 1.0, 1e-5), ("dehnen", 1.2, 2e-4)],
)
def test_truncated_and_dehnen_tracers_keep_the_second_moments(name, gamma, tol):
    """King62 (lines of sight end at its tidal radius; measured 1.6e-6) and Dehnen (r^-4
    tail beyond 100 scale radii left out; 7.6e-5) with 32 nodes."""
    tracer = make_tracer(name, gamma, 1.5, cusp_radius=0.1 if name == "king62" and gamma else None)
    _, (w, s2r, s2t, _, _), ln_s2 = _projector_and_mixture(0.3, dark=0.3, n_nodes=32, tracer=tracer)
    np.testing.assert_allclose(np.sum(w * s2r, axis=1), np.exp(ln_s2[0]), rtol=tol)
    np.testing.assert_allclose(np.sum(w * s2t, axis=1), np.exp(ln_s2[1]), rtol=tol)


def test_mixture_density_integrates_to_one_and_has_heavy_tails():
    """One star's mixture density summed over a fine (v_R, v_T) grid is 1 to 1e-8, and near an
    IMBH its kurtosis (15) is far above a Gaussian's (3): the line of sight mixes dispersions."""
    proj, (w, s2r, s2t, _, _), _ = _projector_and_mixture(bh=0.05)
    lnx = np.log(proj.X)
    sd = np.sqrt(np.sum(w[2] * s2r[2]))
    v = np.linspace(-40 * sd, 40 * sd, 1601)
    vr, vt = (g.ravel() for g in np.meshgrid(v, v, indexing="ij"))
    u = np.full(vr.size, 0.5 * (lnx[2] + lnx[3]))  # between grid points: interpolated
    v2 = np.stack([vr * vr, vt * vt])
    p = np.exp(mixture_ln_densities(u, lnx[0], lnx[1] - lnx[0], w, s2r, s2t, v2, v2 * 0 + 1e-6))
    dv2 = (v[1] - v[0]) ** 2
    assert np.sum(p) * dv2 == pytest.approx(1.0, abs=1e-8)
    m2 = np.sum(p * vr**2) * dv2
    assert np.sum(p * vr**4) * dv2 / m2**2 > 6.0


def test_compiled_mixture_sums_equal_numpy_reference_and_survive_far_outliers():
    """The compiled sums equal the log-sum-exp reference to 1e-10, also for stars 1e3
    dispersions out (every term underflows; the compiled kernel switches to logarithms)."""
    proj, (w, s2r, s2t, ln_sig, _), _ = _projector_and_mixture()
    lnx = np.log(proj.X)
    rng = np.random.default_rng(3)
    u = rng.uniform(lnx[0] - 1, lnx[-1] + 1, 500)
    v2 = rng.gamma(1.0, 0.05, (2, 500))
    v2[:, :5] = 1e6  # far outliers
    e2 = rng.uniform(1e-6, 1e-2, (2, 500))
    args = (u, lnx[0], lnx[1] - lnx[0], w, s2r, s2t, ln_sig, v2, e2)
    got = mixture_star_sums(*args)
    ref = mixture_star_sums_numpy(*args)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, ref, rtol=1e-10)


@pytest.mark.parametrize("spread", ["whole grid", "one interval", "beyond the ends"])
def test_compiled_mixture_sums_do_not_depend_on_the_order_of_the_stars(spread):
    """The compiled sums group the stars by grid interval (a counting sort) and evaluate
    each interval's stars together: for stars over the whole grid, all in one interval, or
    beyond both ends (clamped), in random and in reversed order, they equal the
    per-star log-sum-exp reference to 1e-12."""
    proj, (w, s2r, s2t, ln_sig, _), _ = _projector_and_mixture()
    lnx = np.log(proj.X)
    step = lnx[1] - lnx[0]
    rng = np.random.default_rng(11)
    n = 700
    if spread == "whole grid":
        u = rng.uniform(lnx[0], lnx[-1], n)
    elif spread == "one interval":
        u = lnx[7] + step * rng.uniform(0.01, 0.99, n)
    else:
        u = np.where(rng.uniform(size=n) < 0.5, lnx[0] - 3.0, lnx[-1] + 3.0)
        u += rng.uniform(-1.0, 1.0, n)
    v2 = rng.gamma(1.0, 0.05, (2, n))
    e2 = rng.uniform(1e-6, 1e-2, (2, n))
    ref = mixture_star_sums_numpy(u, lnx[0], step, w, s2r, s2t, ln_sig, v2, e2)
    for order in (np.arange(n), rng.permutation(n), np.arange(n)[::-1]):
        got = mixture_star_sums(
            u[order].copy(), lnx[0], step, w, s2r, s2t, ln_sig,
            v2[:, order].copy(), e2[:, order].copy(),
        )  # fmt: skip
        np.testing.assert_allclose(got, ref, rtol=1e-12)


@pytest.mark.parametrize("scale", [1e-2, 1e-120])
def test_compiled_sums_of_products_equal_the_sum_of_logs(scale):
    """The compiled sums take the stars' logarithms as logarithms of running products:
    6,000 stars at the centre of their distribution with the variances scaled by 1e-2
    (densities ~1e2 each: the product leaves [1e-150, 1e150] many times) or by 1e-120
    (densities above 1e100, logged one by one) equal the per-star log-sum-exp reference to
    1e-12."""
    proj, (w, s2r, s2t, ln_sig, _), _ = _projector_and_mixture()
    lnx = np.log(proj.X)
    rng = np.random.default_rng(5)
    u = rng.uniform(lnx[0], lnx[-1], 6000)
    v2 = np.zeros((2, 6000))
    e2 = np.full((2, 6000), 1e-8 * scale)
    args = (u, lnx[0], lnx[1] - lnx[0], w, s2r * scale, s2t * scale, ln_sig, v2, e2)
    got = mixture_star_sums(*args)
    per_star = mixture_ln_densities(*args[:6], v2, e2)
    if scale < 1e-100:
        assert np.min(per_star) > np.log(1e100)
    else:
        assert np.sum(per_star) > 10 * np.log(1e150) and np.max(per_star) < np.log(1e100)
    np.testing.assert_allclose(got, mixture_star_sums_numpy(*args), rtol=1e-12)
    np.testing.assert_allclose(got[0], np.sum(per_star), rtol=1e-12)


def test_large_errors_reach_the_gaussian_law():
    """With errors 30x the dispersion the mixture is Gaussian to O((sigma / e)^4): the two
    velocity laws agree to 1e-4 per star."""
    rng = np.random.default_rng(0)
    R = rng.uniform(0.1, 17.0, 200)
    v = rng.normal(0.0, 10.0, (2, 200))
    e = np.full(200, 10.0)
    s = StarSample(R, v[0], v[1], e, e, 17.0)
    theta = np.array([5.0, 1.6, 3000.0, 0.2])
    los = DiscreteLikelihood(s, NAMES, distance=4.6, star_counts=False)
    gau = DiscreteLikelihood(s, NAMES, distance=4.6, star_counts=False, velocity_law="gaussian")
    assert los(theta) == pytest.approx(gau(theta), abs=200 * 1e-4)


def test_bad_velocity_law_and_nodes_are_one_line_errors():
    s = StarSample(np.ones(3), np.zeros(3), np.zeros(3), np.ones(3), np.ones(3), 17.0)
    with pytest.raises(Exception, match="velocity_law"):
        DiscreteLikelihood(s, NAMES, velocity_law="lorentzian")
    with pytest.raises(Exception, match="line_of_sight_nodes"):
        DiscreteLikelihood(s, NAMES, line_of_sight_nodes=1)


@settings(max_examples=40, deadline=None)
@given(
    beta=st.floats(-2.0, 0.95),
    bh=st.floats(0.0, 2.0e4),
    gamma=st.floats(0.0, 1.99),
    log_a=st.floats(0.5, 2.5),
    v=st.floats(0.0, 1e3),
    err=st.floats(1e-4, 1.0),
    R=st.floats(0.0, 17.0),
)
def test_mixture_is_finite_and_normalised_at_the_edges(beta, bh, gamma, log_a, v, err, R):
    """Any beta < 1, black-hole mass, cusp, scale, speed and error: finite ln L, weights that
    sum to one and non-negative variances on the grid."""
    names = NAMES + ["gamma", "log_cusp_radius"]
    s = StarSample(
        np.array([R, 5.0]),
        np.array([v, 0.1]),
        np.array([-v, 0.0]),
        np.full(2, err),
        np.full(2, err),
        17.0,
    )
    like = DiscreteLikelihood(s, names, distance=4.6, min_radius=0.01)
    theta = np.array([5.0, log_a, bh, beta, gamma, 0.5])
    w, s2r, s2t, _, _ = like.line_of_sight_on_grid(theta)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-10)
    assert np.all(s2r >= 0) and np.all(s2t >= 0) and np.all(w >= 0)
    assert np.isfinite(like(theta))


def test_plummer_tracer_mixture_of_a_self_consistent_sphere_is_near_gaussian_far_out():
    """Far outside the core of an isotropic Plummer sphere the line of sight crosses nearly
    one dispersion: the mixture's excess kurtosis (3 Var(s^2) / E[s^2]^2) is small (0.07 < 0.1),
    and near the centre of a cluster with an IMBH it is large (25 > 5)."""
    X = np.geomspace(1e-3, 5.0, 24)
    proj = JeansProjector(X)
    iso = Anisotropy(0.0, 0.0, 1.0)
    for bh, j, lo, hi in ((0.0, -1, 0.0, 0.1), (0.02, 0, 5.0, np.inf)):
        w, s2r, _, _, _ = proj.line_of_sight(Plummer(), iso, None, np.array([1.0, bh, 0.0]))
        m1 = np.sum(w[j] * s2r[j])
        excess = 3.0 * (np.sum(w[j] * s2r[j] ** 2) - m1**2) / m1**2
        assert lo < excess < hi
