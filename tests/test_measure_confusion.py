"""Confusion classification and the two-star Cramér-Rao bound (docs/measure-scale.md,
tenth pass), each against an independent reference: the Poisson nearest-neighbour law
and a brute-force pair search on a random field, and a finite-difference Fisher matrix
of an analytically rendered pair."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import SynthPSF, true_epsf
from scipy.stats import norm

from mavispm.measure.stars.confusion import effective_fwhm, nearest_comparable, poisson_within
from mavispm.measure.stars.crlb import blend_crlb, crlb

SIDE = 2000.0


def random_field(n, seed):
    """Uniform positions on SIDE x SIDE px, magnitudes of a rising luminosity function."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, SIDE, (2, n))
    # N(<m) ~ 10^(0.3 m) between m = 18 and 26
    u = rng.uniform(0, 1, n)
    mag = np.log10(10 ** (0.3 * 18) + u * (10 ** (0.3 * 26) - 10 ** (0.3 * 18))) / 0.3
    return x, y, mag


@pytest.mark.parametrize("radius", [2.0, 4.0, 6.0])
def test_nearest_comparable_follows_the_poisson_law(radius):
    """On a uniform field the fraction of stars with a comparable neighbour within r is
    the mean over the stars of 1 - exp(-pi r^2 n(<m + 1)) (n: the other stars' density)."""
    x, y, mag = random_field(40000, 3)
    d, _ = nearest_comparable(x, y, mag, radius, dmag=1.0)
    # targets away from the edge (their neighbours are all in the field)
    inner = (x > radius) & (x < SIDE - radius) & (y > radius) & (y < SIDE - radius)
    ms = np.sort(mag)
    others = np.searchsorted(ms, mag[inner] + 1.0) - 1  # less the star itself
    expected = poisson_within(radius, others / SIDE**2)
    got = d[inner] < radius
    # binomial error of the mean (pairs correlate the two stars: x 2 to be safe)
    sigma = 2 * np.sqrt(np.sum(expected * (1 - expected))) / inner.sum()
    assert abs(got.mean() - expected.mean()) < 4 * sigma, (got.mean(), expected.mean(), sigma)
    # and by magnitude: the bright stars (few comparable neighbours) against the faint ones
    for lo, hi in ((18, 23), (23, 25), (25, 26)):
        sel = (mag[inner] >= lo) & (mag[inner] < hi)
        e = expected[sel]
        s = 2 * np.sqrt(np.sum(e * (1 - e))) / sel.sum() + 1e-4
        assert abs(got[sel].mean() - e.mean()) < 4 * s, (lo, got[sel].mean(), e.mean())


def test_nearest_comparable_and_neighbour_flux_against_brute_force():
    """Every star's nearest comparable neighbour and summed neighbour flux equal an
    all-pairs search."""
    x, y, mag = random_field(1500, 5)
    x, y = x / 10, y / 10  # 200 x 200 px: crowded
    flux = 10 ** (-0.4 * (mag - 25))
    d, f = nearest_comparable(x, y, mag, 6.0, dmag=1.0, flux_radius=3.0, flux=flux)
    dist = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    np.fill_diagonal(dist, np.inf)
    comparable = mag[None, :] < mag[:, None] + 1.0
    ref = np.where(comparable & (dist <= 6.0), dist, np.inf).min(axis=1)
    np.testing.assert_array_equal(d, ref)
    ref_f = np.where(dist <= 3.0, flux[None, :], 0.0).sum(axis=1)
    np.testing.assert_allclose(f, ref_f, rtol=1e-12)
    # strictly brighter (dmag = 0) is a subset
    d0, _ = nearest_comparable(x, y, mag, 6.0, dmag=0.0)
    ref0 = np.where((mag[None, :] < mag[:, None]) & (dist <= 6.0), dist, np.inf).min(axis=1)
    np.testing.assert_array_equal(d0, ref0)


def test_effective_fwhm_of_a_gaussian():
    """A pixel-integrated Gaussian ePSF: FWHM = 2.3548 sqrt(sigma^2 + 1/12) (1/12: the
    pixel's variance; the box blur is close to Gaussian for sigma >~ 1 px)."""
    sigma, os_ = 1.3, 4
    u = (np.arange(101) - 50) / os_
    # the ePSF sampled at oversampled offsets: the pixel-integrated profile
    prof = norm.cdf((u + 0.5) / sigma) - norm.cdf((u - 0.5) / sigma)
    img = prof[:, None] * prof[None, :]
    eq, fx, fy = effective_fwhm(img, os_)
    expected = 2 * np.sqrt(2 * np.log(2)) * np.sqrt(sigma**2 + 1 / 12)
    assert fx == pytest.approx(expected, rel=0.01)
    assert fy == pytest.approx(expected, rel=0.01)
    assert eq == pytest.approx(expected, rel=0.03)


@pytest.mark.parametrize(
    "sep,ratio,angle", [(0.4, 1.0, 0.0), (1.0, 0.4, 0.7), (2.2, 1.0, 2.0), (3.5, 0.25, 4.0)]
)
def test_blend_crlb_matches_brute_force_fisher(sep, ratio, angle):
    """The two-star bound equals the inverse of a finite-difference Fisher matrix of the
    pair rendered from the analytic PRF, on the same pixels."""
    psf = SynthPSF(1.1)
    shape = (300, 300)
    epsf = true_epsf(psf, shape)
    x1, y1, f1, sky, rn2 = 150.2, 149.7, 2e4, 300.0, 40.0
    x2, y2, f2 = x1 + sep * np.cos(angle), y1 + sep * np.sin(angle), ratio * f1
    bound = blend_crlb(epsf, [x1], [y1], [f1], [x2], [y2], [f2], sky, rn2, radius=5)[0]
    # the documented stamp: centred on the pair's midpoint, radius + ceil(sep / 2)
    half = 5 + int(np.ceil(sep / 2))
    cx, cy = int(np.rint((x1 + x2) / 2)), int(np.rint((y1 + y2) / 2))
    cols = np.arange(cx - half, cx + half + 1)[None, :]
    rows = np.arange(cy - half, cy + half + 1)[:, None]
    s1 = s2 = 1.1

    def model(p):
        return (
            p[2] * psf.prf(cols - p[0], rows - p[1], s1, s1)
            + p[5] * psf.prf(cols - p[3], rows - p[4], s2, s2)
            + p[6]
        )

    p0 = np.array([x1, y1, f1, x2, y2, f2, sky])
    steps = np.array([1e-4, 1e-4, 1.0, 1e-4, 1e-4, 1.0, 1e-3])
    jac = np.array(
        [(model(p0 + s * e) - model(p0 - s * e)) / (2 * s) for s, e in zip(steps, np.eye(7))]
    ).reshape(7, -1)
    var = model(p0).ravel() + rn2
    cov = np.linalg.inv((jac / var) @ jac.T)
    np.testing.assert_allclose(bound, np.sqrt(np.diag(cov)), rtol=5e-3)


def test_blend_crlb_limits():
    """Far apart, each star's bound is its isolated one; at one position it is singular."""
    psf = SynthPSF(1.1)
    epsf = true_epsf(psf, (300, 300))
    x1, y1, f, sky, rn2 = 150.2, 149.7, 2e4, 300.0, 40.0
    far = blend_crlb(epsf, [x1], [y1], [f], [x1 + 14.0], [y1], [f], sky, rn2, radius=5)[0]
    alone = crlb(epsf, [x1], [y1], [f], sky, rn2, radius=5)[0]
    # the pair's stamp is larger than one star's (more sky pixels): agree to a few %
    np.testing.assert_allclose(far[:2], alone[:2], rtol=0.03)
    same = blend_crlb(epsf, [x1], [y1], [f], [x1], [y1], [f], sky, rn2, radius=5)[0]
    assert np.all(np.isnan(same))
