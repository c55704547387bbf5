"""The frame's halo profile measured against a far background annulus
(``FitOptions.halo_background``) and around saturated stars (``halo_saturated``), against
the truth of a rendered frame (docs/measure-scale.md, twenty-sixth pass)."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import HALO_FIT, binned_halo_errors, halo_light, halo_test_epsf
from test_measure_halo_tail import _SEEING, _frame, _seeing

_BINS = ((32.0, 44.0), (44.0, 58.0))


def _fit(seed, **options):
    """The fast fit of the halo-tail tests' frame (a seeing halo ``r^(-11/3)`` far out)
    with a 30-px halo radius and a 150-px tail; optionally the bright stars' cores
    saturated (their pixels above ``saturate`` [electron] masked)."""
    from mavispm.measure.stars import batched_fit

    saturate = options.pop("saturate", None)
    image, x, y, flux, d, sky, rn2 = _frame(seed)
    opt = batched_fit.FitOptions(**HALO_FIT, halo_radius=30.0, halo_tail=150.0, **options)
    sat = None if saturate is None else image > saturate
    fit = batched_fit.fit_stars(
        image, halo_test_epsf(), x, y, read_noise_var=rn2, sky0=sky, options=opt,
        saturated=sat, return_model=False,
    )  # fmt: skip
    return fit, opt, x, y, flux, d


def _profile_over_truth(fit, opt, far):
    """The fitted profile continued by the tail over the rendered light per unit fitted
    flux (the core's exponential halo and the seeing halo; the fitted fluxes are ``far``
    of the true ones), median per radius bin."""
    from mavispm.measure.stars import batched_fit
    from mavispm.measure.stars.halo import halo_tail

    r = batched_fit.halo_radii(opt)
    full = halo_tail(fit.halo_profile, r[0], opt.halo_tail)
    rr = r[0] + np.arange(len(full))
    true = ((1 - _SEEING) * halo_light(rr, 8.0) + _seeing(rr)) / far
    bins = ((10.0, 20.0), (20.0, 30.0), (30.0, 45.0))
    return np.array([np.median((full / true)[(rr >= lo) & (rr < hi)]) for lo, hi in bins])


@pytest.mark.parametrize("seed", [0, 1])
def test_a_far_background_annulus_keeps_the_halo_profile_at_its_level(seed):
    """With its background just past the 30-px profile the measured profile misses the
    light still there: 0.80-0.81 / 0.68-0.69 of the rendered light at 20-30 / 30-45 px
    (measured), and faint stars 32-44 / 44-58 px from the bright ones are off by a median
    10-11 / 7 % in flux; measured out to a background at 60-70 px it is within 5 % of the
    truth at 10-45 px and those errors 6-8 / 3-5 %."""
    old, opt_old, x, y, flux, d = _fit(seed)
    new, opt_new, *_ = _fit(seed, halo_background=60.0)
    far_old, f_old, _ = binned_halo_errors(old, x, y, flux, d, _BINS)
    far_new, f_new, _ = binned_halo_errors(new, x, y, flux, d, _BINS)
    q_old = _profile_over_truth(old, opt_old, far_old)
    q_new = _profile_over_truth(new, opt_new, far_new)
    assert np.all(np.abs(q_new - 1) < 0.07), q_new
    assert np.all(q_old[1:] < 0.85), q_old
    assert np.all(f_new < 0.85 * f_old), (f_new, f_old)


def test_saturated_stars_measure_the_halo_when_no_other_star_can():
    """The bright stars saturated (cores above 2e5 e masked) and the others too faint to
    show a halo: without them the frame's profile is empty (no halo model, faint stars
    32-44 px away off by a median ~50 % in flux, measured); measured around them too
    (their saturated pixels left out), within 7 % of the truth at 10-45 px."""
    old, opt_old, x, y, flux, d = _fit(0, halo_background=60.0, saturate=2e5)
    new, opt_new, *_ = _fit(0, halo_background=60.0, halo_saturated=True, saturate=2e5)
    assert not np.any(old.halo_profile)
    far_new, f_new, _ = binned_halo_errors(new, x, y, flux, d, _BINS)
    _, f_old, _ = binned_halo_errors(old, x, y, flux, d, _BINS)
    q_new = _profile_over_truth(new, opt_new, far_new)
    assert np.all(np.abs(q_new - 1) < 0.07), q_new
    assert f_new[0] < 0.5 * f_old[0], (f_new, f_old)


def test_a_background_annulus_the_frame_cannot_hold_falls_back_to_the_near_one():
    """A background annulus at 100-110 px: fewer than 5 bright stars of the 600 x 600 px
    frame have it inside the frame, so the profile is measured against the annulus just past
    ``halo_radius`` and continued as the tail: the faint stars' flux errors as without the
    option (within 3 points, measured 1-2), not the ~50 % of no halo model at all."""
    old, _, x, y, flux, d = _fit(0)
    new, *_ = _fit(0, halo_background=100.0)
    assert np.any(new.halo_profile)
    _, f_old, _ = binned_halo_errors(old, x, y, flux, d, _BINS)
    _, f_new, _ = binned_halo_errors(new, x, y, flux, d, _BINS)
    assert np.all(np.abs(f_new - f_old) < 0.03), (f_new, f_old)


def test_a_background_annulus_past_the_tail_is_refused():
    """The tail is fitted to the measured profile's last 12 px: a background annulus at or
    past ``halo_tail`` would leave no tail (faint stars ~40 % off, measured)."""
    from mavispm.core.errors import InputError

    with pytest.raises(InputError, match="halo_background"):
        _fit(0, halo_background=200.0)
