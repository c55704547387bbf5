"""Honest position errors near bright stars: the bright stars' mis-modelled light (here
PSF-scale speckles in their halos, absent from the model) is a correlated residual
field, and the errors must hold it (``FitResult.correlated_gain``, ``halo_share``;
docs/measure-scale.md, fourteenth pass). The truth of the rendered frame scores."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import HALO_FIT, halo_light, halo_test_core, halo_test_epsf, halo_test_image

_SCALE = 8.0  # halo scale [px]


def _halo_light(r):
    return halo_light(r, _SCALE)


def _frame(seed, speckle=0.25):
    """25 bright stars with round halos plus PSF-scale speckles (each bright star's 200
    speckles at 6-40 px carry ``speckle`` times its halo light there, with random
    signs), 12 faint stars 9-30 px from each (300) and 400 more >= 64 px from any (the
    majority, as on a real frame: they set the typical chi^2); Poisson and read noise. Returns the image, the true positions, whether each is a faint star near a
    bright one / far, the sky and the read-noise variance."""
    rng = np.random.default_rng(seed)
    shape, sky, rn = (750, 750), 50.0, 5.0
    grid = np.arange(75.0, 750.0, 150.0)
    bx, by = (a.ravel() + rng.uniform(-3, 3, a.size) for a in np.meshgrid(grid, grid))
    bflux = 10 ** rng.uniform(6.3, 6.7, bx.size)
    nx_, ny_ = [], []
    for k in range(bx.size):
        d = rng.uniform(9.0, 30.0, 8)
        a = np.arange(8) * 2 * np.pi / 8 + rng.uniform(0, 2 * np.pi)
        nx_.append(bx[k] + d * np.cos(a))
        ny_.append(by[k] + d * np.sin(a))
    mid = np.arange(150.0, 700.0, 150.0)
    cx_, cy_ = (np.repeat(a.ravel(), 40) for a in np.meshgrid(mid, mid))
    fx, fy = cx_ + rng.uniform(-30, 30, cx_.size), cy_ + rng.uniform(-30, 30, cy_.size)
    x = np.concatenate([bx, *nx_, fx])
    y = np.concatenate([by, *ny_, fy])
    near = np.zeros(x.size, bool)
    near[bx.size : bx.size + 8 * bx.size] = True
    far = np.zeros(x.size, bool)
    far[-fx.size :] = True
    flux = np.concatenate([bflux, np.full(x.size - bx.size, 6000.0)])
    m = 60
    image = halo_test_image(shape, sky, x, y, flux, _SCALE, margin=m)
    w = 4
    sub = np.arange(-w, w + 1)
    for k in range(bx.size):  # speckles: PSF-core blobs in the halo, not in the model
        r = rng.uniform(6.0, 40.0, 200)
        a = rng.uniform(0, 2 * np.pi, 200)
        sx, sy = bx[k] + r * np.cos(a), by[k] + r * np.sin(a)
        # light per speckle: the halo's light over the annulus element it stands for
        amp = speckle * bflux[k] * _halo_light(r) * (2 * np.pi * r * 34.0 / 200)
        amp *= rng.choice([-1.0, 1.0], 200)
        for s in range(200):
            cx, cy = int(round(sx[s])) + m, int(round(sy[s])) + m
            dx, dy = sub[None, :] + cx - m - sx[s], sub[:, None] + cy - m - sy[s]
            image[cy - w : cy + w + 1, cx - w : cx + w + 1] += amp[s] * halo_test_core(dx, dy)
    image = rng.poisson(np.maximum(image[m:-m, m:-m], 0)).astype(float)
    image += rng.normal(0, rn, shape)
    return image, x, y, near, far, sky, rn**2


def _normalised(seed, correlated):
    """Robust std of (fitted - true) / error, pooled x and y, near and far."""
    from mavispm.measure.stars import batched_fit
    from mavispm.measure.stars.error_model import estimate_error_model

    image, x, y, near, far, sky, rn2 = _frame(seed)
    opt = batched_fit.FitOptions(**HALO_FIT, halo_radius=40.0, halo_rings=5.0)
    fit = batched_fit.fit_stars(
        image, halo_test_epsf(scale=_SCALE), x, y, read_noise_var=rn2, sky0=sky, options=opt
    )
    usable = (fit.flag & batched_fit.FLAG_FAILED) == 0
    model = estimate_error_model(
        fit.flux, fit.chi2, usable, None, relative_chi2=True, crowding=fit.crowding,
        correlated_gain=fit.correlated_gain if correlated else None,
        halo_share=fit.halo_share, chi2_dof=11**2 - 6,
    )  # fmt: skip
    res = np.concatenate(
        [
            (fit.x - x) / model.position_total(fit.x_err, 0),
            (fit.y - y) / model.position_total(fit.y_err, 1),
        ]
    )
    ok = np.concatenate([usable, usable])

    def rs(sel):
        v = res[ok & np.concatenate([sel, sel])]
        v = v[np.isfinite(v)]
        return 1.4826 * np.median(np.abs(v - np.median(v)))

    return rs(near), rs(far)


@pytest.mark.parametrize("seed", [0, 1])
def test_errors_hold_the_bright_stars_mis_modelled_light(seed):
    """Faint stars 9-30 px from bright stars whose halos carry speckles the model lacks
    (speckle light 0.25 of the halo's): with the chi^2 ratio alone (the old errors) their
    normalised residuals (x and y pooled) are 1.93 / 2.09 (seeds 0 / 1); with the
    correlated-misfit term 1.09 / 1.06, within 1 +- 0.15, and the far stars (no halo
    light) unchanged at 1.10 / 1.07. With speckles 0.5 / 1.0 of the halo's the new
    errors are 1.12-1.15 / 1.29-1.36 in x (old 2.1-2.3): too small still (docs/measure-scale.md,
    fourteenth pass). The near stars are a quarter of the faint ones: as on a
    real frame, the peers that set the typical chi^2 are mostly far from bright stars."""
    near_new, far_new = _normalised(seed, True)
    near_old, far_old = _normalised(seed, False)
    assert near_old > 1.4, near_old
    assert 0.85 < near_new < 1.15, (near_new, near_old)
    assert 0.85 < far_new < 1.15, far_new
