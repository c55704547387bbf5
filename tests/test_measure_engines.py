"""The batched engine agrees with photutils PSFPhotometry on the same frame and ePSF."""

from __future__ import annotations

import numpy as np
from measure_helpers import (
    Detector,
    SynthPSF,
    grid_positions,
    mag_to_flux,
    noisy_frame,
    render_image,
    true_epsf,
)

from mavispm.measure.stars.batched_fit import FLAG_FAILED, fit_stars
from mavispm.measure.stars.photutils_engine import PhotutilsOptions, fit_stars_photutils


def test_engines_agree():
    shape = (160, 160)
    rng = np.random.default_rng(8)
    psf, det = SynthPSF(1.2, gradient=0.3), Detector()
    x, y = grid_positions(shape, 20, 10, rng)
    mag = rng.uniform(17, 21, len(x))
    flux = mag_to_flux(mag)
    image, sat = noisy_frame(render_image(shape, x, y, flux, psf), det, rng)
    image = image * det.gain
    epsf = true_epsf(psf, shape, grid=3, size=15)
    rn2 = det.read_noise**2 * det.nexp
    start_x, start_y = x + rng.normal(0, 0.1, len(x)), y + rng.normal(0, 0.1, len(y))
    fast = fit_stars(image, epsf, start_x, start_y, read_noise_var=rn2, sky0=det.sky, saturated=sat)
    ref = fit_stars_photutils(
        image, epsf, start_x, start_y, read_noise_var=rn2, sky0=det.sky, saturated=sat,
        options=PhotutilsOptions(fitter="levmar"),
    )  # fmt: skip
    ok = ((fast.flag | ref.flag) & FLAG_FAILED) == 0
    assert ok.mean() > 0.95
    # positions agree to a fraction of their uncertainty, fluxes to a few sigma
    dpos = np.hypot(fast.x - ref.x, fast.y - ref.y)[ok] / fast.x_err[ok]
    assert np.median(dpos) < 0.5
    assert np.percentile(dpos, 90) < 1.5
    assert np.median(np.abs(fast.flux - ref.flux)[ok] / fast.flux_err[ok]) < 1.0
    # and both are close to the truth
    for res in (fast, ref):
        z = (res.x - x)[ok] / fast.x_err[ok]
        assert np.std(z) < 1.5
    # photutils reports comparable uncertainties
    assert 0.7 < np.median(ref.x_err[ok] / fast.x_err[ok]) < 1.4
