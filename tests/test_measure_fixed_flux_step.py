"""The fixed-position steps of the batched fitter: the flux and sky rows alone.

Before the first position step (the initial flux fit and ``flux_passes``) and in the
``flux_refresh`` pass the positions are held: the fitter then solves the flux and sky
(and slope) rows only, on ePSF stamps kept from their first evaluation while the
positions have not moved, instead of the full system with the position rows frozen
(docs/measure-scale.md, fifteenth pass). The references: the full system
(``fixed_full_system``, the former path) and, for the fixed point of the passes, a
weighted linear least-squares solve by numpy (``lstsq``) with the weights at the fit's
model. Frames from ``measure_helpers`` (exact pixel-integrated Gaussian PSF, Poisson
and read noise).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from measure_helpers import Detector, SynthPSF, mag_to_flux, noisy_frame, render_image, true_epsf

from mavispm.measure.stars.batched_fit import fit_stars
from mavispm.measure.stars.cli import validate_settings
from mavispm.measure.stars.crlb import sky_plane_basis
from mavispm.measure.stars.measure_frame import fit_options
from mavispm.measure.stars.variable_psf import StampGeometry

SHAPE = (160, 160)
PSF = SynthPSF(1.0)
DET = Detector(saturation=1e9)
RN2 = DET.read_noise**2 * DET.nexp


def _crowd(seed, n=250):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(6, SHAPE[1] - 7, n), rng.uniform(6, SHAPE[0] - 7, n)
    mag = rng.uniform(17, 25, n)
    image, sat = noisy_frame(render_image(SHAPE, x, y, mag_to_flux(mag), PSF), DET, rng)
    return image * DET.gain, sat, x + rng.normal(0, 0.1, n), y + rng.normal(0, 0.1, n)


def _fit(image, sat, x, y, options):
    psf = true_epsf(PSF, SHAPE)
    return fit_stars(
        image, psf, x, y, read_noise_var=RN2, sky0=DET.sky, saturated=sat, options=options,
        return_model=False,
    )  # fmt: skip


def test_the_stage_fit_equals_the_full_system_to_round_off():
    """The stage's options (5 flux passes, 40 sweeps, flux_refresh, sky slopes) on a
    crowd started 0.1 px off the truth: positions, fluxes, errors and flags as with the
    full system at fixed positions."""
    stage = fit_options(validate_settings({}))
    for seed in (0, 1):
        image, sat, x, y = _crowd(seed)
        new = _fit(image, sat, x, y, stage)
        old = _fit(image, sat, x, y, dataclasses.replace(stage, fixed_full_system=True))
        np.testing.assert_array_equal(new.flag, old.flag)
        for key in ("x", "y"):
            np.testing.assert_allclose(getattr(new, key), getattr(old, key), rtol=0, atol=1e-9)
        for key in ("flux", "sky", "x_err", "flux_err"):
            np.testing.assert_allclose(getattr(new, key), getattr(old, key), rtol=1e-9)


def test_fixed_passes_equal_the_full_system_to_round_off():
    """Positions held throughout (no position sweep): the fixed passes alone, with and
    without sky slopes."""
    for gradient in (True, False):
        options = dataclasses.replace(
            fit_options(validate_settings({})), iterations=0, sky_gradient=gradient
        )
        image, sat, x, y = _crowd(2)
        new = _fit(image, sat, x, y, options)
        old = _fit(image, sat, x, y, dataclasses.replace(options, fixed_full_system=True))
        np.testing.assert_array_equal(new.x, x)
        np.testing.assert_allclose(new.flux, old.flux, rtol=1e-10)
        np.testing.assert_allclose(new.sky, old.sky, rtol=1e-10)
        np.testing.assert_allclose(new.sky_slope, old.sky_slope, rtol=1e-8, atol=1e-12)


def test_fixed_passes_reach_the_weighted_least_squares_solution():
    """Isolated stars at held positions: many fixed passes converge to the weighted
    linear least-squares flux, sky and slopes of each stamp (numpy lstsq, the weights
    1 / (model + read noise) at the fit's model), bright or faint."""
    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(np.arange(12, 150, 23.0), np.arange(12, 150, 23.0))
    x = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    y = gy.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    mag = rng.uniform(16, 24, x.size)
    image, sat = noisy_frame(render_image(SHAPE, x, y, mag_to_flux(mag), PSF), DET, rng)
    image = image * DET.gain
    options = dataclasses.replace(
        fit_options(validate_settings({})),
        iterations=0,
        flux_passes=60,
        relative_tolerance=1e-12,
        wing_threshold=0.0,
        crowded_window=0,
    )
    fit = _fit(image, sat, x, y, options)
    psf = true_epsf(PSF, SHAPE)
    r = options.radius
    geom = StampGeometry(np.rint(x).astype(int), np.rint(y).astype(int), r)
    v = psf.evaluate(x, y, geom, derivatives=False).reshape(len(x), -1)
    basis = sky_plane_basis(geom.size)
    rows, cols = geom.rows(), geom.columns()
    for k in range(len(x)):
        data = image[rows[k][:, None], cols[k][None, :]].ravel()
        design = np.column_stack([v[k], np.ones_like(v[k]), basis[0], basis[1]])
        model = design @ np.array([fit.flux[k], fit.sky[k], *fit.sky_slope[k]])
        sw = 1.0 / np.sqrt(np.maximum(model, 0.0) + RN2)
        sol = np.linalg.lstsq(design * sw[:, None], data * sw, rcond=None)[0]
        np.testing.assert_allclose(fit.flux[k], sol[0], rtol=1e-7)
        np.testing.assert_allclose(fit.sky[k], sol[1], rtol=1e-7)
        np.testing.assert_allclose(fit.sky_slope[k], sol[2:], rtol=1e-5, atol=1e-9)
