"""The fitter's model of stars' light outside their stamps (``halo``, ``deposit_radial``).

References: a direct (numpy) sum over the pixels for the compiled deposit; an analytic
radial profile injected into a synthetic frame for the measured halo; a frame without
any halo must give none.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mavispm.measure.stars.halo import halo_profile
from mavispm.measure.stars.stamp_kernel import deposit_radial


def _direct(pixels, shape, x, y, cx, cy, radius, flux, profile, r_in):
    ny, nx = shape
    row, col = pixels // nx, pixels % nx
    out = np.zeros(len(pixels))
    samples = r_in + np.arange(len(profile))
    for k in range(len(x)):
        r = np.hypot(col - x[k], row - y[k])
        own = (np.abs(col - cx[k]) <= radius) & (np.abs(row - cy[k]) <= radius)
        use = (r >= r_in) & (r < samples[-1]) & ~own
        out[use] += flux[k] * np.interp(r[use], samples, profile)
    return out


def test_deposit_radial_equals_the_direct_sum():
    rng = np.random.default_rng(3)
    shape = (120, 150)
    pixels = np.sort(rng.choice(shape[0] * shape[1], 6000, replace=False))
    x, y = rng.uniform(-5, 155, 12), rng.uniform(-5, 125, 12)
    cx, cy = np.rint(x).astype(int), np.rint(y).astype(int)
    flux = rng.uniform(1e3, 1e6, 12)
    profile = np.exp(-np.arange(40) / 9.0) * 1e-3
    got = deposit_radial(pixels, shape, x, y, cx, cy, 5, flux, profile, 5.5)
    want = _direct(pixels, shape, x, y, cx, cy, 5, flux, profile, 5.5)
    assert np.count_nonzero(want) > 1000
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def _halo(r):
    """Analytic halo [1/pixel per unit flux] between 12 and 40 px."""
    return np.where((r > 12) & (r < 40), 2e-5 * np.exp(-(r - 12) / 10.0), 0.0)


def _frame(with_halo, seed=0):
    rng = np.random.default_rng(seed)
    shape = (700, 700)
    sky, rn = 50.0, 5.0
    gx, gy = np.meshgrid(np.arange(80, 640, 110.0), np.arange(80, 640, 110.0))
    x = gx.ravel() + rng.uniform(-5, 5, gx.size)
    y = gy.ravel() + rng.uniform(-5, 5, gy.size)
    flux = 10 ** rng.uniform(6, 7, len(x))
    image = np.full(shape, sky)
    off = np.arange(-45, 46)
    for k in range(len(x)):
        cx, cy = int(x[k]), int(y[k])
        r = np.hypot(off[None, :] + cx - x[k], off[:, None] + cy - y[k])
        core = np.exp(-0.5 * (r / 1.2) ** 2) / (2 * np.pi * 1.2**2)
        image[cy - 45 : cy + 46, cx - 45 : cx + 46] += flux[k] * (
            core + (_halo(r) if with_halo else 0.0)
        )
    image = rng.poisson(image).astype(float) + rng.normal(0, rn, shape)
    return image, x, y, flux


def test_halo_profile_recovers_an_injected_halo_and_finds_none_without():
    radii = np.arange(12.5, 45.0)
    image, x, y, flux = _frame(True)
    got = halo_profile(image, None, x, y, flux, radii, n_stars=25)
    want = _halo(radii)
    strong = want > 4e-6
    assert strong.sum() >= 10
    np.testing.assert_allclose(got[strong], want[strong], rtol=0.15)
    image, x, y, flux = _frame(False)
    got = halo_profile(image, None, x, y, flux, radii, n_stars=25)
    assert np.all(got <= 2e-7)  # at most a stray 3-sigma value, 1 % of the halo's peak


@pytest.mark.parametrize("bad_fraction", [0.0, 0.1, 1.0])
def test_ring_medians_in_one_sort_equal_one_median_per_ring(bad_fraction):
    """The one-sort annulus medians equal numpy's ``nanmedian`` ring by ring, bit for bit,
    with masked (NaN) pixels and with a window where every pixel is masked."""
    from mavispm.measure.stars.halo import _ring_medians, _ring_medians_direct

    rng = np.random.default_rng(7)
    m = 70
    off = np.arange(-m, m + 1)
    radii = np.arange(5.5, 60.5)
    for _ in range(5):
        cut = rng.normal(0.0, 1.0, (2 * m + 1, 2 * m + 1)) + rng.integers(0, 3, (2 * m + 1,) * 2)
        cut[rng.random(cut.shape) < bad_fraction] = np.nan
        x0, y0 = rng.uniform(-0.5, 0.5, 2)
        r = np.hypot(off[None, :] - x0, off[:, None] - y0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            back, med = _ring_medians(cut, r, radii, 60.0, 70.0)
            ref_back, ref = _ring_medians_direct(cut, r, radii, 60.0, 70.0)
        np.testing.assert_array_equal(med, ref)
        np.testing.assert_array_equal(back, ref_back)
