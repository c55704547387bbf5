"""Crowding: neighbours at 2.5-10 px cost little accuracy; close pairs never diverge."""

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

from mavispm.measure.stars.batched_fit import crowding_flags, fit_stars
from mavispm.measure.stars.crlb import crlb

SHAPE = (300, 300)
PSF = SynthPSF(1.0)
DET = Detector()
RN2 = DET.read_noise**2 * DET.nexp


def _pairs(rng, sep_lo, sep_hi, ratio_lo, ratio_hi):
    x, y = grid_positions(SHAPE, 30, 15, rng, jitter=0.5)
    mag = rng.uniform(18, 22, len(x))
    sep = rng.uniform(sep_lo, sep_hi, len(x))
    ang = rng.uniform(0, 2 * np.pi, len(x))
    ratio = np.exp(rng.uniform(np.log(ratio_lo), np.log(ratio_hi), len(x)))
    x2, y2 = x + sep * np.cos(ang), y + sep * np.sin(ang)
    mag2 = mag - 2.5 * np.log10(ratio)
    return x, y, mag, x2, y2, mag2


def _fit(xs, ys, mags, seed):
    flux = mag_to_flux(mags)
    image, sat = noisy_frame(
        render_image(SHAPE, xs, ys, flux, PSF), DET, np.random.default_rng(seed)
    )
    return fit_stars(
        image * DET.gain,
        true_epsf(PSF, SHAPE),
        xs,
        ys,
        read_noise_var=RN2,
        sky0=DET.sky,
        saturated=sat,
    )


def test_neighbours_cost_less_than_20_percent():
    rng = np.random.default_rng(3)
    x, y, mag, x2, y2, mag2 = _pairs(rng, 2.5, 10.0, 0.1, 2.0)
    n = len(x)
    bound = crlb(true_epsf(PSF, SHAPE), x, y, mag_to_flux(mag), DET.sky, RN2)
    crowded, isolated = [], []
    for seed in range(8):
        both = _fit(np.r_[x, x2], np.r_[y, y2], np.r_[mag, mag2], seed)
        alone = _fit(x, y, mag, seed)
        crowded.append(np.r_[(both.x[:n] - x) / bound[:, 0], (both.y[:n] - y) / bound[:, 1]])
        isolated.append(np.r_[(alone.x - x) / bound[:, 0], (alone.y - y) / bound[:, 1]])
    ratio = robust_sigma(np.concatenate(crowded)) / robust_sigma(np.concatenate(isolated))
    assert ratio <= 1.2


def test_close_pairs_do_not_diverge():
    rng = np.random.default_rng(4)
    x, y, mag, x2, y2, mag2 = _pairs(rng, 0.0, 2.5, 0.1, 1.0)
    res = _fit(np.r_[x, x2], np.r_[y, y2], np.r_[mag, mag2], 0)
    n = len(x)
    assert np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.y))
    assert np.all(np.isfinite(res.flux))
    # the brighter star of each pair stays where it is (within 0.5 pixel)
    assert np.all(np.hypot(res.x[:n] - x, res.y[:n] - y) < 0.5)
    # no star walks further than the allowed shift
    assert np.all(np.hypot(res.x - np.r_[x, x2], res.y - np.r_[y, y2]) <= 2.0 + 1e-9)
    # total flux of each pair is recovered within 5 %
    total = np.nan_to_num(res.flux[:n]) + np.nan_to_num(res.flux[n:])
    np.testing.assert_allclose(total, mag_to_flux(mag) + mag_to_flux(mag2), rtol=0.05)


def test_crowding_flags():
    x = np.array([0.0, 5.0, 50.0, 53.0])
    y = np.zeros(4)
    flux = np.array([100.0, 5.0, 100.0, 50.0])
    got = crowding_flags(x, y, flux, radius=10.0, ratio=0.1)
    # star 0's neighbour is only 5 % as bright; star 1's neighbour is 20x brighter
    assert got.tolist() == [False, True, True, True]


@pytest.mark.parametrize("n", [0, 1])
def test_crowding_flags_tiny_lists(n):
    assert crowding_flags(np.zeros(n), np.zeros(n), np.ones(n), 10.0, 0.1).tolist() == [False] * n
