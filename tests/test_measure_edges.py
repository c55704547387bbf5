"""Property-based edge cases of the batched fitter: never a crash, finite outputs, flags."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from measure_helpers import Detector, SynthPSF, mag_to_flux, noisy_frame, render_image, true_epsf

from mavispm.measure.stars.batched_fit import (
    FLAG_EDGE,
    FLAG_FAILED,
    FLAG_SATURATED,
    fit_stars,
)

SHAPE = (60, 60)
PSF = SynthPSF(1.2)
EPSF = true_epsf(PSF, SHAPE, size=15)
RN2 = 36.0

star = st.tuples(
    st.floats(-3.0, 62.0),  # x, may be off the frame
    st.floats(-3.0, 62.0),  # y
    st.one_of(st.just(99.0), st.floats(12.0, 26.0)),  # mag; 99 = zero flux
)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    stars=st.lists(star, min_size=1, max_size=8),
    duplicate=st.booleans(),
    nan_pixels=st.integers(0, 40),
    seed=st.integers(0, 2**16),
)
def test_fitter_never_crashes(stars, duplicate, nan_pixels, seed):
    x, y, mag = (np.array(v, float) for v in zip(*stars))
    if duplicate:  # two stars at identical positions
        x, y, mag = np.r_[x, x[:1]], np.r_[y, y[:1]], np.r_[mag, mag[:1]]
    flux = np.where(mag > 90, 0.0, mag_to_flux(mag))
    det = Detector(saturation=20000.0)
    rng = np.random.default_rng(seed)
    image, sat = noisy_frame(render_image(SHAPE, x, y, flux, PSF), det, rng)
    image = image.astype(float) * det.gain
    image.flat[rng.integers(0, image.size, nan_pixels)] = np.nan
    res = fit_stars(image, EPSF, x, y, read_noise_var=RN2, sky0=det.sky, saturated=sat)
    n = len(x)
    for arr in (res.x, res.y):
        assert arr.shape == (n,)
        assert np.all(np.isfinite(arr))
    good = (res.flag & FLAG_FAILED) == 0
    for arr in (res.x_err, res.y_err, res.flux, res.flux_err, res.sky, res.chi2):
        assert np.all(np.isfinite(arr[good]))
    # errors are either finite and positive or NaN for failed stars
    assert np.all(res.x_err[good] > 0)
    assert np.all(np.isnan(res.x_err[~good]))
    # stars off the frame fail and are flagged as edge stars
    off = (x <= -0.5) | (x >= SHAPE[1] - 0.5) | (y <= -0.5) | (y >= SHAPE[0] - 0.5)
    assert np.all(res.flag[off] & (FLAG_FAILED | FLAG_EDGE) == FLAG_FAILED | FLAG_EDGE)
    # zero-flux stars alone in the frame never claim a significant flux
    zero = (flux == 0) & ~off
    if np.all(flux == 0):
        assert np.all((res.flag[zero] & FLAG_FAILED) | (res.flux[zero] < 10 * res.flux_err[zero]))
    assert np.all(np.isfinite(res.model_image))


def test_saturated_star_is_kept_and_flagged():
    det = Detector(saturation=5000.0)
    x, y, flux = np.array([30.2]), np.array([29.7]), np.array([mag_to_flux(13.0)])
    image, sat = noisy_frame(render_image(SHAPE, x, y, flux, PSF), det, np.random.default_rng(1))
    assert sat.any()
    res = fit_stars(image * det.gain, EPSF, x, y, read_noise_var=RN2, sky0=det.sky, saturated=sat)
    assert res.flag[0] & FLAG_SATURATED
    assert not res.flag[0] & FLAG_FAILED
    # the wings alone still locate the star and recover its flux
    assert abs(res.x[0] - x[0]) < 0.05 and abs(res.y[0] - y[0]) < 0.05
    assert abs(res.flux[0] / flux[0] - 1) < 0.05


def test_edge_star_is_flagged_but_measured():
    det = Detector()
    x, y, flux = np.array([1.3]), np.array([30.0]), np.array([mag_to_flux(17.0)])
    image, sat = noisy_frame(render_image(SHAPE, x, y, flux, PSF), det, np.random.default_rng(2))
    res = fit_stars(image * det.gain, EPSF, x, y, read_noise_var=RN2, sky0=det.sky, saturated=sat)
    assert res.flag[0] & FLAG_EDGE
    assert abs(res.x[0] - x[0]) < 0.05
