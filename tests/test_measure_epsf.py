"""ePSF evaluation, field-variable models and building from the frame."""

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
    true_epsf,
)

from mavispm.core.errors import InputError
from mavispm.measure.stars.batched_fit import fit_stars
from mavispm.measure.stars.epsf import EPSFOptions, build_epsf, build_field_epsf, select_psf_stars
from mavispm.measure.stars.variable_psf import (
    StampGeometry,
    constant_epsf,
    gridded_epsf,
    polynomial_epsf,
    sample_epsf,
)

SHAPE = (240, 240)


def test_evaluation_matches_analytic_prf_and_derivatives():
    psf = SynthPSF(1.1)
    epsf = true_epsf(psf, SHAPE, size=21)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(20, 200, 50), rng.uniform(20, 200, 50)
    geom = StampGeometry(np.rint(x).astype(int), np.rint(y).astype(int), 5)
    val, dvx, dvy = epsf.evaluate(x, y, geom)
    exact = psf.prf(
        geom.columns()[:, None, :] - x[:, None, None],
        geom.rows()[:, :, None] - y[:, None, None],
        1.1,
        1.1,
    )
    assert np.max(np.abs(val - exact)) < 1e-4 * exact.max()
    h = 1e-3
    num_x = (
        epsf.evaluate(x + h, y, geom, derivatives=False)
        - epsf.evaluate(x - h, y, geom, derivatives=False)
    ) / (2 * h)
    num_y = (
        epsf.evaluate(x, y + h, geom, derivatives=False)
        - epsf.evaluate(x, y - h, geom, derivatives=False)
    ) / (2 * h)
    np.testing.assert_allclose(dvx, num_x, atol=2e-5)
    np.testing.assert_allclose(dvy, num_y, atol=2e-5)


def test_gridded_and_polynomial_mixing():
    a = sample_epsf(SynthPSF(1.0).prf_at(0, 0, SHAPE), 11, 4)
    b = sample_epsf(SynthPSF(1.5).prf_at(0, 0, SHAPE), 11, 4)
    grid = gridded_epsf(np.array([a, b]), np.array([50.0, 150.0]), np.array([100.0]), 4)
    np.testing.assert_allclose(grid.epsf_at(50, 100), a)
    np.testing.assert_allclose(grid.epsf_at(100, 30), 0.5 * (a + b))
    np.testing.assert_allclose(grid.epsf_at(400, 100), b)  # constant beyond the last node
    # a first-order polynomial through ePSFs varying linearly in x is exact
    xs = np.array([20.0, 120.0, 220.0, 20.0, 120.0, 220.0])
    ys = np.array([20.0, 20.0, 20.0, 220.0, 220.0, 220.0])
    frac = (xs - 20) / 200
    stack = np.array([(1 - f) * a + f * b for f in frac])
    poly = polynomial_epsf(stack, xs, ys, 1, SHAPE, 4)
    np.testing.assert_allclose(poly.epsf_at(70, 130), 0.75 * a + 0.25 * b, atol=1e-12)
    with pytest.raises(InputError, match="order 3"):
        polynomial_epsf(stack, xs, ys, 3, SHAPE, 4)


def _frame(psf, seed=1, spacing=24):
    rng = np.random.default_rng(seed)
    x, y = grid_positions(SHAPE, spacing, 14, rng)
    mag = rng.uniform(15.5, 18.5, len(x))
    det = Detector()
    image, sat = noisy_frame(render_image(SHAPE, x, y, mag_to_flux(mag), psf), det, rng)
    return image * det.gain, sat, x, y, mag_to_flux(mag), det


def test_fast_builder_recovers_the_psf():
    psf = SynthPSF(1.2)
    image, sat, x, y, flux, det = _frame(psf)
    truth = sample_epsf(psf.prf_at(120, 120, SHAPE), 21, 4)
    noise = det.sky + det.read_noise**2 * det.nexp
    rng = np.random.default_rng(3)
    for pert in (0.0, 0.05):
        xs, ys = x + rng.normal(0, pert, len(x)), y + rng.normal(0, pert, len(x))
        built = build_epsf(image - det.sky, xs, ys, EPSFOptions(size=21), sat, noise)
        assert built.shape == truth.shape
        assert built.sum() / 16 == pytest.approx(1.0)
        assert np.max(np.abs(built - truth)) < 0.05 * truth.max()


def test_variable_epsf_captures_field_variability():
    """A gridded ePSF built from the frame beats a constant one when the PSF varies."""
    psf = SynthPSF(1.2, gradient=0.4)
    image, sat, x, y, flux, det = _frame(psf, seed=2, spacing=20)
    noise = det.sky + det.read_noise**2 * det.nexp
    rn2 = det.read_noise**2 * det.nexp
    scores = {}
    for variation in ("constant", "grid", "polynomial"):
        opts = EPSFOptions(
            variation=variation, grid=3, poly_order=2, size=21, stars_per_node=30, min_snr=50
        )
        model, used = build_field_epsf(image - det.sky, x, y, flux, sat, noise, opts)
        assert model.kind == variation and len(used) > 20
        res = fit_stars(image, model, x, y, read_noise_var=rn2, sky0=det.sky, saturated=sat)
        scores[variation] = (np.median(res.chi2), None)
        corner = sample_epsf(psf.prf_at(40, 40, SHAPE), 21, 4)
        scores[variation] += (np.max(np.abs(model.epsf_at(40, 40) - corner)),)
    assert scores["grid"][0] < 0.5 * scores["constant"][0]
    assert scores["polynomial"][0] < 0.5 * scores["constant"][0]
    # the local ePSF near a corner matches the true local PSF better
    assert scores["grid"][2] < 0.5 * scores["constant"][2]
    # (the quadratic extrapolates to the corner: better than constant, not 2x)
    assert scores["polynomial"][2] < 0.9 * scores["constant"][2]


def test_psf_star_selection():
    x = np.array([50.0, 58.0, 120.0, 200.0, 5.0])
    y = np.array([50.0, 50.0, 120.0, 120.0, 120.0])
    flux = np.array([1e6, 1e5, 5e5, 2e5, 1e6])
    bad = np.zeros(SHAPE, bool)
    bad[122, 205] = True  # a saturated pixel next to star 3 (row, column)
    got = select_psf_stars(x, y, flux, SHAPE, bad, 21, 12.0, 0.01, 1e4)
    # 0 and 1 are too close, 3 touches a bad pixel, 4 is at the edge
    assert got.tolist() == [2]


def test_no_psf_stars_is_a_clear_error():
    image = np.zeros(SHAPE)
    with pytest.raises(InputError, match="PSF stars"):
        build_field_epsf(
            image,
            np.array([120.0]),
            np.array([120.0]),
            np.array([-1.0]),
            np.zeros(SHAPE, bool),
            60.0,
            EPSFOptions(),
        )


@pytest.mark.slow
def test_photutils_builder_cross_check():
    """Our builder and photutils' ``EPSFBuilder`` on the same PSF stars of a frame with a
    field-constant PSF, both scored against the exact pixel-integrated PSF (the
    synthesiser's error-function PRF): ours is at least as close to it, and the bright
    stars fitted with it at least as close to their true positions."""
    psf = SynthPSF(1.2)
    image, sat, x, y, flux, det = _frame(psf)
    noise = det.sky + det.read_noise**2 * det.nexp
    rn2 = det.read_noise**2 * det.nexp
    truth = sample_epsf(psf.prf_at(120, 120, SHAPE), 21, 4)
    built, misfit, scatter = {}, {}, {}
    for builder in ("fast", "photutils"):
        opts = EPSFOptions(size=21, builder=builder)
        built[builder] = build_epsf(image - det.sky, x, y, opts, sat, noise)
        misfit[builder] = np.sqrt(np.mean((built[builder] - truth) ** 2)) / truth.max()
        res = fit_stars(
            image, constant_epsf(built[builder], 4), x, y, read_noise_var=rn2, sky0=det.sky,
            saturated=sat,
        )  # fmt: skip
        ok = (res.flag & 32) == 0
        scatter[builder] = np.sqrt(np.mean((res.x - x)[ok] ** 2 + (res.y - y)[ok] ** 2))
    assert np.max(np.abs(built["fast"] - built["photutils"])) < 0.05 * truth.max()
    assert misfit["fast"] <= misfit["photutils"], misfit
    assert scatter["fast"] <= scatter["photutils"], scatter
