"""Halo (large central PSF) and tilt covariance cross-checks against independent paths."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import j1

from mavispm.simulate.optics.atmosphere import (
    MAS_PER_RAD,
    AtmosphereSettings,
    fried_parameter,
    von_karman_psd,
)
from mavispm.simulate.optics.pupil import PupilSettings
from mavispm.simulate.optics.seeing_halo import HaloSettings, build_halo, ramp
from mavispm.simulate.optics.tiptilt import tilt_covariance_function


def test_zero_residual_halo_profile_is_obscured_airy():
    lam, diam, eps = 550e-9, 8.0, 0.14
    halo = build_halo(
        HaloSettings(size=2.0),
        np.array([0.0, 1000.0]),
        np.array([0.0, 0.0]),  # zero residual PSD everywhere
        lam,
        diam,
        eps,
        r0=1e6,
        outer_scale=25.0,
        control_radius_mas=284.0,
        stamp_half_width_mas=400.0,
    )
    alpha = np.array([5.0, 20.0, 40.0, 100.0]) / MAS_PER_RAD
    x = np.pi * diam * alpha / lam
    amp = (2 * j1(x) / x - eps**2 * 2 * j1(eps * x) / (eps * x)) / (1 - eps**2)
    area = np.pi * (diam / 2) ** 2 * (1 - eps**2)
    airy = area / lam**2 * amp**2 / MAS_PER_RAD**2  # per mas^2
    got = np.interp(alpha * MAS_PER_RAD, halo.radius, halo.profile)
    peak = area / lam**2 / MAS_PER_RAD**2
    np.testing.assert_allclose(got, airy, atol=2e-3 * peak, rtol=0.03)


def test_ramp_and_kernel_support():
    r = np.linspace(0, 10, 101)
    w = ramp(r, 2.0, 6.0)
    assert np.all(w[r <= 2] == 0) and np.all(w[r >= 6] == 1)
    assert np.all(np.diff(w) >= 0)


def _brute_force_tilt_cov(atm, pupil, height, delta):
    """2-D Fourier integral of the G-tilt cross-spectrum for one layer."""
    f1 = np.linspace(-3.0, 3.0, 1201)
    fx, fy = np.meshgrid(f1, f1)
    f = np.hypot(fx, fy)
    f = np.where(f == 0, 1e-9, f)
    eps = pupil.obscuration_ratio
    x = np.pi * pupil.diameter * f
    filt = (2 * j1(x) / x - eps**2 * 2 * j1(eps * x) / (eps * x)) / (1 - eps**2)
    r0 = fried_parameter(atm, 500e-9)
    w = von_karman_psd(f**2, r0, atm.outer_scale) * (500e-9 / (2 * np.pi)) ** 2
    s = (
        (2 * np.pi) ** 2
        * filt**2
        * w
        * np.cos(2 * np.pi * height * (fx * delta[0] + fy * delta[1]))
    )
    df2 = (f1[1] - f1[0]) ** 2
    return (
        np.array(
            [[np.sum(fx * fx * s), np.sum(fx * fy * s)], [np.sum(fx * fy * s), np.sum(fy * fy * s)]]
        )
        * df2
    )


@pytest.mark.parametrize("delta_arcsec", [(0.0, 0.0), (20.0, 0.0), (14.0, 14.0)])
def test_tilt_covariance_matches_brute_force(delta_arcsec):
    atm = AtmosphereSettings(
        layer_heights=(10000.0,),
        layer_weights=(1.0,),
        wind_speeds=(10.0,),
        wind_directions=(0.0,),
        zenith_angle=0.0,
    )
    pupil = PupilSettings()
    cov = tilt_covariance_function(atm, pupil, 100.0 / 206265.0)
    delta = np.asarray(delta_arcsec) / 206265.0
    got = cov(delta)
    ref = _brute_force_tilt_cov(atm, pupil, 10000.0, delta)
    np.testing.assert_allclose(got, ref, atol=0.02 * ref[0, 0] + 1e-30, rtol=0.02)
