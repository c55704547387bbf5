"""Forced-position fitting reaches the Cramér-Rao bound on isolated stars (known PSF)."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import (
    Detector,
    SynthPSF,
    grid_positions,
    mag_to_flux,
    noisy_frame,
    render_image,
    robust_sigma,
    true_epsf,
)

from mavispm.measure.stars.batched_fit import FLAG_NOT_CONVERGED, FitOptions, fit_stars
from mavispm.measure.stars.crlb import crlb

SHAPE = (300, 300)
BINS = [(16, 17), (17, 18), (18, 19), (19, 20), (20, 22), (22, 24)]


@pytest.fixture(scope="module")
def isolated_runs():
    """Isolated stars m = 16..24, 16 noise realisations, fitted with the true ePSF."""
    rng = np.random.default_rng(11)
    psf, det = SynthPSF(1.2), Detector()
    x, y = grid_positions(SHAPE, 20, 10, rng)
    # every bin equally populated
    mag = np.concatenate([rng.uniform(lo, hi, len(x) // len(BINS) + 1) for lo, hi in BINS])[
        : len(x)
    ]
    rng.shuffle(mag)
    flux = mag_to_flux(mag)
    epsf = true_epsf(psf, SHAPE)
    noiseless = render_image(SHAPE, x, y, flux, psf)
    rn2 = det.read_noise**2 * det.nexp
    dx, ex = [], []
    for seed in range(16):
        image, sat = noisy_frame(noiseless, det, np.random.default_rng(100 + seed))
        start_x = x + rng.normal(0, 0.2, len(x))
        start_y = y + rng.normal(0, 0.2, len(y))
        res = fit_stars(
            image * det.gain,
            epsf,
            start_x,
            start_y,
            read_noise_var=rn2,
            sky0=det.sky,
            saturated=sat,
        )
        assert not np.any(res.flag & ~FLAG_NOT_CONVERGED), np.bincount(res.flag)
        assert np.mean(res.flag & FLAG_NOT_CONVERGED) < 0.05
        dx.append(np.concatenate([res.x - x, res.y - y]))
        ex.append(np.concatenate([res.x_err, res.y_err]))
    bound = crlb(epsf, x, y, flux, det.sky, rn2, radius=FitOptions().radius)
    cr = np.concatenate([bound[:, 0], bound[:, 1]])
    return np.concatenate([mag, mag]), np.array(dx), np.array(ex), cr


@pytest.mark.parametrize("lo,hi", BINS)
def test_rms_and_bias_at_crlb(isolated_runs, lo, hi):
    mag, dx, _, cr = isolated_runs
    sel = (mag >= lo) & (mag < hi)
    z = (dx[:, sel] / cr[sel]).ravel()
    assert z.size >= 300
    assert robust_sigma(z) <= 1.1
    assert abs(np.mean(z)) <= 0.1


@pytest.mark.parametrize("lo,hi", BINS)
def test_reported_errors_match_scatter(isolated_runs, lo, hi):
    mag, dx, ex, _ = isolated_runs
    sel = (mag >= lo) & (mag < hi)
    z = (dx[:, sel] / ex[:, sel]).ravel()
    assert abs(np.std(z) - 1.0) <= 0.1


def test_crlb_matches_brute_force_fisher():
    """CRLB from the ePSF equals a finite-difference Fisher matrix of the analytic PRF."""
    psf = SynthPSF(1.3)
    epsf = true_epsf(psf, SHAPE)
    x0, y0, flux, sky, rn2 = 150.3, 149.8, 5e4, 40.0, 36.0
    bound = crlb(epsf, [x0], [y0], [flux], sky, rn2, radius=5)[0]
    cols = np.arange(145, 156)[None, :]
    rows = np.arange(145, 156)[:, None]

    def model(p):
        return p[2] * psf.prf(cols - p[0], rows - p[1], 1.3, 1.3) + p[3]

    p0 = np.array([x0, y0, flux, sky])
    steps = np.array([1e-4, 1e-4, 1.0, 1e-3])
    jac = np.array(
        [(model(p0 + s * e) - model(p0 - s * e)) / (2 * s) for s, e in zip(steps, np.eye(4))]
    ).reshape(4, -1)
    var = model(p0).ravel() + rn2
    cov = np.linalg.inv((jac / var) @ jac.T)
    np.testing.assert_allclose(bound, np.sqrt(np.diag(cov)), rtol=2e-3)


def test_crlb_photon_limit():
    """Without sky and read noise a well-sampled Gaussian gives sigma / sqrt(F)."""
    psf = SynthPSF(3.0)
    epsf = true_epsf(psf, SHAPE, size=41)
    flux = 1e6
    bound = crlb(epsf, [150.0], [150.0], [flux], 0.0, 1e-9, radius=18)[0]
    # pixel integration adds 1/12 pixel^2 to the variance of a Gaussian
    expected = np.sqrt(3.0**2 + 1 / 12) / np.sqrt(flux)
    assert bound[0] == pytest.approx(expected, rel=0.02)
    assert bound[2] == pytest.approx(np.sqrt(flux), rel=0.05)


def test_zero_flux_crlb_is_nan():
    epsf = true_epsf(SynthPSF(1.2), SHAPE)
    bound = crlb(epsf, [150.0], [150.0], [0.0], 50.0, 36.0)
    assert np.all(np.isnan(bound[0, :2]))
