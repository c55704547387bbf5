"""The halo past ``halo_radius`` (``FitOptions.halo_tail``): continued as a seeing halo and
added by FFT, against the truth of a rendered frame and a brute-force deposit
(docs/measure-scale.md, seventeenth pass)."""

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

_BINS = ((32.0, 44.0), (44.0, 58.0))
_SEEING, _CORE_RADIUS = 0.2, 15.0


def _seeing(r):
    """The seeing halo per unit flux [1/pixel]: ``(1 + (r / rc)^2)^(-11/6)`` (the
    Kolmogorov ``r^(-11/3)`` far out), normalised to ``_SEEING`` of the light."""
    return _SEEING * (1 + (r / _CORE_RADIUS) ** 2) ** (-11 / 6) / (1.2 * np.pi * _CORE_RADIUS**2)


def _frame(seed):
    """9 bright stars (200 px apart) whose light is the halo tests' core and exponential
    halo plus a seeing halo falling as ``r^(-11/3)`` (rendered out to 250 px), faint
    stars 32-56 px from each at random angles and others far from any; Poisson and read
    noise. Returns the image, the true positions and fluxes, each star's distance to its
    bright star (NaN: bright, inf: far), the sky and the read-noise variance."""
    rng = np.random.default_rng(seed)
    shape, sky, rn = (600, 600), 50.0, 5.0
    grid = np.arange(100.0, 600.0, 200.0)
    bx, by = jittered_grid(rng, grid)
    bflux = 10 ** rng.uniform(7.5, 7.8, bx.size)
    dist = np.arange(32.0, 57.0, 3.0)
    x, y, d = ring_scene(rng, bx, by, dist, np.arange(200.0, 500.0, 200.0))
    flux = np.concatenate([bflux, np.full(x.size - bx.size, 2000.0)])
    m = 60
    image = halo_test_image(shape, 0.0, x, y, flux * (1 - _SEEING), 8.0, margin=m)
    image = image[m:-m, m:-m] + sky
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    for k in range(bx.size):
        r = np.hypot(xx - bx[k], yy - by[k])
        image += bflux[k] * np.where(r < 250, _seeing(r), 0.0)
    image = rng.poisson(image).astype(float) + rng.normal(0, rn, shape)
    return image, x, y, flux, d, sky, rn**2


def _errors(tail, seed):
    """Per distance bin (``_BINS``) the faint stars' median |fitted / true flux - 1| (over
    the far stars' median ratio) and median position error [px] against the truth."""
    from mavispm.measure.stars import batched_fit

    image, x, y, flux, d, sky, rn2 = _frame(seed)
    opt = batched_fit.FitOptions(**HALO_FIT, halo_radius=30.0, halo_tail=tail)
    fit = batched_fit.fit_stars(
        image, halo_test_epsf(), x, y, read_noise_var=rn2, sky0=sky, options=opt
    )
    far, flux_off, pos_off = binned_halo_errors(fit, x, y, flux, d, _BINS)
    assert abs(far - (1 - _SEEING)) < 0.03  # the seeing halo lies outside the ePSF
    return flux_off, pos_off


@pytest.mark.parametrize("seed", [0, 1])
def test_halo_tail_models_the_seeing_halo_past_halo_radius(seed):
    """Bright stars with a seeing halo (``r^(-11/3)`` far out, the truth of the rendered
    frame) and a fitter whose halo profile stops at 30 px: without the tail faint stars
    32-44 / 44-58 px from them are off by a median 40-42 / 10-12 % in flux and 0.30-0.39
    / 0.14-0.15 px in position (measured), with it (``halo_tail`` 150 px) 10-11 / 7 % and
    0.25-0.26 / 0.14 px."""
    f_old, p_old = _errors(0.0, seed)
    f_new, p_new = _errors(150.0, seed)
    assert np.all(f_new < (0.35 * f_old[0], 0.8 * f_old[1])), (f_new, f_old)
    assert np.all(f_new < (0.15, 0.09)), f_new
    assert p_new[0] < 0.9 * p_old[0], (p_new, p_old)
    assert p_new[1] < p_old[1] + 0.005, (p_new, p_old)


@pytest.mark.parametrize("strip", [512, 64])
def test_deposit_tail_against_brute_force(strip, monkeypatch):
    """The FFT deposit (in one strip of rows or several) of a smooth profile that rises
    from zero at its first radius is each star's ``flux * profile(r)`` summed pixel by
    pixel (brute force), to 0.3 % rms (2 % at most, on its rise); the seam between a
    star's own deposit and the FFT's is a monotone ramp over ``TAIL_SEAM`` px."""
    from mavispm.measure.stars import halo
    from mavispm.measure.stars.halo import TAIL_SEAM, deposit_tail, halo_tail, tail_ramp

    monkeypatch.setattr(halo, "TAIL_STRIP", strip)
    rng = np.random.default_rng(1)
    ny, nx, r_in = 300, 340, 5.5
    x, y, f = rng.uniform(0, nx, 40), rng.uniform(0, ny, 40), rng.uniform(1, 10, 40)
    rr = r_in + np.arange(120)
    prof = np.exp(-rr / 30.0) * (0.5 - 0.5 * np.cos(np.pi * np.clip((rr - r_in) / 5, 0, 1)))
    pixels = np.sort(rng.choice(ny * nx, 30000, replace=False))
    got = np.zeros(len(pixels))
    deposit_tail(pixels, (ny, nx), x, y, f, prof, r_in, (got,))
    want = np.zeros(len(pixels))
    px, py = pixels % nx, pixels // nx
    for k in range(len(x)):
        r = np.hypot(px - x[k], py - y[k])
        want += f[k] * np.interp(r, rr, prof, left=0.0, right=0.0)
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.003 * np.mean(want)
    assert np.max(np.abs(got - want)) < 0.02 * np.max(want)  # the rise, blurred by a pixel
    # the seam: each star's share and the FFT's add up to the whole
    measured = 1e-3 * np.exp(-rr[:55] / 12.0) - 1e-3 * np.exp(-65 / 12.0)
    full = halo_tail(measured, r_in, 150.0)
    seam = tail_ramp(r_in + np.arange(len(full)), rr[54])
    assert seam[0] == 0 and np.all(seam[54:] == 1) and np.all(np.diff(seam) >= 0)
    assert np.all(seam[: 54 - int(TAIL_SEAM)] == 0)


def test_halo_tail_continues_a_power_law_halo():
    """A halo ``A r^(-11/3)`` measured against the median of the annulus [60, 70) px (the
    brute-force median of its pixels) is returned whole: raised inside, the power law
    beyond out to the outer half's fade (analytic)."""
    from mavispm.measure.stars.halo import halo_tail

    amp, r_in, edge = 50.0, 5.5, 60.0
    off = np.arange(-80, 81) + 0.3
    r = np.hypot(off[None, :], off[:, None])
    floor = np.median(amp * r[(r >= edge) & (r < edge + 10)] ** (-11 / 3))
    radii = np.arange(r_in, edge, 1.0)
    measured = amp * radii ** (-11 / 3) - floor
    full = halo_tail(measured, r_in, 200.0)
    rr = np.arange(r_in, 200.0, 1.0)
    law = amp * rr ** (-11 / 3)
    assert len(full) == len(rr)
    np.testing.assert_allclose(full[:40], law[:40], rtol=2e-3)
    np.testing.assert_allclose(full[55:125], law[55:125], rtol=2e-3)
    assert np.all(np.diff(full[55:]) <= 0) and full[-1] < 1e-3 * law[-1]


def test_star_deposit_and_fft_deposit_add_up_to_the_profile():
    """Each star's own deposit of the profile faded over the seam plus the FFT deposit of
    the profile faded in is the profile at every radius outside the star's stamp (brute
    force, pixel by pixel), to 0.3 % rms."""
    from mavispm.measure.stars.halo import deposit_tail, tail_ramp
    from mavispm.measure.stars.stamp_kernel import deposit_radial

    rng = np.random.default_rng(2)
    ny, nx, r_in, n_in = 300, 340, 5.5, 55
    x, y, f = rng.uniform(0, nx, 40), rng.uniform(0, ny, 40), rng.uniform(1, 10, 40)
    rr = r_in + np.arange(120)
    prof = np.exp(-rr / 30.0)
    pixels = np.sort(rng.choice(ny * nx, 30000, replace=False))
    cx, cy = np.rint(x).astype(int), np.rint(y).astype(int)
    seam = tail_ramp(rr, rr[n_in - 1])
    got = np.zeros(len(pixels))
    deposit_tail(pixels, (ny, nx), x, y, f, prof * seam, r_in, (got,))
    deposit_radial(pixels, (ny, nx), x, y, cx, cy, 5, f, (prof * (1 - seam))[:n_in], r_in, out=got)
    want = np.zeros(len(pixels))
    px, py = pixels % nx, pixels // nx
    for k in range(len(x)):
        r = np.hypot(px - x[k], py - y[k])
        own = (np.abs(px - cx[k]) <= 5) & (np.abs(py - cy[k]) <= 5)
        use = (r >= r_in) & (r < rr[-1]) & ~own
        want += f[k] * np.where(use, np.interp(r, rr, prof), 0.0)
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.003 * np.mean(want)
