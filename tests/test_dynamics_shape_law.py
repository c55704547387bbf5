"""The free-kurtosis velocity law (``velocity_law = "free_kurtosis"``,
:mod:`mavispm.dynamics.shape_law`) against quadrature, brute-force convolution, analytic
moments and maximum-likelihood fits of samples drawn from known laws."""

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import minimize

from mavispm.dynamics.fit import make_likelihood, parameter_space
from mavispm.dynamics.likelihood import DiscreteLikelihood, StarSample
from mavispm.dynamics.settings import DynamicsSettings
from mavispm.dynamics.shape_law import (
    kappa_at,
    shape_density,
    shape_star_sums,
    shape_star_sums_about,
    shape_star_sums_numpy,
)
from mavispm.dynamics.star_sums import stars_about

KAPPAS = (-1.9, -0.6, -0.1, 0.0, 0.2, 1.0, 2.9)


def _moments(s2, e2, kappa):
    f = lambda v, n: v**n * shape_density(v, s2, e2, kappa)  # noqa: E731
    lim = 40.0 * np.sqrt(s2 + e2)
    return [quad(f, -lim, lim, args=(n,), points=[0.0], limit=400)[0] for n in (0, 2, 4)]


@pytest.mark.parametrize("kappa", KAPPAS)
@pytest.mark.parametrize("e2", [0.0, 0.3, 4.0])
def test_density_normalised_with_the_model_variance_and_kurtosis(kappa, e2):
    """Quadrature: integral 1, variance s^2 + e^2, excess kurtosis kappa (s^2 / S^2)^2 (the
    error's Gaussian adds variance, no fourth cumulant)."""
    s2 = 1.7
    m0, m2, m4 = _moments(s2, e2, kappa)
    big = s2 + e2
    assert m0 == pytest.approx(1.0, abs=1e-9)
    assert m2 == pytest.approx(big, rel=1e-9)
    assert m4 / m2**2 - 3.0 == pytest.approx(kappa * (s2 / big) ** 2, abs=1e-8)


@pytest.mark.parametrize("kappa", [-1.2, -0.3, 0.4, 2.0])
def test_density_is_the_error_convolution_of_the_intrinsic_law(kappa):
    """The closed form with e > 0 equals the intrinsic law (e = 0) convolved numerically
    with the Gaussian error on a fine grid."""
    s2, e2 = 0.8, 0.5
    grid = np.linspace(-12.0, 12.0, 24001)
    dx = grid[1] - grid[0]
    intrinsic = shape_density(grid, s2, 0.0, kappa)
    v = np.array([-3.1, -1.0, 0.0, 0.4, 1.7, 2.9, 4.5])
    kernel = np.exp(-0.5 * (v[:, None] - grid[None, :]) ** 2 / e2) / np.sqrt(2 * np.pi * e2)
    brute = np.sum(kernel * intrinsic[None, :], axis=1) * dx
    np.testing.assert_allclose(shape_density(v, s2, e2, kappa), brute, rtol=1e-8)


def test_kappa_zero_is_the_gaussian_and_small_kappa_the_gauss_hermite_term():
    """kappa = 0: N(0, s^2 + e^2); small kappa: N(0, s^2)[1 + kappa He4(v/s) / 24] to
    relative O(|kappa|^(1/2)) (the displaced pair's next term is O(|kappa|^(3/2))), from
    both sides of 0: kappa passes continuously through the Gaussian law."""
    v = np.linspace(-4, 4, 17)
    np.testing.assert_allclose(
        shape_density(v, 2.0, 0.5, 0.0), np.exp(-v * v / 5.0) / np.sqrt(5.0 * np.pi), rtol=1e-14
    )
    gauss = np.exp(-0.5 * v * v) / np.sqrt(2 * np.pi)
    he4 = v**4 - 6 * v**2 + 3
    for kappa in (-1e-3, 1e-3, -1e-5, 1e-5):
        first = gauss * kappa * he4 / 24.0
        diff = shape_density(v, 1.0, 0.0, kappa) - gauss
        assert np.max(np.abs(diff - first)) < 2 * np.sqrt(abs(kappa)) * np.max(np.abs(first))


def _case(seed, n=400):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-6.0, 1.0, n)
    v2 = rng.exponential(1.0, (2, n)) * rng.uniform(0.1, 30.0, (2, n))
    e2 = rng.uniform(0.0, 2.0, (2, n))
    e2[:, :5] = 0.0
    ln_s2 = rng.normal(0.5, 0.5, (2, 40))
    ln_sig = rng.normal(0.0, 1.0, 40)
    return u, v2, e2, ln_s2, ln_sig


@pytest.mark.parametrize(
    "kpar",
    [(0.0, 0.0, 0.0, 1.0), (0.7, 0.7, 0.0, 1.0), (-1.8, 2.8, -4.0, -0.5), (-0.4, -1.9, -3, 0)],
)
def test_compiled_sums_equal_numpy_reference_and_direct_density(kpar):
    """shape_star_sums == its numpy reference == -sum(2 ln p + ln 2 pi) of shape_density
    at the interpolated dispersions, kappa linear in ln R between the anchors."""
    u, v2, e2, ln_s2, ln_sig = _case(3)
    kpar = np.array(kpar, dtype=float)
    ln_a, x0, step = 0.3, -7.0, 0.25
    got = shape_star_sums(u, ln_a, x0, step, ln_s2, ln_sig, v2, e2, kpar)
    ref = shape_star_sums_numpy(u, ln_a, x0, step, ln_s2, ln_sig, v2, e2, kpar)
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    # direct: linear interpolation weights would differ, so use the reference's dispersions
    from mavispm.dynamics.interpolation import cubic_weights, interpolate

    idx, w = cubic_weights(x0, step, ln_sig.size, u)
    s2 = np.exp(interpolate(ln_s2, idx, w))
    kappa = np.clip(
        kpar[0] + (kpar[1] - kpar[0]) * (u + ln_a - kpar[2]) / (kpar[3] - kpar[2]),
        min(kpar[:2]),
        max(kpar[:2]),
    )
    direct = -np.sum(2 * np.log(shape_density(np.sqrt(v2), s2, e2, kappa)) + np.log(2 * np.pi))
    assert got[0] == pytest.approx(direct, rel=1e-11)
    np.testing.assert_allclose(kappa_at(u + ln_a, *kpar), kappa, rtol=1e-14)


def test_compiled_sums_far_in_the_pairs_tails_and_nan_kappa():
    """Where ``|v| mu / W`` is far beyond ``cosh``'s range (the pair of a star with a tiny
    error at a strongly negative kappa) the compiled sums equal the log-space density
    ``ln W - 2 logaddexp(-(|v| - mu)^2 / 2W, -(|v| + mu)^2 / 2W) + 2 ln 2`` (no overflow);
    a NaN kappa gives a NaN sum, as any NaN parameter."""
    n = 64
    rng = np.random.default_rng(11)
    u = rng.uniform(-2.0, 0.5, n)
    ln_s2 = np.full((2, 40), np.log(4.0))
    ln_sig = np.zeros(40)
    v2 = rng.uniform(1.0, 16.0, (2, n))
    e2 = np.full((2, n), 1e-6)
    kappa = -1.99
    kpar = np.array([kappa, kappa, 0.0, 1.0])
    got, _ = shape_star_sums(u, 0.3, -7.0, 0.25, ln_s2, ln_sig, v2, e2, kpar)
    m = np.sqrt(-kappa / 2.0)
    mu, w = np.sqrt(m * 4.0), (1.0 - m) * 4.0 + 1e-6
    av = np.sqrt(v2)
    assert np.max(av * mu / w) > 300.0
    ref = np.sum(
        np.log(w)
        - 2 * np.logaddexp(-((av - mu) ** 2) / (2 * w), -((av + mu) ** 2) / (2 * w))
        + 2 * np.log(2.0)
    )
    assert np.isfinite(got)
    assert got == pytest.approx(ref, rel=1e-12)
    nan_par = np.array([np.nan, np.nan, 0.0, 1.0])
    assert np.isnan(shape_star_sums(u, 0.3, -7.0, 0.25, ln_s2, ln_sig, v2, e2, nan_par)[0])


def test_compiled_sums_about_a_moved_centre():
    """shape_star_sums_about == stars_about then shape_star_sums."""
    rng = np.random.default_rng(4)
    n = 300
    x, y = rng.uniform(-10, 10, (2, n))
    pmx, pmy = rng.normal(0, 1, (2, n))
    R = np.hypot(x, y)
    cx, sy = x / R, y / R
    er2, et2 = rng.uniform(0, 0.1, (2, n))
    _, _, _, ln_s2, ln_sig = _case(5)
    kpar = np.array([-0.5, 1.0, 0.0, 2.0])
    args = (x, y, pmx, pmy, cx, sy, er2, et2, 0.4, -0.3, 0.05, -0.02, 0.01)
    ln_a = 1.2
    got = shape_star_sums_about(*args, ln_a, -7.0, 0.25, ln_s2, ln_sig, kpar)
    ln_r, v2, e2 = stars_about(*args)
    ref = shape_star_sums_numpy(ln_r - ln_a, ln_a, -7.0, 0.25, ln_s2, ln_sig, v2, e2, kpar)
    np.testing.assert_allclose(got, ref, rtol=1e-12)


def _fit_kappa(v, e2):
    def nll(p):
        if not -1.99 < p[1] < 2.99:
            return 1e30
        return -np.sum(np.log(shape_density(v, np.exp(p[0]), e2, p[1])))

    r = minimize(nll, [np.log(np.var(v)), 0.0], method="Nelder-Mead", options={"xatol": 1e-7})
    h = 1e-3  # curvature of the profile in kappa for its error
    prof = [
        minimize(lambda q, k=k: nll([q[0], k]), [r.x[0]], method="Nelder-Mead").fun
        for k in (r.x[1] - h, r.x[1], r.x[1] + h)
    ]
    return r.x, 1.0 / np.sqrt((prof[0] - 2 * prof[1] + prof[2]) / h**2)


@pytest.mark.parametrize(
    "law, excess",
    [
        # uniform of variance 1 plus N(0, 1): excess kurtosis -1.2 / 2^2
        ("uniform+gauss", -0.3),
        # Laplace of variance 0.5 plus N(0, 1): 3 * 0.5^2 / 1.5^2
        ("laplace+gauss", 3 * 0.25 / 2.25),
    ],
)
def test_fit_recovers_the_kurtosis_of_a_law_outside_the_family(law, excess):
    """(sigma, kappa) fitted to 20,000 draws of a mildly non-Gaussian law outside the
    family, observed with heteroscedastic Gaussian errors: kappa within 3 sigma of the
    law's analytic excess kurtosis and sigma^2 within 3% of its variance (2)."""
    rng = np.random.default_rng(11)
    n = 20_000
    if law == "uniform+gauss":
        x = rng.uniform(-np.sqrt(3), np.sqrt(3), n) + rng.standard_normal(n)
    else:
        x = rng.laplace(0.0, 0.5, n) + rng.standard_normal(n)
    e = rng.uniform(0.3, 1.0, n)
    (ln_s2, kappa), err = _fit_kappa(x + e * rng.standard_normal(n), e * e)
    assert abs(kappa - excess) < 3 * err, (kappa, err)
    assert np.exp(ln_s2) == pytest.approx(2.0 if law == "uniform+gauss" else 1.5, rel=0.03)


def _stars(seed, n=300):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-8, 8, (2, n))
    R = np.hypot(x, y)
    e = rng.uniform(0.02, 0.06, n)
    return StarSample(R, rng.normal(0, 0.3, n), rng.normal(0, 0.3, n), e, e * 1.2, 12.0, x=x, y=y)


@pytest.mark.parametrize("moving", [False, True])
def test_likelihood_is_gaussian_law_plus_shape_terms(moving):
    """DiscreteLikelihood(velocity_law="free_kurtosis") with kappa_inner/outer == the Gaussian
    law's ln L minus its Gaussian kinematic terms plus sum ln shape_density at the model
    dispersions (dispersion_at), with kappa at each star's radius about the centre."""
    stars = _stars(1)
    base = ["log_mass", "log_scale_radius", "bh_mass", "beta"]
    theta = [5.2, 1.9, 1500.0, 0.1]
    if moving:
        base += ["x0", "y0", "pm_x0", "pm_y0"]
        theta += [0.3, -0.2, 0.01, -0.02]
    kw = dict(tracer="plummer", distance=4.6, scale_radius_range=(10.0, 1000.0), grid_size=32)
    gauss = DiscreteLikelihood(stars, base, velocity_law="gaussian", **kw)
    shape = DiscreteLikelihood(
        stars, [*base, "kappa_inner", "kappa_outer"], velocity_law="free_kurtosis", **kw
    )
    k_in, k_out = -0.7, 1.3
    got = shape(np.array([*theta, k_in, k_out]))
    ln_r, v2, e2 = gauss._stars_about_numpy(np.array(theta))
    R = np.exp(ln_r)
    s = gauss.dispersion_at(np.array(theta), R)
    lo, hi = np.log(np.percentile(stars.R, [10, 90]))
    kappa = k_in + (k_out - k_in) * np.clip((ln_r - lo) / (hi - lo), 0, 1)
    gauss_kin = -0.5 * np.sum(v2 / (s**2 + e2) + np.log(s**2 + e2)) - stars.R.size * np.log(
        2 * np.pi
    )
    shape_kin = np.sum(np.log(shape_density(np.sqrt(v2), s**2, e2, kappa)))
    assert got == pytest.approx(gauss(np.array(theta)) - gauss_kin + shape_kin, rel=1e-6, abs=1e-4)
    # one global kappa = 0 is the Gaussian law
    one = DiscreteLikelihood(stars, [*base, "kappa"], velocity_law="free_kurtosis", **kw)
    assert one(np.array([*theta, 0.0])) == pytest.approx(gauss(np.array(theta)), rel=1e-12)
    assert one(np.array([*theta, 3.0])) == -np.inf


def test_settings_put_kappa_in_the_parameter_space():
    """kappa_profile "constant": one kappa, "radial": kappa_inner and kappa_outer, both
    uniform on kappa_range; no kappa for the other laws; bad ranges rejected."""
    s = DynamicsSettings(velocity_law="free_kurtosis", kappa_range=(-1.0, 2.0))
    space = parameter_space(s, 4.6, "imbh")
    p = space.params[space.index("kappa")]
    assert (p.prior, p.lo, p.hi) == ("uniform", -1.0, 2.0)
    radial = DynamicsSettings(velocity_law="free_kurtosis", kappa_profile="radial")
    names = parameter_space(radial, 4.6, "none").names
    assert "kappa_inner" in names and "kappa_outer" in names and "kappa" not in names
    # the stage's default law (since 2026-12-04) fits one kappa; the other laws none
    assert [
        n
        for n in parameter_space(DynamicsSettings(velocity_law="free_kurtosis"), 4.6).names
        if "kappa" in n
    ] == ["kappa"]
    for law in ("line_of_sight", "gaussian"):
        names = parameter_space(DynamicsSettings(velocity_law=law), 4.6).names
        assert not any(n.startswith("kappa") for n in names)
    stars = _stars(2)
    like = make_likelihood(stars, space, s, 4.6)
    assert like.velocity_law == "free_kurtosis"
    for bad in [
        dict(kappa_range=(-2.0, 1.0)),
        dict(kappa_range=(0.5, 0.2)),
        dict(kappa_profile="x"),
    ]:
        with pytest.raises(ValueError):
            DynamicsSettings(velocity_law="free_kurtosis", **bad)
