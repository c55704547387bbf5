"""Jeans projection against analytic and independent high-precision integrals."""

import functools

import astropy.units as u
import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.jeans import JeansProjector, projected_dispersion
from mavispm.dynamics.tracers import Cusped, Dehnen, King62, Plummer

RADII = np.logspace(-4, 3, 22)  # R = 1e-4 a ... 1e3 a


def test_plummer_projected_dispersion_matches_analytic():
    """Isotropic Plummer: sigma_p^2 = 3 pi G M / (64 sqrt(R^2 + a^2)) to 1e-4."""
    mom = JeansProjector(RADII).moments(Plummer(), 0.0)
    analytic = 3 * np.pi / (64 * np.sqrt(1 + RADII**2))
    np.testing.assert_allclose(mom.radial_cluster, analytic, rtol=1e-4)
    np.testing.assert_allclose(mom.tangential_cluster, analytic, rtol=1e-4)


def _plummer_point_mass_jeans(r):
    """nu sigma_r^2 / (G M_bh) for a Plummer tracer, beta = 0, in closed form.

    int_r^inf nu / r'^2 dr' = 3 / (4 pi) (1 - u)^3 (u + 3) / (3 u), u = r / sqrt(1 + r^2),
    with 1 - u = 1 / (s (s + r)), s = sqrt(1 + r^2): free of cancellation.
    """
    s = mp.sqrt(1 + r * r)
    one_minus_u = 1 / (s * (s + r))
    u_ = r / s
    return 3 / (4 * mp.pi) * one_minus_u**3 * (u_ + 3) / (3 * u_)


def test_closed_form_point_mass_jeans_integral_matches_quad():
    nu = Plummer().density
    for r in (1e-4, 0.5, 30.0):
        ref = integrate.quad(
            lambda s: nu(s) / s**2, r, np.inf, epsabs=0, epsrel=1e-12, points=None
        )[0]
        assert float(_plummer_point_mass_jeans(mp.mpf(r))) == pytest.approx(ref, rel=1e-9)


def _point_mass_reference(X):
    """Projected point-mass term (Plummer, beta = 0) by 25-digit mpmath quadrature."""
    mp.mp.dps = 25
    X = mp.mpf(X)
    tmax = mp.acosh(mp.mpf(10) ** 4 / X)  # the same 1e4 a truncation as the projector
    pts = [mp.mpf(0)] + [tmax * k / 16 for k in range(1, 17)]
    num = 2 * mp.quad(lambda t: _plummer_point_mass_jeans(X * mp.cosh(t)) * X * mp.cosh(t), pts)
    return float(num / (1 / mp.pi * (1 + X * X) ** -2))


@pytest.mark.parametrize("X", [1e-4, 3e-3, 0.1, 1.0, 7.0, 100.0, 1e3])
def test_point_mass_term_matches_mpmath(X):
    mom = JeansProjector([X]).moments(Plummer(), 0.0)
    assert mom.radial_bh[0] == pytest.approx(_point_mass_reference(X), rel=1e-4)
    assert mom.tangential_bh[0] == pytest.approx(mom.radial_bh[0], rel=1e-12)


def _jeans_quad(tr, beta, r, bh):
    """nu sigma_r^2 at r by adaptive quad (truncated at 1e4 plus the exact tail)."""

    def f(s):
        return s ** (2 * beta - 2) * tr.density(s) * (1.0 if bh else tr.enclosed(s))

    val = sum(
        integrate.quad(f, lo, hi, epsabs=0, epsrel=1e-11, limit=200)[0]
        for lo, hi in ((r, 10 * r), (10 * r, 1e4), (1e4, np.inf))
    )
    return r ** (-2 * beta) * val


def _project_quad(func, R, kernel):
    """2 int_R^1e4 func(r) kernel r dr / sqrt(r^2 - R^2) via r = R cosh t."""
    tmax = np.arccosh(1e4 / R)
    pts = np.linspace(0, tmax, 12)

    def g(t):
        return func(R * np.cosh(t)) * R * np.cosh(t) * kernel(t)

    return 2 * sum(integrate.quad(g, a, b, epsrel=1e-10)[0] for a, b in zip(pts[:-1], pts[1:]))


@pytest.mark.slow  # brute-force nested quad: ~3 min per beta (passes)
@pytest.mark.parametrize("beta", [-0.5, 0.4])
def test_anisotropic_dehnen_matches_scipy_quad(beta):
    """Cluster + point-mass terms for a cusped Dehnen tracer and beta != 0 vs nested quad."""
    tr = Dehnen(gamma=1.5)
    X = np.array([0.01, 0.3, 5.0])
    mom = JeansProjector(X).moments(tr, beta)
    one = np.ones_like
    for j, R in enumerate(X):
        sig = _project_quad(tr.density, R, one)
        for bh, rad, tan in (
            (False, mom.radial_cluster, mom.tangential_cluster),
            (True, mom.radial_bh, mom.tangential_bh),
        ):
            p = functools.partial(_jeans_quad, tr, beta, bh=bh)
            p_vec = np.vectorize(p)
            t_ref = (1 - beta) * _project_quad(p_vec, R, one) / sig
            r_ref = t_ref + beta * _project_quad(p_vec, R, lambda t: 1 / np.cosh(t) ** 2) / sig
            assert rad[j] == pytest.approx(r_ref, rel=1e-4)
            assert tan[j] == pytest.approx(t_ref, rel=1e-4)


def test_surface_density_and_projected_mass_of_tracers():
    X = np.logspace(-3, 1.3, 12)
    for tr in (Plummer(), King62(1.5)):
        mom = JeansProjector(X).moments(tr, 0.0)
        np.testing.assert_allclose(mom.surface_density, tr.surface_density(X), rtol=1e-4)
        np.testing.assert_allclose(mom.projected_enclosed, tr.projected_enclosed(X), rtol=1e-4)
    tr = Dehnen(1.55)
    mom = JeansProjector(X).moments(tr, 0.0)
    ref = [_project_quad(tr.density, R, np.ones_like) for R in X]
    np.testing.assert_allclose(mom.surface_density, ref, rtol=1e-4)


def test_dehnen_enclosed_mass_is_integral_of_density():
    tr = Dehnen(1.2)
    for x in (0.01, 1.0, 30.0):
        m = integrate.quad(lambda s: 4 * np.pi * s**2 * tr.density(s), 0, x, epsrel=1e-12)[0]
        assert tr.enclosed(x) == pytest.approx(m, rel=1e-6)


def test_physical_units_and_point_mass_dominates_centre():
    """Keplerian rise in a gamma = 1.5 cusp: projected sigma^2 ~ G M_bh / R near the centre."""
    R = [0.001, 0.002] * u.pc
    s_r, _ = projected_dispersion(
        R, 1e5 * u.Msun, 2 * u.pc, bh_mass=1e4 * u.Msun, tracer=Dehnen(1.5)
    )
    ratio = (s_r[0] / s_r[1]).to_value(u.one) ** 2
    assert ratio == pytest.approx(2.0, rel=0.05)
    s_ang, _ = projected_dispersion(
        [1.0] * u.arcsec, 1e5 * u.Msun, 60 * u.arcsec, distance=5 * u.kpc
    )
    assert s_ang.unit == u.mas / u.yr


def test_cubic_interpolation_exact_for_cubics():
    grid = np.linspace(-2, 3, 11)
    vals = grid**3 - 2 * grid
    q = np.array([-1.93, 0.17, 2.71])
    idx, w = cubic_weights(grid[0], grid[1] - grid[0], grid.size, q)
    np.testing.assert_allclose(interpolate(vals, idx, w), q**3 - 2 * q, rtol=1e-12)


def test_bad_anisotropy_and_radii_raise():
    with pytest.raises(ValueError, match="beta"):
        JeansProjector([1.0]).moments(Plummer(), 1.0)
    with pytest.raises(ValueError, match="radii"):
        JeansProjector([0.0])


def _cusp_shape(base, gamma, xc):
    """Unnormalised cusped density, written independently of the tabulated code."""
    return lambda x: base.density(x) * (1 + (xc / x) ** 2) ** (gamma / 2)


def _quad_mass(shape, x, xc):
    """int_0^x 4 pi r^2 shape dr by adaptive quad in ln r (from ln r = -40)."""
    pts = [p for p in (np.log(xc) - 2, np.log(xc), np.log(xc) + 2, 0.0) if -40 < p < np.log(x)]
    return integrate.quad(
        lambda lr: 4 * np.pi * np.exp(3 * lr) * shape(np.exp(lr)),
        -40,
        np.log(x),
        points=pts or None,
        limit=400,
        epsabs=0,
        epsrel=1e-12,
    )[0]


@pytest.mark.parametrize("base", [Plummer(), King62(1.33)])
@pytest.mark.parametrize("gamma, xc", [(1.55, 0.5), (2.3, 1e-3), (0.7, 3.0)])
def test_cusped_profile_mass_matches_quad(base, gamma, xc):
    """Cusped King/Plummer: tabulated enclosed mass and density match scipy quad of the
    same (independently written) profile to 1e-4, from 1e-5 to 15 scale radii."""
    shape = _cusp_shape(base, gamma, xc)
    if isinstance(base, King62):
        total = _quad_mass(shape, base.tidal_radius, xc)
    else:
        total = _quad_mass(shape, 1e5, xc) + 1 - base.enclosed(1e5)
    x = np.array([1e-5, 1e-3, 0.02, 0.3, 1.0, 4.0, 15.0])
    ref = np.array([_quad_mass(shape, xi, xc) for xi in x]) / total
    tr = Cusped(base, gamma, xc)
    np.testing.assert_allclose(tr.enclosed(x), ref, rtol=1e-4)
    np.testing.assert_allclose(tr.density(x), shape(x) / total, rtol=1e-4)


@pytest.mark.parametrize("base", [Plummer(), King62(1.33)])
def test_cusped_profile_limits(base):
    """Unit total mass, gamma = 0 gives back the base profile, nu ~ r^-gamma inside the cusp,
    and scalars and 2-D arrays keep their shape."""
    cusped = Cusped(base, 1.55, 0.5)
    assert cusped.enclosed(1e6) == pytest.approx(1.0, rel=1e-6)
    x = np.array([0.05, 0.3, 2.0])
    np.testing.assert_allclose(Cusped(base, 0.0, 0.5).density(x), base.density(x), rtol=1e-6)
    # (the King62 base mass is itself tabulated: linear in ln m, ~2e-6)
    np.testing.assert_allclose(Cusped(base, 0.0, 0.5).enclosed(x), base.enclosed(x), rtol=1e-5)
    slope = np.log(cusped.density(1e-4) / cusped.density(1e-3)) / np.log(0.1)
    assert slope == pytest.approx(-1.55, abs=1e-3)
    assert np.shape(cusped.enclosed(0.3)) == ()
    assert cusped.density(np.ones((2, 3))).shape == (2, 3)


def test_family_evaluators_match_direct_profiles():
    """The projector's cached per-family evaluators equal the profiles' own methods."""
    pts, mpts = np.logspace(-6, 3.5, 50), np.logspace(-5, 3, 30)
    for proto, members in (
        (Dehnen(1.0), [Dehnen(0.0), Dehnen(1.55), Dehnen(2.2)]),
        (
            Cusped(King62(1.33), 1.0, 0.1),
            [Cusped(King62(1.33), 0.3, 0.02), Cusped(King62(1.33), 2.0, 2.0)],
        ),
    ):
        ev = proto.at_points(pts, mpts)
        for tr in members:
            nu, m = ev(tr)
            np.testing.assert_allclose(nu, tr.density(pts), rtol=1e-12)
            np.testing.assert_allclose(m, tr.enclosed(mpts), rtol=1e-12)


def test_cusped_king_surface_density_matches_quad():
    """Projector with a cusped King62 tracer: surface density vs quad projection of the profile."""
    tr = Cusped(King62(1.33), 1.55, 0.4)
    X = np.array([0.005, 0.1, 0.7, 5.0])
    mom = JeansProjector(X).moments(tr, 0.0)
    xt = King62(1.33).tidal_radius

    def dens(r):
        return np.where(r < xt, tr.density(np.minimum(r, xt)), 0.0)

    ref = [_project_quad(dens, R, np.ones_like) for R in X]
    np.testing.assert_allclose(mom.surface_density, ref, rtol=1e-4)


@pytest.mark.parametrize("base", [Plummer(), King62(1.33)])
def test_radius_enclosing_inverts_enclosed_mass(base):
    q = np.array([1e-12, 1e-6, 1e-3, 0.05, 0.5, 0.9])
    x = np.array([base.radius_enclosing(qi) for qi in q])
    np.testing.assert_allclose(base.enclosed(x), q, rtol=1e-4)
    with pytest.raises(ValueError, match="mass fraction"):
        base.radius_enclosing(1.0)


def _nested_quad_moments(nu, mass, beta_of_r, ln_g, R):
    """Independent reference: Sigma, Sigma sigma_R^2, Sigma sigma_T^2 at R by nested scipy quad.

    ``nu sigma_r^2(r) = exp(-ln_g(r)) int_r^inf exp(ln_g(s)) nu(s) mass(s) / s^2 ds``, then
    projected with ``r = R cosh t`` (the code under test is not used).
    """

    def p(r):
        val = integrate.quad(
            lambda s: np.exp(ln_g(s) - ln_g(r)) * nu(s) * mass(s) / s**2,
            r,
            np.inf,
            epsabs=0,
            epsrel=1e-9,
            limit=200,
        )[0]
        return val

    def proj(kernel):
        return (
            2
            * integrate.quad(
                lambda t: kernel(R * np.cosh(t), R) * R * np.cosh(t),
                0,
                np.arccosh(1e4 / R),
                epsabs=0,
                epsrel=1e-8,
                limit=200,
            )[0]
        )

    sig = proj(lambda r, R_: nu(r))
    rad = proj(lambda r, R_: (1 - beta_of_r(r) + beta_of_r(r) * R_**2 / r**2) * p(r))
    tan = proj(lambda r, R_: (1 - beta_of_r(r)) * p(r))
    return sig, rad / sig, tan / sig


@pytest.mark.parametrize("r_a", [0.5, 3.0])
def test_osipkov_merritt_projection_matches_nested_quad(r_a):
    """Osipkov-Merritt beta(r) = r^2/(r^2+r_a^2): cluster, point-mass and dark terms vs quad."""
    from mavispm.dynamics.anisotropy import osipkov_merritt

    tr = Plummer()
    b = 0.2
    X = np.array([0.05, 1.0])
    mom = JeansProjector(X).moments(tr, osipkov_merritt(r_a), dark_radius=b)
    ln_g = lambda r: np.log(r * r + r_a * r_a)  # noqa: E731 - integrating factor by hand
    beta = lambda r: r * r / (r * r + r_a * r_a)  # noqa: E731
    masses = {
        "cluster": lambda s: s**3 / (1 + s * s) ** 1.5,
        "bh": lambda s: 1.0,
        "dark": lambda s: (s / b) ** 3 / (1 + (s / b) ** 2) ** 1.5,
    }
    for j, R in enumerate(X):
        for key, mass in masses.items():
            _, rad, tan = _nested_quad_moments(tr.density, mass, beta, ln_g, R)
            assert getattr(mom, f"radial_{key}")[j] == pytest.approx(rad, rel=2e-4), key
            assert getattr(mom, f"tangential_{key}")[j] == pytest.approx(tan, rel=2e-4), key


def test_general_anisotropy_projection_matches_nested_quad():
    """beta(r) = b0 + (binf - b0) r^2/(r^2 + r_a^2) (tangential centre, radial outside),
    Plummer tracer with a point mass: vs nested quad with g(r) integrated by hand."""
    from mavispm.dynamics.anisotropy import Anisotropy

    b0, binf, r_a = -0.3, 0.6, 0.8
    tr = Plummer()
    X = np.array([0.05, 1.0])
    mom = JeansProjector(X).moments(tr, Anisotropy(b0, binf, r_a))
    beta = lambda r: b0 + (binf - b0) * r * r / (r * r + r_a * r_a)  # noqa: E731
    # ln g = int 2 beta(s) / s ds, integrated by hand: 2 b0 ln r + (binf - b0) ln(r^2 + r_a^2)
    ln_g = lambda r: 2 * b0 * np.log(r) + (binf - b0) * np.log(r * r + r_a * r_a)  # noqa: E731
    for j, R in enumerate(X):
        _, rad, tan = _nested_quad_moments(tr.density, lambda s: 1.0, beta, ln_g, R)
        assert mom.radial_bh[j] == pytest.approx(rad, rel=3e-4)
        assert mom.tangential_bh[j] == pytest.approx(tan, rel=3e-4)


def test_dark_component_constant_beta_matches_nested_quad():
    """Extended dark Plummer sphere in a cusped Dehnen tracer, beta = 0.3, vs nested quad."""
    tr = Dehnen(gamma=1.2)
    b, beta0 = 0.05, 0.3
    X = np.array([0.02, 0.4])
    mom = JeansProjector(X).moments(tr, beta0, dark_radius=b)
    mass = lambda s: (s / b) ** 3 / (1 + (s / b) ** 2) ** 1.5  # noqa: E731
    for j, R in enumerate(X):
        _, rad, tan = _nested_quad_moments(
            tr.density, mass, lambda r: beta0, lambda r: 2 * beta0 * np.log(r), R
        )
        assert mom.radial_dark[j] == pytest.approx(rad, rel=2e-4)
        assert mom.tangential_dark[j] == pytest.approx(tan, rel=2e-4)


def test_large_anisotropy_radius_is_isotropic_and_tiny_dark_radius_is_point_mass():
    """Limits: r_a -> inf gives beta = 0; a dark sphere far inside R acts as the point mass."""
    from mavispm.dynamics.anisotropy import osipkov_merritt

    X = np.array([0.3, 1.0, 3.0])
    proj = JeansProjector(X)
    iso = proj.moments(Plummer(), 0.0)
    om = proj.moments(Plummer(), osipkov_merritt(1e3), dark_radius=1e-4)
    np.testing.assert_allclose(om.radial_cluster, iso.radial_cluster, rtol=1e-5)
    np.testing.assert_allclose(om.tangential_cluster, iso.tangential_cluster, rtol=1e-5)
    np.testing.assert_allclose(om.radial_dark, iso.radial_bh, rtol=1e-4)


def _tracer_cases():
    return [
        Plummer(),
        King62(1.33),
        Dehnen(1.3),
        Cusped(Plummer(), 1.55, 0.05),
        Cusped(King62(1.33), 0.8, 2.0),
    ]


@pytest.mark.parametrize("tracer", _tracer_cases(), ids=lambda t: type(t).__name__)
def test_compiled_weighted_dispersions_equal_numpy_moments(tracer):
    """The likelihood's compiled path (components weighted before the projection) equals
    the weighted numpy moments for every anisotropy form, with and without a dark sphere."""
    from mavispm.dynamics.anisotropy import Anisotropy, osipkov_merritt

    X = np.exp(np.linspace(np.log(1e-5), np.log(3.0), 40))
    proj = JeansProjector(X, n_panels=16)
    w = np.array([2.0e-3, 7.0e-2, 3.0e-2])
    for aniso in (0.0, -0.4, 0.5, osipkov_merritt(0.7), Anisotropy(-0.3, 0.6, 2.0)):
        for b in (None, 0.05):
            mom = proj.moments(tracer, aniso, dark_radius=b)
            dark = w[2] if b is not None else 0.0
            rad = w[0] * mom.radial_cluster + w[1] * mom.radial_bh + dark * mom.radial_dark
            tan = w[0] * mom.tangential_cluster + w[1] * mom.tangential_bh
            tan = tan + dark * mom.tangential_dark
            ln_s2, ln_sig, ln_proj = proj.log_dispersions(tracer, aniso, b, w)
            np.testing.assert_allclose(ln_s2[0], np.log(rad), rtol=0, atol=1e-12)
            np.testing.assert_allclose(ln_s2[1], np.log(tan), rtol=0, atol=1e-12)
            np.testing.assert_allclose(ln_sig, np.log(mom.surface_density), rtol=0, atol=1e-12)
            np.testing.assert_allclose(ln_proj, np.log(mom.projected_enclosed), atol=1e-12)


def test_compiled_weighted_dispersions_match_nested_quad():
    """Compiled path against the independent nested quad: Plummer tracer, general anisotropy,
    cluster + point mass + dark sphere weighted together."""
    from mavispm.dynamics.anisotropy import Anisotropy

    b0, binf, r_a, b = -0.2, 0.7, 1.5, 0.1
    w = np.array([1.0, 0.03, 0.05])
    X = np.array([0.04, 0.9])
    ln_s2, ln_sig, _ = JeansProjector(X).log_dispersions(Plummer(), Anisotropy(b0, binf, r_a), b, w)
    beta = lambda r: b0 + (binf - b0) * r * r / (r * r + r_a * r_a)  # noqa: E731
    ln_g = lambda r: 2 * b0 * np.log(r) + (binf - b0) * np.log(r * r + r_a * r_a)  # noqa: E731

    def mass(s):  # w_cl m_Plummer + w_bh + w_dark m_Plummer(s / b), written out by hand
        return w[0] * s**3 / (1 + s * s) ** 1.5 + w[1] + w[2] / (1 + (b / s) ** 2) ** 1.5

    for j, R in enumerate(X):
        sig, rad, tan = _nested_quad_moments(Plummer().density, mass, beta, ln_g, R)
        assert np.exp(ln_sig[j]) == pytest.approx(sig, rel=1e-5)
        assert np.exp(ln_s2[0, j]) == pytest.approx(rad, rel=3e-4)
        assert np.exp(ln_s2[1, j]) == pytest.approx(tan, rel=3e-4)


def test_compiled_plummer_dispersion_matches_closed_form():
    """Isotropic self-consistent Plummer sphere through the compiled path:
    sigma_p^2 = 3 pi / (64 sqrt(1 + X^2)) (G = M = a = 1) in both components."""
    ln_s2, ln_sig, ln_proj = JeansProjector(RADII).log_dispersions(
        Plummer(), 0.0, None, np.array([1.0, 0.0, 0.0])
    )
    closed = 3 * np.pi / (64 * np.sqrt(1 + RADII**2))
    np.testing.assert_allclose(np.exp(ln_s2), np.stack([closed, closed]), rtol=1e-4)
    np.testing.assert_allclose(np.exp(ln_sig), Plummer().surface_density(RADII), rtol=1e-4)
    np.testing.assert_allclose(np.exp(ln_proj), Plummer().projected_enclosed(RADII), rtol=1e-4)


@pytest.mark.parametrize("base", [Plummer(), King62(1.33)], ids=["plummer", "king62"])
def test_compiled_cusp_tables_equal_numpy_reference(base):
    """CuspedAtPoints: the compiled evaluation (series outside and deep inside the cusp)
    equals the numpy reference, across slopes and cusp radii that move the series bounds
    over the whole grid."""
    pts = np.logspace(-7, 4, 300)
    ev = Cusped(base, 1.0, 0.1).at_points(pts, pts)
    for gamma in (0.0, 0.4, 1.55, 2.0, 2.49):
        for xc in (1e-6, 1e-3, 0.05, 1.0, 8.0):
            tr = Cusped(base, gamma, xc)
            for got, ref in zip(ev(tr), ev.call_numpy(tr)):
                np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("model", ["imbh", "imbh_dark"])
def test_full_model_dispersions_match_independent_forward_model(model):
    """Projected dispersions of the likelihood (cusped Plummer tracer, cluster mass following
    it, point mass, extended dark Plummer component, constant beta, distance) against the
    SBC's forward model, written independently as dense trapezoid sums on fine log grids
    (``sbc_helpers``), for parameter vectors drawn from the prior: agree to 1e-4."""
    from sbc_helpers import draw_prior, sbc_space

    space, s = sbc_space(model)
    R = np.geomspace(0.02, 20.0, 7)
    for seed in range(3):
        rng = np.random.default_rng([seed, 5])
        p = draw_prior(space, rng)
        got, ref = _dispersions_against_forward_model(space, s, p, rng, R, 50)
        np.testing.assert_allclose(got, ref, rtol=1e-4)


def _dispersions_against_forward_model(space, s, p, rng, R, n_stars):
    """Projected dispersions [mas/yr] at ``R`` [arcsec] for parameters ``p``: the
    likelihood's (on a sample of ``n_stars`` drawn with ``rng``) and the SBC forward
    model's (``sbc_helpers``, written apart from the package)."""
    from sbc_helpers import SBC_DISTANCE, draw_sample, projected_dispersions

    from mavispm.dynamics.fit import make_likelihood

    like = make_likelihood(draw_sample(p, n_stars, rng), space, s, SBC_DISTANCE)
    theta = np.array([p[n] for n in space.names])
    ref = np.sqrt(np.array(projected_dispersions(p, R / 10.0 ** p["log_scale_radius"])))
    return like.dispersion_at(theta, R), ref


#: General anisotropy profiles (beta_0, beta_inf, log10 r_a [arcsec]) whose anisotropy radius
#: lies in or near the 15" field, where the prior's draws mostly put it beyond (r_a up to
#: 1000"): strongly radial outside, tangential outside, Osipkov-Merritt-like.
GENERAL_PROFILES = [(-0.4, 0.9, 0.5), (0.45, -0.5, 1.0), (0.0, 0.95, 0.0), (-0.5, 0.6, 1.5)]


@pytest.mark.parametrize("model", ["imbh", "imbh_dark"])
def test_general_anisotropy_dispersions_match_independent_forward_model(model):
    """The default general profile beta(r) = beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2):
    projected dispersions of the likelihood against the SBC forward model (its integrating
    factor a trapezoid sum of 2 beta over ln r, beta(r) projected depth by depth), for prior
    draws and for profiles turning inside the field: agree to 1e-4 (measured 3e-5)."""
    from sbc_helpers import draw_prior, sbc_space

    space, s = sbc_space(model, anisotropy="general")
    R = np.geomspace(0.02, 20.0, 7)
    draws = [None, None] + GENERAL_PROFILES
    for seed, profile in enumerate(draws):
        rng = np.random.default_rng([seed, 6])
        p = draw_prior(space, rng)
        if profile is not None:
            p.update(zip(("beta_0", "beta_inf", "log_anisotropy_radius"), profile))
        got, ref = _dispersions_against_forward_model(space, s, p, rng, R, 50)
        np.testing.assert_allclose(got, ref, rtol=1e-4)


def test_full_model_ln_likelihood_matches_independent_sum():
    """ln L of the full model with the Gaussian velocity law (kinematic and star-count parts,
    centre and systemic motion off zero, extended dark component) against the SBC forward model's own Gaussian sum and
    a midpoint sum of the surface density over the field disc: agree to 0.01 in ln L for
    300 stars."""
    from sbc_helpers import (
        SBC_DISTANCE,
        draw_prior,
        draw_sample,
        independent_ln_likelihood,
        sbc_space,
    )

    from mavispm.dynamics.fit import make_likelihood

    space, s = sbc_space("imbh_dark", "gaussian")
    for seed in range(2):
        rng = np.random.default_rng([seed, 99])
        p = draw_prior(space, rng)
        stars = draw_sample(p, 300, rng)
        theta = np.array([p[n] for n in space.names])
        full = make_likelihood(stars, space, s, SBC_DISTANCE)(theta)
        kin = make_likelihood(stars, space, s, SBC_DISTANCE, star_counts=False)(theta)
        ref_kin, ref_counts = independent_ln_likelihood(p, stars)
        assert kin == pytest.approx(ref_kin, abs=0.01)
        assert full - kin == pytest.approx(ref_counts, abs=0.01)


@settings(max_examples=25, deadline=None)
@given(
    beta_0=st.floats(-0.5, 0.5),
    beta_inf=st.floats(-0.5, 0.95),
    log_r_a=st.floats(0.0, 3.0),
    seed=st.integers(0, 10_000),
)
def test_general_anisotropy_dispersions_across_the_prior_box(beta_0, beta_inf, log_r_a, seed):
    """Anywhere in the general profile's prior box, edges included (r_a from 1" to 1000",
    beta_inf to 0.95), every other parameter a prior draw (``imbh_dark``): the likelihood's
    projected dispersions from 0.01" to 20" are finite and within 2e-4 of the SBC forward
    model (measured up to 8e-5, at the corner beta_0 = -0.5, beta_inf = 0.95, r_a = 1")."""
    from sbc_helpers import draw_prior, sbc_space

    space, s = sbc_space("imbh_dark", anisotropy="general")
    rng = np.random.default_rng([seed, 8])
    p = draw_prior(space, rng)
    p.update(beta_0=beta_0, beta_inf=beta_inf, log_anisotropy_radius=log_r_a)
    got, ref = _dispersions_against_forward_model(space, s, p, rng, np.geomspace(0.01, 20.0, 6), 20)
    assert np.all(np.isfinite(got)) and np.all(got > 0)
    np.testing.assert_allclose(got, ref, rtol=2e-4)
