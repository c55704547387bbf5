"""Stars whose positions the fitter held below ``min_snr`` (docs/measure-scale.md,
tenth pass): on the 1e5-star frame 5.8 % of the V < 25 stars had a negative or
sub-``min_snr`` flux in their first position step, rested there as converged, and the
last flux pass gave them SNR > 3 and flag 0 at their start position (the truth in the
benchmark, so they also deflated its scatter). Now such a star is stepped again in the
next sweeps, and one never fitted is flagged failed."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import (
    Detector,
    SynthPSF,
    fit_noisy_frame,
    grid_positions,
    noisy_frame,
    render_image,
    true_epsf,
)

from mavispm.measure.stars.batched_fit import FLAG_FAILED, FitOptions

SHAPE = (200, 200)


def _fit(iterations):
    """Isolated bright stars started 0.3 px off; a third of them with a negative first
    flux (as a neighbour's mis-modelled light leaves a faint star after the fixed pass):
    their positions are held in their first position step while their flux recovers."""
    rng = np.random.default_rng(4)
    psf, det = SynthPSF(1.2), Detector()
    x, y = grid_positions(SHAPE, 20, 8, rng)
    flux = np.full(len(x), 2e5)
    image, sat = noisy_frame(render_image(SHAPE, x, y, flux, psf), det, rng)
    angle = rng.uniform(0, 2 * np.pi, len(x))
    x0, y0 = x + 0.3 * np.cos(angle), y + 0.3 * np.sin(angle)
    negative = np.arange(len(x)) % 3 == 0
    res = fit_noisy_frame(
        image, sat, det, true_epsf(psf, SHAPE), x0, y0,
        flux0=np.where(negative, -0.5 * flux, flux),
        options=FitOptions(wing_threshold=0.0, iterations=iterations),
    )  # fmt: skip
    ok = (res.flag & FLAG_FAILED) == 0
    return res, ok, np.hypot(res.x - x, res.y - y), negative, flux


@pytest.mark.parametrize("iterations", [2, 40])
def test_a_held_star_is_fitted_in_a_later_sweep(iterations):
    """Against the truth: every star is measured, the held ones in their second sweep
    (the old code returned them unflagged 0.3 px from the truth)."""
    res, ok, dist, negative, flux = _fit(iterations)
    assert np.all(ok)
    assert np.all(dist < 0.05), np.sort(dist)[-5:]
    np.testing.assert_allclose(res.flux[negative], flux[negative], rtol=0.05)


def test_a_never_fitted_position_is_flagged_failed():
    """With one sweep the held stars are never fitted: flagged failed, not reported as
    measured at their start (the old code: flag 0, 0.3 px from the truth)."""
    res, ok, dist, negative, flux = _fit(1)
    assert np.all(dist[ok] < 0.05), np.sort(dist[ok])[-5:]
    assert np.all(~ok[negative])
    assert np.all(ok[~negative])
    # the flux itself did recover
    np.testing.assert_allclose(res.flux[negative], flux[negative], rtol=0.05)
