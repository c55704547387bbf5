"""Honest proper-motion errors and the extrapolation flag (issue 14, PSF-R-sized errors).

Synthesised epochs with known true motions (``propermotions_helpers``): per-epoch
position errors from 3 microarcsec (bright, PSF-R-like) to 0.3 mas (faint), internal
motions of 0.25 mas/yr (a 2.5 mas jitter over 10 yr that dominates the alignment
weights) and a ~0.03 mas quadratic + cubic dynamic distortion in the second epoch (the
size of the stacked image motion's non-linear part on the NGC 3201 frames). The truth
is the injected motion, taken into the measured relative frame here by an independent
``numpy.linalg.lstsq`` projection (not the stage's own ``pm_x_true``).
"""

from __future__ import annotations

import numpy as np
import pytest
from propermotions_helpers import distortion_transform, make_cluster, observe

from mavispm.measure.propermotions.alignment import TransformModel, fit_transform
from mavispm.measure.propermotions.pipeline import PMFlag, derive_proper_motions, extrapolated
from mavispm.measure.propermotions.settings import validate_settings

#: magnitude bins of the calibration check (make_cluster: errors log-uniform in mag)
BINS = [(16, 18), (18, 20), (20, 22), (22, 24), (24, 26), (26, 27)]


def _monomials(x, y, order, length=15.0):
    u, v = np.asarray(x) / length, np.asarray(y) / length
    return np.column_stack([u**i * v ** (n - i) for n in range(order + 1) for i in range(n + 1)])


def _relative_truth(res, truth, obs, order):
    """True motions [mas/yr] minus what the epoch-1 fit absorbs (weighted lstsq)."""
    fit = res.fits[1]
    ids = res.match.ids
    idx = np.searchsorted(truth.ids, ids)
    pm = np.column_stack([truth.pm_x, truth.pm_y])[idx]
    rows = np.searchsorted(obs[1].ids, ids)
    a = _monomials(obs[1].x[rows], obs[1].y[rows], order)
    out = []
    for k in range(2):
        w = np.sqrt(fit.weights[fit.used, k])
        c, *_ = np.linalg.lstsq(a[fit.used] * w[:, None], pm[fit.used, k] * w, rcond=None)
        out.append(pm[:, k] - a @ c)
    keep = np.isin(ids, np.asarray(res.stars["id"]))
    return out[0][keep], out[1][keep]


def _pooled(order, seeds=range(6)):
    z, mag, f64 = [], [], []
    for seed in seeds:
        truth = make_cluster(n=2500, seed=seed, err_range=(3e-6, 3e-4))
        tr = distortion_transform(seed=30 + seed, amplitude=3e-5, order=3)
        obs = observe(truth, [0.0, 10.0], [None, tr], seed=50 + seed)
        res = derive_proper_motions(obs, validate_settings({"order": order}))
        s = res.stars
        rx, ry = _relative_truth(res, truth, obs, order)
        z.append((s["pm_x"].value - rx) / s["pm_x_err"].value)
        z.append((s["pm_y"].value - ry) / s["pm_y_err"].value)
        mag += [s["mag"].value] * 2
        f64.append(np.asarray(s["flag"]) & PMFlag.EXTRAPOLATED > 0)
    z, mag = np.concatenate(z), np.concatenate(mag)
    std = {b: float(np.std(z[(mag >= b[0]) & (mag < b[1])])) for b in BINS}
    return std, float(np.mean(np.concatenate(f64)))


def test_pm_errors_are_calibrated_in_magnitude_bins_and_few_stars_flagged_64():
    std, frac64 = _pooled(order=3)
    # measured: 0.96-1.03 in the six bins; no star flagged 64 (the former rule, transformation
    # variance > the star's own, flagged 21% here: the best-measured stars)
    for b, s in std.items():
        assert abs(s - 1.0) <= 0.15, (b, s)
    assert frac64 <= 0.01


def test_a_transformation_that_cannot_absorb_the_distortion_shows_in_the_bright_bins():
    # the cause of the NGC 3201 std 1.47: order 1 leaves the cubic image motion in the
    # PMs, visible where the stars' own errors are small (measured 2.21 at V 16-18,
    # 1.46 at 18-20, 1.00 at 24-26)
    std, _ = _pooled(order=1)
    assert std[(16, 18)] > 1.5
    assert abs(std[(24, 26)] - 1.0) <= 0.15


@pytest.mark.parametrize("epochs", [(0.0, 10.0), (0.0, 2.5, 5.0, 7.5, 10.0)])
def test_frame_error_columns_make_errors_honest_against_the_absolute_motion(epochs):
    # against the true motion minus the injected systemic motion, the bright stars'
    # error is the frame's (the reference stars' internal motions): pm_x_err alone is
    # far too small, hypot(pm_x_err, pm_x_err_frame) is right (pooled over realisations:
    # the frame error is common to neighbouring stars)
    z_total, z_own = [], []
    for seed in range(16):
        truth = make_cluster(n=1500, seed=seed, err_range=(3e-6, 1e-3))
        tr = [None] + [
            distortion_transform(seed=40 + seed + k, amplitude=0.0) for k in (1, 2, 3, 4)
        ]
        obs = observe(truth, epochs, tr[: len(epochs)], seed=60 + seed)
        s = derive_proper_motions(obs, validate_settings({"order": 1})).stars
        idx = np.searchsorted(truth.ids, np.asarray(s["id"]))
        bright = truth.mag[idx] < 20
        for axis, sys_pm in (("x", 0.3), ("y", -0.2)):  # make_cluster's pm_sys
            d = s[f"pm_{axis}"].value - (getattr(truth, f"pm_{axis}")[idx] - sys_pm)
            own = s[f"pm_{axis}_err"].value
            total = np.hypot(own, s[f"pm_{axis}_err_frame"].value)
            z_total.append((d / total)[bright])
            z_own.append((d / own)[bright])
    assert abs(np.std(np.concatenate(z_total)) - 1.0) <= 0.15  # measured 0.97 (2 epochs), 1.00 (5)
    assert np.std(np.concatenate(z_own)) > 3.0  # measured 5.2, 6.7


def _disc_fit(n=400, radius=10.0, seed=0, order=3):
    rng = np.random.default_rng(seed)
    r = radius * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    x, y = r * np.cos(phi), r * np.sin(phi)
    var = np.full(n, (0.1e-3) ** 2)
    model = TransformModel(order=order, length=radius)
    fit = fit_transform(
        x, y, x + rng.normal(0, 1e-4, n), y + rng.normal(0, 1e-4, n), var, var, model
    )
    return fit, x, y


@pytest.mark.parametrize("order", [1, 3])
def test_extrapolation_flag_marks_positions_beyond_the_reference_stars(order):
    fit, xr, yr = _disc_fit(order=order)
    # probe points: the centre, half-way out, the disc's corners (inside its bounding
    # box but beyond every reference star) and outside the box
    px = np.array([0.0, 5.0, -3.0, 9.5, -9.5, 12.0, 0.0])
    py = np.array([0.0, 0.0, 4.0, 9.5, -9.5, 0.0, -11.0])
    x = np.concatenate([xr, px])
    y = np.concatenate([yr, py])
    tx, ty, _ = fit.model.position_covariance(fit.measurement_covariance, x, y)
    used = np.concatenate([fit.used, np.zeros(px.size, bool)])
    sub = type(fit)(**{**fit.__dict__, "used": used})
    flag = extrapolated(sub, x, y, tx, ty)
    assert not np.any(flag[: xr.size])  # no reference star is extrapolated
    assert list(flag[xr.size :]) == [False, False, False, True, True, True, True]


def test_best_measured_stars_are_not_flagged_and_stars_beyond_the_reference_area_are():
    truth = make_cluster(n=2500, seed=4, err_range=(3e-6, 3e-4))
    # the reference candidates (V <= 22) only inside |x|, |y| < 9 arcsec
    bright = truth.mag <= 22
    truth.x[bright] *= 9.0 / 14.0
    truth.y[bright] *= 9.0 / 14.0
    obs = observe(truth, [0.0, 10.0], [None, distortion_transform(seed=5, amplitude=3e-5)], seed=6)
    res = derive_proper_motions(obs, validate_settings({"order": 2, "ref_mag_max": 22.0}))
    s = res.stars
    f64 = np.asarray(s["flag"]) & PMFlag.EXTRAPOLATED > 0
    beyond = (np.abs(s["x"].value) > 9.2) | (np.abs(s["y"].value) > 9.2)
    inside = (np.abs(s["x"].value) < 8.0) & (np.abs(s["y"].value) < 8.0)
    assert np.all(f64[beyond])
    assert not np.any(f64[inside])
    assert not np.any(f64[s["mag"].value < 18])
