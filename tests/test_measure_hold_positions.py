"""Forced photometry of chosen stars (``fit_stars(hold_positions=...)``): their positions
stay at their start, their fluxes are fitted with their neighbours' light in the model.
The oracle benchmark of the 1e5-star frame holds the V > 25 stars at their input
positions with it (``benchmarks/bench_scale_oracles.py``; docs/measure-scale.md,
thirty-first pass). Against the rendered truth."""

from __future__ import annotations

import measure_helpers as mh
import numpy as np
import pytest

from mavispm.core.errors import InputError
from mavispm.measure.stars.batched_fit import (
    FLAG_FAILED,
    FLAG_NOT_CONVERGED,
    FitOptions,
    fit_stars,
)

SHAPE = (200, 200)


def _scene(hold, offset=0.3):
    """Bright stars, each with a star 3 mag fainter 2.5 px away; the faint ones start
    ``offset`` px off their truth, the bright ones at it."""
    rng = np.random.default_rng(11)
    psf, det = mh.SynthPSF(1.2, profile="moffat"), mh.Detector()
    bx, by = mh.grid_positions(SHAPE, 24, 12, rng)
    angle = rng.uniform(0, 2 * np.pi, len(bx))
    fx, fy = bx + 2.5 * np.cos(angle), by + 2.5 * np.sin(angle)
    x, y = np.concatenate([bx, fx]), np.concatenate([by, fy])
    flux = np.concatenate([np.full(len(bx), 2e5), np.full(len(bx), 2e5 / 10**1.2)])
    image, sat = mh.noisy_frame(mh.render_image(SHAPE, x, y, flux, psf), det, rng)
    faint = np.arange(len(x)) >= len(bx)
    turn = rng.uniform(0, 2 * np.pi, len(x))
    x0 = np.where(faint, x + offset * np.cos(turn), x)
    y0 = np.where(faint, y + offset * np.sin(turn), y)
    res = mh.fit_noisy_frame(
        image, sat, det, mh.true_epsf(psf, SHAPE), x0, y0,
        options=FitOptions(wing_threshold=0.0), hold_positions=faint if hold else None,
    )  # fmt: skip
    return res, x, y, x0, y0, flux, faint


def test_held_stars_stay_at_their_start_and_their_flux_is_fitted():
    res, x, y, x0, y0, flux, faint = _scene(hold=True)
    # held: exactly at the start (0.3 px off the truth), no position error, converged
    np.testing.assert_array_equal(res.x[faint], x0[faint])
    np.testing.assert_array_equal(res.y[faint], y0[faint])
    assert np.all(np.isnan(res.x_err[faint])) and np.all(np.isnan(res.y_err[faint]))
    assert np.all(res.flag[faint] & (FLAG_NOT_CONVERGED | FLAG_FAILED) == 0)
    # the bright neighbours are fitted freely; the misplaced faint light biases them
    # (measured ~0.012 px, ~3.6 of their errors), within 0.05 px
    bright = ~faint
    d = np.hypot(res.x[bright] - x[bright], res.y[bright] - y[bright])
    assert np.all(d < 0.05), np.sort(d)[-3:]


def test_stars_held_at_their_true_positions_get_their_flux_within_its_errors():
    res, x, y, x0, y0, flux, faint = _scene(hold=True, offset=0.0)
    np.testing.assert_array_equal(res.x[faint], x[faint])
    assert np.all(res.flag[faint] & (FLAG_NOT_CONVERGED | FLAG_FAILED) == 0)
    pull = (res.flux[faint] - flux[faint]) / res.flux_err[faint]
    assert abs(np.median(pull)) < 0.5, np.median(pull)
    assert 0.7 < 1.4826 * np.median(np.abs(pull - np.median(pull))) < 1.4
    # with their neighbours' light where it is, the bright stars land within their errors
    bright = ~faint
    d = np.hypot(res.x[bright] - x[bright], res.y[bright] - y[bright])
    err = np.hypot(res.x_err[bright], res.y_err[bright])
    assert np.median(d / err) < 2.0, np.median(d / err)


def test_without_the_hold_the_same_stars_move_to_their_truth():
    """The control arm: the stars the hold keeps 0.3 px off are found by the free fit."""
    res, x, y, x0, y0, flux, faint = _scene(hold=False)
    ok = faint & (res.flag & FLAG_FAILED == 0)
    assert ok.sum() >= 0.9 * faint.sum()
    d = np.hypot(res.x[ok] - x[ok], res.y[ok] - y[ok])
    assert np.median(d) < 0.1, np.median(d)
    assert np.all(np.isfinite(res.x_err[ok]))


def test_hold_positions_of_the_wrong_length_is_refused():
    psf = mh.SynthPSF(1.2)
    with pytest.raises(InputError, match="hold_positions"):
        fit_stars(
            np.zeros(SHAPE),
            mh.true_epsf(psf, SHAPE),
            np.array([50.0, 60.0]),
            np.array([50.0, 60.0]),
            read_noise_var=1.0,
            sky0=0.0,
            hold_positions=np.array([True]),
        )


def test_the_photutils_engine_refuses_held_positions():
    """Only the fast engine holds positions; the photutils engine says so in one line."""
    from mavispm.core.frame import Frame
    from mavispm.measure.stars.cli import validate_settings
    from mavispm.measure.stars.measure_frame import run_engine

    psf = mh.SynthPSF(1.2)
    frame = Frame(
        image=np.zeros(SHAPE),
        saturated=np.zeros(SHAPE, bool),
        sky=0.0,
        read_noise_var=1.0,
        pixel_scale=0.00736,
    )
    with pytest.raises(InputError, match="hold_positions needs engine 'fast'"):
        run_engine(
            frame,
            mh.true_epsf(psf, SHAPE),
            np.array([50.0]),
            np.array([50.0]),
            validate_settings({"engine": "photutils"}),
            hold_positions=np.array([True]),
        )
