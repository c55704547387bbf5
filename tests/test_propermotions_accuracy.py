"""Accuracy of matching, alignment and proper motions against injected truth."""

from __future__ import annotations

import numpy as np
import pytest
from propermotions_helpers import distortion_transform, make_cluster, observe
from scipy import stats

from mavispm.measure.propermotions.alignment import TransformModel, fit_transform
from mavispm.measure.propermotions.motion_fit import fit_linear_motion
from mavispm.measure.propermotions.pipeline import PMFlag, derive_proper_motions
from mavispm.measure.propermotions.settings import validate_settings


def _normalised(stars):
    zx = ((stars["pm_x"] - stars["pm_x_true"]) / stars["pm_x_err"]).value
    zy = ((stars["pm_y"] - stars["pm_y_true"]) / stars["pm_y_err"]).value
    return np.concatenate([zx, zy])


@pytest.mark.parametrize("epochs", [(0.0, 10.0), (0.0, 2.0, 5.0, 7.5, 10.0)])
def test_unbiased_and_calibrated_with_dynamic_distortion(epochs):
    truth = make_cluster(n=4000, seed=11, n_fast=15)
    transforms = [None] + [distortion_transform(seed=20 + k) for k in range(1, len(epochs))]
    obs = observe(truth, epochs, transforms, seed=12)
    res = derive_proper_motions(obs, validate_settings({"order": 2}))
    z = _normalised(res.stars)
    assert np.all(np.isfinite(z))
    assert abs(np.mean(z)) < 0.05
    assert abs(np.std(z) - 1.0) < 0.1
    # the injected high-velocity stars are clipped from the reference set
    fast = np.isin(res.stars["id"], truth.ids[:15])
    assert np.all(res.stars["flag"][fast] & PMFlag.CLIPPED)
    assert np.mean(res.stars["flag"][~fast] & PMFlag.CLIPPED > 0) < 0.01


def _true_params(fit, transform, shift):
    """The injected transformation (plus the absorbed systemic shift) in the fit's basis."""
    g = np.linspace(-14, 14, 11)
    gx, gy = (a.ravel() for a in np.meshgrid(g, g))
    xx, yy = transform.apply(gx, gy)
    b = np.concatenate([xx - shift[0], yy - shift[1]])
    p, *_ = np.linalg.lstsq(fit.model.design(gx, gy), b, rcond=None)
    return p


@pytest.mark.parametrize("match", ["id", "position"])
def test_fitted_transform_matches_injected_within_errors(match):
    chi2 = []
    for seed in range(4):
        truth = make_cluster(n=2500, seed=seed)
        tr = distortion_transform(seed=50 + seed)
        obs = observe(truth, [0.0, 10.0], [None, tr], seed=100 + seed)
        res = derive_proper_motions(obs, validate_settings({"order": 2, "match": match}))
        fit = res.fits[1]
        assert res.match.method == match
        shift = (np.array([0.3, -0.2]) * 1e-3) * 10.0  # systemic PM x baseline [arcsec]
        d = fit.params - _true_params(fit, tr, shift)
        chi2.append(d @ np.linalg.solve(fit.covariance, d))
    n_par = TransformModel(order=2).n_params
    # the sum of 4 chi-square(12) variables: chi-square(48)
    assert stats.chi2.sf(np.sum(chi2), 4 * n_par) > 1e-3
    assert stats.chi2.cdf(np.sum(chi2), 4 * n_par) > 1e-3


def test_conformal_transform_recovers_scale_and_rotation():
    truth = make_cluster(n=1500, seed=5, sigma_pm=0.05)
    tr = distortion_transform(seed=3, amplitude=0.0)
    obs = observe(truth, [0.0, 10.0], [None, tr], seed=6)
    res = derive_proper_motions(obs, validate_settings({"order": 1, "conformal": True}))
    fit = res.fits[1]
    length = fit.model.length
    scale = np.hypot(fit.params[2], fit.params[3]) / length - 1
    rot = np.arctan2(fit.params[3], fit.params[2])
    err = fit.param_errors[2:] / length
    assert abs(scale - tr.scale) < 5 * err[0]
    assert abs(rot - tr.rotation) < 5 * err[1]
    assert abs(np.mean(_normalised(res.stars))) < 0.1


def _analytic_sigma(sigma, t):
    return sigma / np.sqrt(np.sum((t - t.mean()) ** 2))


@pytest.mark.parametrize("epochs", [(0.0, 10.0), (0.0, 1.0, 3.0, 7.0, 10.0)])
def test_errors_match_analytic_least_squares_variance(epochs):
    t = np.asarray(epochs)
    sigma = 100e-6  # arcsec, the same for every star and epoch
    truth = make_cluster(n=3000, seed=8, err_range=(sigma, sigma))
    obs = observe(truth, epochs, None, seed=9)
    res = derive_proper_motions(obs, validate_settings({"order": 1}))
    expected = _analytic_sigma(sigma, t) * 1e3  # mas/yr
    if len(t) == 2:
        assert expected == pytest.approx(np.sqrt(2) * sigma * 1e3 / 10.0)
    err = res.stars["pm_x_err"].value
    # reported = analytic + the (small) transformation term
    assert np.all(err >= expected * (1 - 1e-9))
    assert np.median(err) == pytest.approx(expected, rel=0.01)
    resid = np.concatenate(
        [
            (res.stars["pm_x"] - res.stars["pm_x_true"]).value,
            (res.stars["pm_y"] - res.stars["pm_y_true"]).value,
        ]
    )
    # empirical scatter agrees with the analytic variance (std error ~ 1/sqrt(2 n))
    assert np.std(resid) / expected == pytest.approx(1.0, abs=0.05)


def test_linear_motion_matches_brute_force_weighted_fit():
    rng = np.random.default_rng(4)
    n, n_ep = 50, 6
    t = np.sort(rng.uniform(0, 12, n_ep))
    x = rng.normal(0, 1, (n, n_ep))
    y = rng.normal(0, 1, (n, n_ep))
    vx = rng.uniform(0.5, 2, (n, n_ep))
    vy = rng.uniform(0.5, 2, (n, n_ep))
    valid = rng.uniform(size=(n, n_ep)) > 0.3
    valid[:, :2] = True
    lm = fit_linear_motion(t, x, y, vx, vy, np.zeros_like(vx), valid, t_ref=t[0])
    for i in range(n):
        v = valid[i]
        a = np.column_stack([np.ones(v.sum()), t[v] - t[0]])
        w = 1 / vx[i, v]
        cov = np.linalg.inv(a.T @ (a * w[:, None]))
        p = cov @ (a.T @ (w * x[i, v]))
        assert lm.pm_x[i] == pytest.approx(p[1])
        assert lm.x0[i] == pytest.approx(p[0])
        assert lm.var_pm_x[i] == pytest.approx(cov[1, 1])
    two = fit_linear_motion(
        t[:2],
        x[:, :2],
        y[:, :2],
        vx[:, :2],
        vy[:, :2],
        0 * vx[:, :2],
        np.ones((n, 2), bool),
        t_ref=t[0],
    )
    np.testing.assert_allclose(two.pm_x, (x[:, 1] - x[:, 0]) / (t[1] - t[0]))
    np.testing.assert_allclose(two.var_pm_x, (vx[:, 0] + vx[:, 1]) / (t[1] - t[0]) ** 2)


def test_clipping_rejects_injected_outliers_and_jitter_matches_dispersion():
    rng = np.random.default_rng(3)
    n = 2000
    x, y = rng.uniform(-10, 10, (2, n))
    s = 0.002  # intrinsic scatter of displacements [arcsec]
    err = np.full(n, 1e-4)
    xr = x + rng.normal(0, s, n) + rng.normal(0, 1e-4, n)
    yr = y + rng.normal(0, s, n) + rng.normal(0, 1e-4, n)
    xr[:20] += 0.05  # high-velocity stars
    fit = fit_transform(x, y, xr, yr, err**2, err**2, TransformModel(order=1, length=10.0))
    assert not np.any(fit.used[:20])
    assert np.mean(fit.used[20:]) > 0.99
    assert fit.jitter == pytest.approx(s, rel=0.05)


def test_too_low_order_is_reported():
    truth = make_cluster(n=2000, seed=31)
    obs = observe(truth, [0.0, 10.0], [None, distortion_transform(seed=4)], seed=32)
    low = derive_proper_motions(obs, validate_settings({"order": 1}))
    assert any("order 2 fits significantly better" in n for n in low.notes)
    # the unmodelled distortion shows up as miscalibrated errors ...
    assert np.std(_normalised(low.stars)) > 1.5
    good = derive_proper_motions(obs, validate_settings({"order": 2}))
    assert not any("fits significantly better" in n for n in good.notes)


def test_position_matching_identifies_the_right_stars():
    truth = make_cluster(n=1500, seed=41)
    obs = observe(truth, [0.0, 5.0, 10.0], [None, *(distortion_transform(k) for k in (1, 2))])
    by_pos = derive_proper_motions(obs, validate_settings({"order": 2, "match": "position"}))
    match = by_pos.match
    assert match.method == "position"
    for k in (1, 2):
        rows = match.index[:, k]
        found = rows >= 0
        assert np.mean(found) > 0.9
        right = obs[k].ids[rows[found]] == match.ids[found]
        assert np.all(right[~match.ambiguous[found]])  # unambiguous matches are all correct
        assert match.n_unmatched[k] == obs[k].ids.size - np.count_nonzero(found)
    # both matchings give calibrated motions (each against the truth in its own frame)
    by_id = derive_proper_motions(obs, validate_settings({"order": 2, "match": "id"}))
    for res in (by_id, by_pos):
        z = _normalised(res.stars)
        assert abs(np.mean(z)) < 0.05 and abs(np.std(z) - 1) < 0.1


def test_choice_of_reference_epoch_does_not_change_motions():
    truth = make_cluster(n=2000, seed=42)
    trans = [None, distortion_transform(7), distortion_transform(8)]
    obs = observe(truth, [0.0, 4.0, 10.0], trans, seed=43)
    first = derive_proper_motions(obs, validate_settings({"order": 2}))
    last = derive_proper_motions(obs, validate_settings({"order": 2, "reference": -1}))
    assert last.reference_epoch == 10.0 and last.fits[2] is None
    d = (first.stars["pm_x"] - last.stars["pm_x"]) / first.stars["pm_x_err"]
    # both frames are the cluster's mean motion; they differ by the frame noise only
    assert np.std(d.value) < 0.3
    assert abs(np.mean(_normalised(last.stars))) < 0.05
    assert abs(np.std(_normalised(last.stars)) - 1) < 0.1


@pytest.mark.parametrize(("order", "conformal"), [(1, True), (1, False), (2, False), (3, False)])
def test_alignment_solver_matches_numpy_lstsq(order, conformal):
    rng = np.random.default_rng(order)
    n = 400
    x, y = rng.uniform(-12, 12, (2, n))
    tr = distortion_transform(seed=order, amplitude=0.0 if conformal else 1e-3, order=max(order, 2))
    xr, yr = tr.apply(x, y)
    vx, vy = rng.uniform(1e-9, 4e-8, (2, n))
    xr = xr + rng.normal(0, np.sqrt(vx))
    yr = yr + rng.normal(0, np.sqrt(vy))
    model = TransformModel(order=order, conformal=conformal, length=12.0)
    fit = fit_transform(x, y, xr, yr, vx, vy, model)
    idx = np.flatnonzero(fit.used)
    w = np.sqrt(np.concatenate([fit.weights[idx, 0], fit.weights[idx, 1]]))
    a = model.design(x[idx], y[idx]) * w[:, None]
    b = np.concatenate([xr[idx], yr[idx]]) * w
    ref, *_ = np.linalg.lstsq(a, b, rcond=None)
    np.testing.assert_allclose(fit.params, ref, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(fit.covariance, np.linalg.inv(a.T @ a), rtol=1e-6, atol=1e-20)


@pytest.mark.parametrize(("order", "conformal"), [(1, True), (2, False), (3, False)])
def test_analytic_jacobian_matches_finite_differences(order, conformal):
    model = TransformModel(order=order, conformal=conformal, length=10.0)
    params = np.random.default_rng(order).normal(0, 1, model.n_params)
    x, y = np.random.default_rng(9).uniform(-10, 10, (2, 50))
    jac = model.jacobian(params, x, y)
    h = 1e-5
    for col, (ex, ey) in enumerate([(h, 0.0), (0.0, h)]):
        xp, yp = model.apply(params, x + ex, y + ey)
        xm, ym = model.apply(params, x - ex, y - ey)
        np.testing.assert_allclose(jac[:, 0, col], (xp - xm) / (2 * h), rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(jac[:, 1, col], (yp - ym) / (2 * h), rtol=1e-6, atol=1e-9)
