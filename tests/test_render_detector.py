"""Photometry and detector: zero points, sky, noise statistics, saturation, stacks."""

import astropy.units as u
import numpy as np
import pytest

from mavispm.simulate.render.detector import DetectorSettings, expose_stack
from mavispm.simulate.render.zero_point import (
    PhotometrySettings,
    collecting_area,
    sky_electrons_per_pixel,
    star_electrons,
)


def test_star_electrons_follow_the_photometric_chain():
    p = PhotometrySettings()
    area = np.pi / 4 * (820.0**2 - 111.6**2)  # cm^2
    expected = 1000.0 * 880.0 * area * 0.45 * 0.89 * 30.0 * 10 ** (-0.4 * (20.0 + 0.129))
    got = star_electrons([20.0], p, 30 * u.s)
    assert got.unit == u.electron
    assert got.value[0] == pytest.approx(expected, rel=1e-12)
    assert collecting_area(p).to_value(u.m**2) == pytest.approx(51.83, rel=1e-3)
    # 5 magnitudes = factor 100; airmass 2 adds one more extinction
    assert star_electrons([15.0], p, 30 * u.s).value[0] / expected == pytest.approx(100.0)
    p2 = PhotometrySettings(airmass=2.0)
    ratio = star_electrons([20.0], p2, 30 * u.s).value[0] / expected
    assert ratio == pytest.approx(10 ** (-0.4 * 0.129))


def test_sky_per_pixel_scales_with_area_and_has_no_extinction():
    p = PhotometrySettings()
    sky = sky_electrons_per_pixel(p, 7.5 * u.mas, 30 * u.s).value
    star_like = star_electrons([21.61 - 2.5 * np.log10(0.0075**2)], p, 30 * u.s).value[0]
    assert sky == pytest.approx(star_like * 10 ** (0.4 * 0.129), rel=1e-10)
    assert sky_electrons_per_pixel(p, 15 * u.mas, 30 * u.s).value == pytest.approx(4 * sky)


@pytest.mark.parametrize("skew", [0.0, 0.01])
@pytest.mark.parametrize("nexp,gain", [(1, 1.0), (8, 1.0), (4, 2.5)])
def test_sky_only_variance_equals_mean_plus_read_noise(nexp, gain, skew):
    det = DetectorSettings(nx=300, ny=300, read_noise=3.0, gain=gain)
    mu = np.full((300, 300), 40.0)
    img, sat = expose_stack(mu, nexp, det, np.random.default_rng(5), skew_limit=skew)
    e = img.astype(float) * gain
    assert e.mean() == pytest.approx(40.0 * nexp, rel=2e-3)
    assert e.var() == pytest.approx(nexp * (40.0 + 9.0), rel=0.02)
    assert not sat.any()


def test_saturation_level_per_subexposure():
    det = DetectorSettings(nx=4, ny=1, bits=16, gain=2.0)
    full = 65535 * 2.0
    mu = np.array([[0.5 * full, 5 * full, 1e10, 0.0]])
    img, sat = expose_stack(mu, 3, det, np.random.default_rng(1))
    assert sat.tolist() == [[False, True, True, False]]
    assert img[0, 1] == img[0, 2] == pytest.approx(3 * 65535.0)
    img0, sat0 = expose_stack(mu, 3, det, np.random.default_rng(1), noise=False)
    assert img0[0].tolist() == pytest.approx([1.5 * 65535, 3 * 65535, 3 * 65535, 0.0])


def test_stack_matches_sum_of_individual_subexposures_in_distribution():
    """Per pixel level (incl. levels where sub-exposures sometimes saturate)."""
    det = DetectorSettings(nx=3000, ny=5, bits=10, read_noise=3.0)  # saturates at 1023 e-
    levels = np.array([5.0, 200.0, 1000.0, 1023.0, 1100.0])
    mu = np.repeat(levels[:, None], 3000, axis=1)
    nexp = 6
    rng = np.random.default_rng(11)
    stack, _ = expose_stack(mu, nexp, det, rng)
    singles = sum(expose_stack(mu, 1, det, rng)[0].astype(float) for _ in range(nexp))
    for row in range(len(levels)):
        a, b = stack[row].astype(float), singles[row]
        se = np.sqrt((a.var() + b.var()) / a.size)
        assert abs(a.mean() - b.mean()) < 5 * se + 1e-9
        assert abs(a.var() - b.var()) < 5 * np.hypot(_var_se(a), _var_se(b))


def _var_se(x):
    """Standard error of the sample variance (from the fourth central moment)."""
    d = x - x.mean()
    return np.sqrt(max((d**4).mean() - d.var() ** 2, 0.0) / x.size)


def test_bad_detector_settings_rejected():
    with pytest.raises(ValueError, match="gain"):
        DetectorSettings(gain=0)
    with pytest.raises(ValueError, match="nexp"):
        expose_stack(np.zeros((2, 2)), 0, DetectorSettings(), np.random.default_rng(0))


@pytest.mark.parametrize("var_rn,limit", [(1080.0, 0.01), (9.0, 0.05), (1080.0, 0.02)])
def test_exact_draw_window_is_where_skewness_reaches_the_limit(var_rn, limit):
    from mavispm.simulate.render.detector import _skewed_window

    lo, hi = _skewed_window(var_rn, limit)
    lam = np.geomspace(1e-3, 1e7, 20001)
    skew = lam / (lam + var_rn) ** 1.5
    inside = (lam >= lo) & (lam <= hi)
    assert np.array_equal(inside, skew >= limit)


@pytest.mark.parametrize("lam,var_rn", [(400.0, 0.0), (2160.0, 1080.0), (25.0, 4.0)])
def test_skew_corrected_draws_match_three_moments_of_poisson_plus_read_noise(lam, var_rn):
    from mavispm.simulate.render.detector import normal_stack_draws, skewed_normal

    n = 400_000
    z = np.random.default_rng(3).standard_normal(n, dtype=np.float32)
    mu = np.full(n, lam / 6.0)  # per sub-exposure, 6 sub-exposures
    compiled = np.empty(n, dtype=np.float32)
    normal_stack_draws(mu, z, 6, var_rn, 0.0, compiled)
    reference = skewed_normal(np.full(n, lam), var_rn, z.astype(float), 0.0)
    assert np.allclose(compiled, reference, rtol=1e-6, atol=1e-3)
    sd = np.sqrt(lam + var_rn)
    g = lam / sd**3  # skewness of Poisson(lam) + N(0, var_rn)
    d = compiled - compiled.mean()
    assert compiled.mean() == pytest.approx(lam, abs=5 * sd / np.sqrt(n))
    assert d.var() == pytest.approx(sd**2, rel=5 * np.sqrt(2 / n))
    skew = (d**3).mean() / d.var() ** 1.5
    assert abs(skew - g) < 5 * np.sqrt(6 / n)
    # below the limit: a plain Gaussian (no skewness)
    plain = np.empty(n, dtype=np.float32)
    normal_stack_draws(mu, z, 6, var_rn, np.inf, plain)
    assert np.allclose(plain, lam + sd * z, rtol=1e-6, atol=1e-3)


def test_skew_corrected_tier_of_the_stack_keeps_mean_variance_and_skewness():
    """With poisson_skew_limit above the largest skewness, no Poisson draw, same moments."""
    det = DetectorSettings(nx=1000, ny=2000, read_noise=3.0)
    nexp = 120
    mu = np.full((2000, 1000), 2160.0 / nexp)  # the most skewed level of this stack (0.0117)
    img, _ = expose_stack(
        mu, nexp, det, np.random.default_rng(8), skew_limit=0.01, poisson_skew_limit=0.1
    )
    e = img.astype(float).ravel()
    var = 2160.0 + nexp * 9.0
    d = e - e.mean()
    assert e.mean() == pytest.approx(2160.0, abs=5 * np.sqrt(var / e.size))
    assert d.var() == pytest.approx(var, rel=5 * np.sqrt(2 / e.size))
    skew = (d**3).mean() / d.var() ** 1.5
    # 3 standard errors (0.005): a plain Gaussian (skewness 0) would be 7 away
    assert abs(skew - 2160.0 / var**1.5) < 3 * np.sqrt(6 / e.size)


def test_noise_tiers_exact_corrected_and_plain():
    """skew_limit = 0: exact Poisson everywhere; between the limits: skew-corrected."""
    det = DetectorSettings(nx=200, ny=100, read_noise=0.0)
    mu = np.full((100, 200), 400.0)  # skewness of the 1-exposure stack: 400**-0.5 = 0.05
    exact, _ = expose_stack(
        mu, 1, det, np.random.default_rng(2), skew_limit=0.0, poisson_skew_limit=0.1
    )
    assert np.array_equal(exact, np.round(exact))  # Poisson counts (no read noise)
    corrected, _ = expose_stack(
        mu, 1, det, np.random.default_rng(2), skew_limit=0.01, poisson_skew_limit=0.1
    )
    assert not np.array_equal(corrected, np.round(corrected))
    counts, _ = expose_stack(
        mu.astype(int), 1, det, np.random.default_rng(2), skew_limit=0.01, poisson_skew_limit=0.04
    )
    assert np.array_equal(counts, np.round(counts))  # 0.05 >= 0.04: exact again
