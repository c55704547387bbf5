"""The bright stars' common non-round light (``FitOptions.halo_stack``): a 2-D median of
their residuals, stacked in their own frames, added to each bright star's model, against
the truth of a rendered frame (docs/measure-scale.md, sixteenth pass)."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import (
    HALO_FIT,
    binned_halo_errors,
    halo_test_epsf,
    halo_test_image,
    jittered_grid,
    ring_scene,
)

_BINS = ((11.0, 15.0), (15.0, 21.0))


def _frame(seed, lobes):
    """16 bright stars whose halos carry the same square pattern (``1 + lobes cos(4
    theta)``, as an AO PSF's control-radius structure; the fitter's ePSF and radial halo
    model are round), faint stars 8-26 px from each at random angles and others far from
    any; Poisson and read noise. Returns the image, the true positions and fluxes, each
    star's distance to its bright star (NaN: bright, inf: far), the sky and the
    read-noise variance."""
    rng = np.random.default_rng(seed)
    shape, sky, rn = (600, 600), 50.0, 5.0
    grid = np.arange(75.0, 600.0, 150.0)
    bx, by = jittered_grid(rng, grid)
    bflux = 10 ** rng.uniform(6.3, 6.7, bx.size)
    dist = np.array([8.0, 9.5, 11.0, 12.5, 14.0, 16.0, 18.0, 20.0, 23.0, 26.0])
    x, y, d = ring_scene(rng, bx, by, dist, np.arange(150.0, 500.0, 150.0))
    flux = np.concatenate([bflux, np.full(x.size - bx.size, 4000.0)])
    m = 60
    image = halo_test_image(
        shape, sky, x, y, flux, 8.0, margin=m, lobes=np.where(np.isnan(d), lobes, 0.0)
    )
    image = rng.poisson(image[m:-m, m:-m]).astype(float) + rng.normal(0, rn, shape)
    return image, x, y, flux, d, sky, rn**2


def _errors(stack, seed, lobes):
    """Per distance bin (``_BINS``) the faint stars' median |fitted / true flux - 1| (over
    the far stars' median ratio) and median position error [px] against the truth."""
    from mavispm.measure.stars import batched_fit

    image, x, y, flux, d, sky, rn2 = _frame(seed, lobes)
    opt = batched_fit.FitOptions(**HALO_FIT, halo_radius=40.0, halo_rings=5.0,
                                 halo_stack=stack)  # fmt: skip
    fit = batched_fit.fit_stars(
        image, halo_test_epsf(), x, y, read_noise_var=rn2, sky0=sky, options=opt
    )
    far, flux_off, pos_off = binned_halo_errors(fit, x, y, flux, d, _BINS)
    assert 0.95 < far < 1.05
    return flux_off, pos_off


@pytest.mark.parametrize("seed", [0, 1])
def test_stacked_residual_takes_the_common_structure(seed):
    """Bright stars whose halos carry a common square pattern of +-60 % (the truth of the
    rendered frame): without the stack faint stars 11-21 px from them are off by a median
    59-64 % / 20-23 % in flux and 0.68-0.74 / 0.20-0.25 px in position at 11-15 / 15-21
    px (measured); with the stacked residual (``halo_stack`` 30 px) 17-20 % / 6 % and
    0.27-0.40 / 0.13-0.17 px. With round halos (nothing common to take) the stack's
    noise leaves them within 1.5 points in flux and 0.01 px in position of the fit
    without it (measured -0.7 to +0.7 points, -0.012 to +0.006 px)."""
    f_old, p_old = _errors(0.0, seed, 0.6)
    f_new, p_new = _errors(30.0, seed, 0.6)
    assert np.all(f_new < 0.5 * f_old), (f_new, f_old)
    assert np.all(f_new < (0.25, 0.10)), f_new
    assert np.all(p_new < 0.75 * p_old), (p_new, p_old)
    f_old, p_old = _errors(0.0, seed, 0.0)
    f_new, p_new = _errors(30.0, seed, 0.0)
    assert np.all(f_new < f_old + 0.015), (f_new, f_old)
    assert np.all(p_new < p_old + 0.01), (p_new, p_old)


def test_stacked_residual_is_the_common_non_round_light():
    """Stars whose light is ``F (A(dx, dy) + g_k(r))`` (a common pattern ``A`` and a radial
    profile of their own, constant in each 1-px annulus) on every pixel: the map is ``A`` less its mean in each 1-px
    annulus, outside the stamp and within the reach (brute force, pixel by pixel), and
    its deposit puts ``F`` times it around each star."""
    from mavispm.measure.stars.halo import deposit_stacked, stacked_residual

    rng = np.random.default_rng(3)
    ny, nx, half, reach = 120, 160, 2, 9
    off = np.arange(-reach, reach + 1)
    pattern = rng.normal(0.0, 1.0, (2 * reach + 1,) * 2)
    cx, cy = np.array([20, 60, 100, 140, 40, 120]), np.array([20, 30, 25, 40, 90, 95])
    flux = rng.uniform(1.0, 5.0, cx.size)
    values = np.zeros((ny, nx))
    for k in range(cx.size):
        ring = np.rint(np.hypot(off[None, :], off[:, None]))  # radial: one value per annulus
        own = rng.uniform(0.5, 2.0) * np.exp(-ring / rng.uniform(2.0, 6.0))
        window = values[cy[k] - reach : cy[k] + reach + 1, cx[k] - reach : cx[k] + reach + 1]
        window += flux[k] * (pattern + own)
    pixels = np.arange(ny * nx)
    bad = np.zeros(ny * nx, bool)
    got = stacked_residual(
        pixels, (ny, nx), values.ravel(), np.zeros(ny * nx), bad, cx, cy, flux, half, reach
    )
    want = np.zeros_like(pattern)
    for ring in range(int(np.ceil(reach * np.sqrt(2))) + 1):
        cells = [
            (i, j)
            for i in range(2 * reach + 1)
            for j in range(2 * reach + 1)
            if round(np.hypot(i - reach, j - reach)) == ring
            and np.hypot(i - reach, j - reach) <= reach
            and max(abs(i - reach), abs(j - reach)) > half
        ]
        if cells:
            mean = np.mean([pattern[c] for c in cells])
            for c in cells:
                want[c] = pattern[c] - mean
    np.testing.assert_allclose(got, want, atol=1e-12)
    out = np.zeros(ny * nx)
    deposit_stacked(pixels, (ny, nx), cx[:1], cy[:1], flux[:1], got, (out,))
    image = out.reshape(ny, nx)
    box = image[cy[0] - reach : cy[0] + reach + 1, cx[0] - reach : cx[0] + reach + 1]
    np.testing.assert_allclose(box, flux[0] * want, atol=1e-12)
    assert np.sum(np.abs(image)) == pytest.approx(np.sum(np.abs(box)))
