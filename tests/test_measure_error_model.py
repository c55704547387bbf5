"""Honest uncertainties: ePSF model error and chi^2 terms against the truth of rendered frames."""

from __future__ import annotations

import json

import astropy.units as u
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from measure_helpers import (
    SynthPSF,
    normalised_residuals,
    render_image,
    robust_sigma,
    write_frames,
)

from mavispm.core.errors import ConfigError
from mavispm.core.products import read_product
from mavispm.measure.stars.batched_fit import FitOptions, fit_stars
from mavispm.measure.stars.cli import run_stage, validate_settings
from mavispm.measure.stars.epsf import AUTO_OVERSAMPLING_X4, resolve_oversampling
from mavispm.measure.stars.error_model import (
    ErrorModel,
    epsf_difference_shifts,
    estimate_error_model,
    flux_trend,
)
from mavispm.measure.stars.measure_frame import MEASURED_SPEC
from mavispm.measure.stars.variable_psf import constant_epsf, sample_epsf

SHAPE = (300, 300)
#: few PSF stars per node and a x4 ePSF: the bright stars are limited by the ePSF
SETTINGS = {
    "psf_grid": 2,
    "psf_stars_per_node": 25,
    "psf_star_min_snr": 50.0,
    "epsf_iterations": 5,
    "oversampling": 4,
}


def _gaussian_epsf(shift=0.0, sigma=1.3, over=4):
    psf = SynthPSF(sigma)
    return sample_epsf(lambda dx, dy: psf.prf(dx - shift, dy, sigma, sigma), 15, over)


def test_linearised_shift_recovers_a_known_epsf_offset():
    over = 4
    psf_a = constant_epsf(_gaussian_epsf(0.0), over)
    psf_b = constant_epsf(_gaussian_epsf(0.02), over)
    x = np.array([20.3, 40.0, 60.7])
    y = np.array([20.1, 40.5, 60.9])
    flux = np.array([1e4, 1e5, 1e6])
    out = epsf_difference_shifts(psf_a, psf_a, psf_b, x, y, flux, np.full(3, 50.0), 36.0, 5)
    # model b is model a moved by +0.02 px in x: one Gauss-Newton step finds it
    np.testing.assert_allclose(out[:, 0], 0.02, rtol=0.05)
    np.testing.assert_allclose(out[:, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(out[:, 2] / flux, 0.0, atol=2e-3)
    # identical ePSFs: no change; a non-finite star: NaN, no crash
    same = epsf_difference_shifts(
        psf_a, psf_a, psf_a, np.array([20.0, np.nan]), np.array([20.0, 5.0]),
        np.array([1e4, 1e4]), np.array([50.0, 50.0]), 36.0, 5,
    )  # fmt: skip
    np.testing.assert_allclose(same[0], 0.0, atol=1e-10)
    assert np.all(np.isnan(same[1]))


@pytest.mark.parametrize("sep, ratio", [(1.8, 0.02), (2.5, 0.1), (3.0, 1.0)])
def test_blended_pair_errors_match_the_joint_fisher_matrix(sep, ratio):
    """Errors of a close pair = brute-force joint Fisher matrix of both stars."""
    psf = SynthPSF(1.2)
    epsf = constant_epsf(sample_epsf(psf.prf_at(0, 0, (1, 1)), 21, 4), 4)
    sky, rn2, n = 100.0, 36.0, 61
    x, y = np.array([30.3, 30.3 + sep]), np.array([30.2, 30.2])
    flux = np.array([1e6, 1e6 * ratio])
    image = render_image((n, n), x, y, flux, psf) + sky
    plain = fit_stars(
        image, epsf, x, y, read_noise_var=rn2, sky0=sky, options=FitOptions(blend_radius=0.0)
    )
    joint_fit = fit_stars(image, epsf, x, y, read_noise_var=rn2, sky0=sky)
    # brute force: 7 parameters (x, y, flux of both, one sky) on the union of the stamps
    yy, xx = np.mgrid[:n, :n]
    inside = np.zeros((n, n), bool)
    for xi, yi in zip(x, y):
        inside |= (np.abs(xx - np.rint(xi)) <= 5) & (np.abs(yy - np.rint(yi)) <= 5)
    model, columns, h = np.full((n, n), sky), [], 1e-4
    for k in range(2):

        def prf(xs, ys):
            return psf.prf(xx - xs, yy - ys, 1.2, 1.2)

        model += flux[k] * prf(x[k], y[k])
        columns += [
            flux[k] * (prf(x[k] + h, y[k]) - prf(x[k] - h, y[k])) / (2 * h),
            flux[k] * (prf(x[k], y[k] + h) - prf(x[k], y[k] - h)) / (2 * h),
            prf(x[k], y[k]),
        ]
    columns.append(np.ones((n, n)))
    jac = np.array([c[inside] for c in columns])
    cov = np.linalg.inv((jac / (model[inside] + rn2)) @ jac.T)
    joint = np.sqrt(np.diag(cov))[[0, 3]]
    np.testing.assert_allclose(joint_fit.x_err, joint, rtol=0.05)
    # the per-star Fisher errors miss the pair's covariance
    assert np.all(plain.x_err < 0.9 * joint)


def test_flux_trend_follows_a_known_law():
    rng = np.random.default_rng(3)
    flux = 10 ** rng.uniform(3, 6, 4000)
    sigma = 0.5 * (flux / 1e3) ** -0.25
    values = rng.normal(0.0, sigma)
    trend = flux_trend(flux, values, lambda v: 1.4826 * np.median(np.abs(v)), min_per_bin=200)
    probe = np.array([3e3, 3e4, 3e5])
    np.testing.assert_allclose(trend(probe), 0.5 * (probe / 1e3) ** -0.25, rtol=0.15)
    # a power law (the chi^2 of bright stars) is extrapolated beyond the brightest bin
    chi2 = 1e-3 * flux
    power = flux_trend(flux, chi2, np.median, min_per_bin=200, log_values=True)
    np.testing.assert_allclose(power(np.array([1e7])), 1e4, rtol=0.2)


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(0, 30),
    bad=st.floats(0, 1),
    with_shifts=st.booleans(),
)
def test_error_model_edges_are_finite(n, bad, with_shifts):
    rng = np.random.default_rng(n)
    flux = 10 ** rng.uniform(2, 6, n)
    flux[rng.uniform(size=n) < bad] = np.nan
    chi2 = rng.uniform(0.5, 50, n)
    chi2[rng.uniform(size=n) < bad / 2] = np.nan
    shifts = rng.normal(0, 0.01, (n, 4)) if with_shifts else None
    usable = np.isfinite(flux)
    model = estimate_error_model(flux, chi2, usable, shifts)
    for arr in (model.position, model.flux, model.chi2_ratio, model.chi2_inflation):
        assert arr.shape == (n,) and np.all(np.isfinite(arr))
    assert np.all(model.chi2_ratio >= 1) and np.all(model.chi2_inflation >= 1)
    total = model.total(np.full(n, 0.01), model.position)
    assert np.all(total >= 0.01 - 1e-15)


def test_error_model_without_model_terms_is_fisher():
    model = ErrorModel.fisher_only(3)
    np.testing.assert_array_equal(
        model.total(np.array([0.1, 0.2, np.nan]), model.position)[:2], [0.1, 0.2]
    )


def test_oversampling_auto_follows_the_psf_star_count():
    assert resolve_oversampling("auto", AUTO_OVERSAMPLING_X4) == 4
    assert resolve_oversampling("auto", AUTO_OVERSAMPLING_X4 - 1) == 2
    assert resolve_oversampling(3, 5) == 3  # an explicit setting wins
    assert validate_settings({}).oversampling == "auto"
    assert validate_settings({"oversampling": 2}).oversampling == 2
    with pytest.raises(ConfigError):
        validate_settings({"oversampling": "four"})
    with pytest.raises(ConfigError):
        validate_settings({"error_model": "chi"})


@pytest.fixture(scope="module")
def crowded_frame(tmp_path_factory):
    rng = np.random.default_rng(7)
    n = 300
    x, y = rng.uniform(6, SHAPE[1] - 6, n), rng.uniform(6, SHAPE[0] - 6, n)
    mag = 16 + 10 * rng.uniform(0, 1, n) ** 0.6
    path = tmp_path_factory.mktemp("errors") / "frame.h5"
    psf = SynthPSF(1.3, gradient=0.25, profile="moffat")
    write_frames(path, SHAPE, x, y, mag, psf, seed=3)
    return path


def test_reported_errors_describe_the_scatter_with_a_frame_built_epsf(crowded_frame, tmp_path):
    out = run_stage(crowded_frame, SETTINGS, tmp_path / "measured.h5", seed=1)
    product = read_product(out, "measured", specs={"stars": MEASURED_SPEC})
    stars = product.tables["stars"]
    assert product.attrs["error_model"] == "epsf"
    assert product.attrs["epsf_position_error"].to_value(u.mas) > 0
    fitted = np.isfinite(stars["x_err"])
    assert np.all(stars["x_err"][fitted] >= stars["x_err_fisher"][fitted])
    fisher = list(normalised_residuals(stars, "x_err_fisher").values())
    honest = list(normalised_residuals(stars, "x_err").values())
    # the problem: the Fisher errors of the bright stars miss the ePSF error
    assert np.std(fisher[0]) > 3
    # the reported errors: normalised residuals with unit scatter in every bin
    # (faintest bin: robust, a few blends make the tail); the sky plane of the fit
    # (default) removes part of the neighbours' residual light that the chi^2 terms
    # of the error model describe, so the errors are conservative by up to 1 / 0.63
    # here (0.63-1.0 over four frames; 0.81-1.37 with a constant sky)
    for z in honest[:3]:
        assert 0.55 < np.std(z) < 1.4
    assert 0.7 < robust_sigma(honest[3]) < 1.3
    # error_model = "fisher" reports the Fisher errors
    pure = run_stage(
        crowded_frame, {**SETTINGS, "error_model": "fisher"}, tmp_path / "f.h5", seed=1
    )
    pure_stars = read_product(pure, "measured").tables["stars"]
    np.testing.assert_allclose(
        pure_stars["x_err"].value, pure_stars["x_err_fisher"].value, equal_nan=True
    )


def test_auto_oversampling_counts_the_stars_used(tmp_path):
    """484 isolated stars, constant PSF: more than 200 usable PSF stars but 150 used (the
    cap). The old rule (x4 from 200 usable) left the bright stars at 2.75x the Cramér-Rao
    bound (computed with the exact PRF); "auto" now takes x2, at 1.0-1.1x."""
    from measure_helpers import Detector, grid_positions, mag_to_flux, true_epsf, write_frames

    from mavispm.measure.stars.crlb import crlb

    rng = np.random.default_rng(5)
    shape, psf, det = (300, 300), SynthPSF(1.0), Detector()
    x, y = grid_positions(shape, 13, 8, rng)
    mag = rng.uniform(16.0, 21.0, len(x))
    write_frames(tmp_path / "f.h5", shape, x, y, mag, psf, det, seed=3)
    epsf = true_epsf(psf, shape)
    ratio = {}
    for setting in ("auto", 4):
        out = run_stage(
            tmp_path / "f.h5", {"psf_variation": "constant", "oversampling": setting},
            tmp_path / f"m{setting}.h5", seed=0,
        )  # fmt: skip
        prod = read_product(out, "measured")
        assert prod.attrs["n_psf_stars"] == 150
        stars = prod.tables["stars"]
        flux = mag_to_flux(mag) * prod.attrs["epsf_flux_fraction"]
        sky = np.full(len(x), det.sky)
        bound = crlb(epsf, x, y, flux, sky, det.read_noise**2 * det.nexp, 5)[:, 0]
        dx = np.asarray(stars["x_pix"]) - x
        ok = (np.asarray(stars["flag"]) & (4 | 8 | 32)) == 0
        ratio[setting] = [
            robust_sigma(dx[k]) / np.median(bound[k])
            for lo, hi in ((16, 18), (18, 19.5), (19.5, 21))
            for k in [ok & (mag >= lo) & (mag < hi)]
        ]
        if setting == "auto":
            assert json.loads(prod.attrs["epsf"])["oversampling"] == 2
    assert max(ratio["auto"]) < 1.3, ratio
    assert ratio[4][0] > 1.5 * ratio["auto"][0], ratio  # the frame where x4 fell short


def test_frame_built_epsf_bright_stars_accurate_and_honest_against_the_truth(tmp_path):
    """The peer benchmark's frame (benchmarks/bench_measure.py, section 4c: 3,500 stars on
    2000 x 2000 px, Gaussian PSF sigma 1.2 px +-20 % over the field, m = 16-25, start
    positions with 0.05 px catalogue errors), default settings (3 x 3 ePSF grid from the
    frame, one neighbour pass); scored against the truth only.

    Before: the neighbour-pass rebuild took PSF stars with neighbours as bright as
    themselves, whose residuals moved node ePSFs by up to 0.024 px (3.5 x CRLB at V
    16-18), and the half-set ePSFs of the error model were built from the full chain's
    fitted positions and shared its errors (robust normalised residuals 1.76 / 1.34 at V
    16-18 / 18-20). Then 1.8 / 1.2 x CRLB, normalised residuals 0.90 / 0.90; since the
    neighbour-pass rebuild is centred on the (perturbed) start positions, as the first
    build, 2.1 / 1.3 x and 0.99 / 0.96 (docs/measure.md, "ePSF of the frame on the
    NGC 3201 frame")."""
    from measure_helpers import Detector, mag_to_flux, true_epsf

    from mavispm.measure.stars.crlb import crlb
    from mavispm.measure.stars.measure_frame import measure_frame, read_frame

    n, side, det, psf = 3500, 2000, Detector(saturation=1e9), SynthPSF(1.2, gradient=0.2)
    rng = np.random.default_rng(n + 1)
    x, y = rng.uniform(3, side - 4, n), rng.uniform(3, side - 4, n)
    mag = rng.uniform(16, 25, n)
    write_frames(tmp_path / "peer.h5", (side, side), x, y, mag, psf, det, seed=n + 2)
    frame = read_frame(tmp_path / "peer.h5")
    stars, attrs, _ = measure_frame(frame, validate_settings({"perturbation": 0.05}), seed=5)
    assert attrs["psf_model"] == "epsf" and attrs["error_model"] == "epsf"
    scale = frame.pixel_scale
    sx, sy = np.asarray(stars["x_pix"]), np.asarray(stars["y_pix"])
    x_err = stars["x_err"].to_value(u.arcsec) / scale
    y_err = stars["y_err"].to_value(u.arcsec) / scale
    ok = ((np.asarray(stars["flag"]) & 32) == 0) & np.isfinite(sx) & np.isfinite(x_err)
    bound = crlb(
        true_epsf(psf, (side, side), grid=5, size=21), x, y, mag_to_flux(mag),
        np.full(n, det.sky), det.read_noise**2 * det.nexp, 5,
    )  # fmt: skip
    dx, dy = sx - x, sy - y
    for lo, hi, worst in ((16, 18, 2.5), (18, 20, 1.5)):
        s = ok & (mag >= lo) & (mag < hi)
        assert s.sum() > 600
        ratio = np.r_[dx[s] / bound[s, 0], dy[s] / bound[s, 1]]
        assert robust_sigma(ratio) <= worst, (lo, robust_sigma(ratio))
        norm = np.r_[dx[s] / x_err[s], dy[s] / y_err[s]]
        assert abs(robust_sigma(norm) - 1.0) <= 0.2, (lo, robust_sigma(norm))


def test_odd_chi2_is_one_for_noise_and_blind_to_an_even_misfit():
    """The odd part's reduced chi^2: 1 for white noise (its expectation, analytic), 0 for
    a field even about the star at any sub-pixel phase, large for one on one side."""
    from mavispm.measure.stars.odd_residual import odd_chi2

    rng = np.random.default_rng(2)
    n, size = 3000, 11
    dx, dy = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n)
    valid = rng.random((n, size, size)) > 0.05
    noise = odd_chi2(rng.normal(size=(n, size, size)), valid, dx, dy, 0)
    assert np.mean(noise) == pytest.approx(1.0, abs=0.02)
    rows, cols = np.mgrid[:size, :size] - size // 2
    for ox, oy in ((0.0, 0.0), (0.3, -0.2), (-0.45, 0.5)):
        even = np.exp(-((cols - ox) ** 2 + (rows - oy) ** 2) / 8.0)[None] * 50
        side = np.exp(-((cols - ox - 2.5) ** 2 + (rows - oy) ** 2) / 8.0)[None] * 50
        ones = np.ones((1, size, size), bool)
        at = (np.array([ox]), np.array([oy]))
        full = np.sum(even**2) / size**2
        assert odd_chi2(even, ones, *at, 0)[0] < 5e-3 * full  # interpolation leak only
        assert odd_chi2(side, ones, *at, 0)[0] > 0.5 * full


@pytest.mark.parametrize("model", ["psfr", "centred_epsf"])
def test_position_errors_ignore_an_even_misfit_and_keep_an_odd_one(model):
    """Rendered frame, the truth as reference: one model PSF (Gaussian, sigma 1.6 px, well
    sampled) for three kinds of star. Half are rendered with it; a quarter 10 % narrower
    (a misfit even about the star: it raises the chi^2 ~17 x and leaves the positions at
    their Fisher scatter); a quarter with an unlisted companion 4 px away, 3 % of its
    flux (odd: it pulls the star). The error rules that take the chi^2 against the
    peers' (``error_terms`` with PSF-R kernels, and the frame-built ePSF with its nodes
    centred on all stars, the stage's default) with the whole chi^2 made the narrower
    stars' position errors 3 x too large (normalised residuals 0.31 / 0.32); from the odd
    part of the residual they are right, and the companions' stars keep an inflation."""
    import types

    from mavispm.measure.stars.measure_frame import FramePSF, error_terms
    from mavispm.measure.stars.settings import MeasureSettings

    rng = np.random.default_rng(3)
    shape, sigma, sky, rn2 = (360, 360), 1.6, 100.0, 25.0
    grid = np.arange(12, 350, 14)
    x, y = (a.ravel() + rng.uniform(-0.5, 0.5, a.size) for a in np.meshgrid(grid, grid))
    n = len(x)
    flux = 10 ** rng.uniform(4.3, 5.7, n)
    kind = rng.permutation(np.arange(n) % 4)  # 0, 1: exact; 2: narrower; 3: companion
    angle = rng.uniform(0, 2 * np.pi, n)
    psf = SynthPSF(sigma)
    image = np.full(shape, sky)
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    for i in range(n):
        cx, cy = int(np.rint(x[i])), int(np.rint(y[i]))
        box = np.s_[cy - 6 : cy + 7, cx - 6 : cx + 7]
        ox, oy = cols[box] - x[i], rows[box] - y[i]
        width = sigma * (0.9 if kind[i] == 2 else 1.0)
        light = psf.prf(ox, oy, width, width)
        if kind[i] == 3:
            cos, sin = 4.0 * np.cos(angle[i]), 4.0 * np.sin(angle[i])
            light = light + 0.03 * psf.prf(ox - cos, oy - sin, sigma, sigma)
        image[box] += flux[i] * light
    image = rng.poisson(image) + rng.normal(0.0, np.sqrt(rn2), shape)
    epsf = constant_epsf(sample_epsf(psf.prf_at(0, 0, (1, 1)), 21, 4), 4)
    settings = MeasureSettings()
    options = FitOptions(radius=settings.stamp_radius, sky_gradient=settings.sky_gradient)
    fit = fit_stars(image, epsf, x, y, read_noise_var=rn2, sky0=sky, options=options)
    frame = types.SimpleNamespace(shape=shape, read_noise_var=rn2, sky=sky)
    if model == "psfr":
        frame_psf = FramePSF(epsf, 0, psfr_kernels=np.zeros((1, 4)))
    else:  # the nodes centred on all stars, their own (here: no) centring error
        centring = types.SimpleNamespace(error_at=lambda psf, x, y: np.zeros(len(x)))
        frame_psf = FramePSF(epsf, 0, centring=(centring,))
    errors = error_terms(frame, frame_psf, fit, settings)
    ok = (fit.flag & 32) == 0
    assert ok.mean() > 0.99
    d = np.r_[fit.x - x, fit.y - y]
    err = np.r_[errors.position_total(fit.x_err, 0), errors.position_total(fit.y_err, 1)]
    fisher = np.r_[fit.x_err, fit.y_err]

    def scores(members):
        s = np.r_[ok & members, ok & members]
        moved = robust_sigma(d[s] / fisher[s])  # the truth: how far they moved, in Fisher
        return moved, robust_sigma(d[s] / err[s]), np.median(err[s] / fisher[s])

    for members in (kind < 2, kind == 2):
        moved, norm, _ = scores(members)
        assert moved < 1.15  # the even misfit does not move them (the scene's premise)
        assert abs(norm - 1.0) <= 0.15, norm  # whole chi^2: 0.31 for the narrower stars
    moved, norm, inflation = scores(kind == 3)
    assert moved > 3.0  # the companion pulls them (truth: 4.4 x Fisher)
    # their errors are inflated (1.62 x; the whole chi^2 gave 1.22 x), yet still short of
    # the pull of an unlisted companion, which the fit absorbs (normalised 2.9)
    assert inflation > 1.4, inflation
