"""Each very bright star's own radial misfit (``FitOptions.halo_rings``) against the
truth of a rendered frame (docs/measure-scale.md, eleventh pass)."""

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


def _frame(seed, scales=(5.5, 11.0), dist=(8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 23.0, 26.0)):
    """16 bright stars whose halos differ star by star (scale 5.5 or 11 px, alternating:
    the frame's one radial profile fits none of them), faint stars 8-26 px from them
    and others far from any; Poisson and read noise. Returns the image, the true
    positions and fluxes, each star's distance to its bright star (NaN: bright, inf:
    far), the sky and the read-noise variance."""
    rng = np.random.default_rng(seed)
    shape, sky, rn = (600, 600), 50.0, 5.0
    grid = np.arange(75.0, 600.0, 150.0)
    bx, by = jittered_grid(rng, grid)
    bflux = 10 ** rng.uniform(6.3, 6.7, bx.size)
    scale = np.where(np.arange(bx.size) % 2 == 0, *scales)
    dist = np.array(dist)
    x, y, d = ring_scene(rng, bx, by, dist, np.arange(150.0, 500.0, 150.0))
    flux = np.concatenate([bflux, np.full(x.size - bx.size, 4000.0)])
    star_scale = np.concatenate([scale, np.full(x.size - bx.size, 8.0)])
    m = 60
    image = halo_test_image(shape, sky, x, y, flux, star_scale, margin=m)
    image = rng.poisson(image[m:-m, m:-m]).astype(float) + rng.normal(0, rn, shape)
    return image, x, y, flux, d, sky, rn**2


def _bias(rings, seed):
    """Per distance bin the faint stars' median fitted / true flux over the far stars'."""
    from mavispm.measure.stars import batched_fit

    image, x, y, flux, d, sky, rn2 = _frame(seed)
    opt = batched_fit.FitOptions(**HALO_FIT, halo_radius=40.0, halo_rings=rings)
    fit = batched_fit.fit_stars(
        image, halo_test_epsf(), x, y, read_noise_var=rn2, sky0=sky, options=opt
    )
    far, off, _ = binned_halo_errors(fit, x, y, flux, d, ((11, 15), (15, 19), (19, 27)))
    return off, far


@pytest.mark.parametrize("seed", [0, 1])
def test_ring_medians_mend_each_bright_stars_own_halo(seed):
    """Faint stars 11-26 px from bright stars whose halos are 0.7 / 1.4 times the frame's
    median scale (the truth of the rendered frame): with the frame's one profile their
    fluxes are off by a median 11-13 % at 11-19 px (measured 0.106-0.130); with each
    bright star's own ring medians added (``halo_rings``) within 7.5 % in every bin
    (measured 0.021-0.057). Closer (8-11 px, the stamps overlapping) both are off by
    ~50 % and the rings make it worse (0.50-0.51 -> 0.58-0.63): not scored here, see
    docs/measure.md."""
    off_old, far_old = _bias(0.0, seed)
    off_new, far_new = _bias(5.0, seed)
    assert 0.95 < far_new < 1.05 and 0.95 < far_old < 1.05
    assert np.all(off_new < 0.075), off_new
    assert np.all(off_new <= off_old + 0.01), (off_new, off_old)
