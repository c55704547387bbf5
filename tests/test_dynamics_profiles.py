"""Binned dispersion profiles: ML deconvolution, uncertainties, edge cases."""

import astropy.units as u
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.errors import InputError
from mavispm.dynamics.profiles import (
    dispersion_profile,
    equal_count_bins,
    fisher_error,
    ml_dispersion,
    radial_tangential,
)

PM = u.mas / u.yr


def test_ml_deconvolution_recovers_intrinsic_dispersion():
    """Errors comparable to the dispersion are removed (naive std would be biased)."""
    rng = np.random.default_rng(4)
    n, true = 20000, 0.3
    e = rng.uniform(0.05, 0.5, n)
    v = 0.1 + rng.normal(0, true, n) + e * rng.standard_normal(n)
    sig, mu = ml_dispersion(v, e)
    err = fisher_error(sig, e)
    assert abs(sig - true) < 3 * err
    assert abs(mu - 0.1) < 0.02
    assert np.std(v) > true * 1.2  # the naive estimate really is biased


def test_analytic_and_bootstrap_errors_agree_and_cover():
    rng = np.random.default_rng(5)
    n = 3000
    R = rng.uniform(0, 17, n) * u.arcsec
    e = np.full(n, 0.05)
    v_r, v_t = rng.normal(0, 0.3, (2, n))
    prof = dispersion_profile(
        R, v_r * PM, v_t * PM, e * PM, e * PM, bin_size=300, n_bootstrap=300, distance=4.6 * u.kpc
    )
    assert len(prof) == 10 and np.all(prof["n"] == 300)
    a = prof["sigma_r_err"].value
    b = prof["sigma_r_err_boot"].value
    np.testing.assert_allclose(np.median(b / a), 1.0, atol=0.15)
    pulls = (prof["sigma_pm"].value - 0.3) / prof["sigma_pm_err"].value
    assert np.mean(np.abs(pulls) < 2) >= 0.8
    conv = 4.740470463533348 * 4.6
    np.testing.assert_allclose(prof["sigma_r_kms"].value, prof["sigma_r"].value * conv)
    assert np.all(np.diff(prof["R_mean"].value) > 0)


def test_bins_merge_small_remainder():
    sl = equal_count_bins(950, 300)
    sizes = [s.stop - s.start for s in sl]
    assert sum(sizes) == 950 and sizes == [300, 300, 350]
    sizes = [s.stop - s.start for s in equal_count_bins(1000, 300)]
    assert sizes == [300, 300, 300, 100] or sizes == [300, 300, 400]
    assert equal_count_bins(1, 300) == []
    with pytest.raises(InputError):
        equal_count_bins(10, 1)


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(0, 40),
    err_scale=st.sampled_from([0.0, 1e-8, 1.0, 1e6]),
    at_centre=st.booleans(),
)
def test_profile_edge_cases_are_finite(n, err_scale, at_centre):
    rng = np.random.default_rng(n)
    R = (np.zeros(n) if at_centre else rng.uniform(0, 5, n)) * u.arcsec
    v = rng.normal(0, 0.3, (2, n))
    e = np.full(n, err_scale)
    prof = dispersion_profile(R, v[0] * PM, v[1] * PM, e * PM, e * PM, bin_size=10, n_bootstrap=5)
    assert len(prof) == (0 if n < 2 else max(n // 10, 1) + (1 if n >= 10 and n % 10 >= 5 else 0))
    for col in ("sigma_r", "sigma_t", "sigma_pm"):
        if len(prof):
            assert np.all(np.isfinite(prof[col].value)) and np.all(prof[col].value >= 0)


def test_bad_inputs_are_clear_errors():
    R = np.ones(5) * u.arcsec
    v = np.zeros(5) * PM
    with pytest.raises(InputError, match="negative"):
        dispersion_profile(R, v, v, -np.ones(5) * PM, v)
    with pytest.raises(InputError, match="mas/yr"):
        dispersion_profile(R, v, v, np.ones(5) * u.m, v)
    with pytest.raises(InputError, match="finite"):
        dispersion_profile(R, v, v, np.full(5, np.nan) * PM, v)


def test_radial_tangential_rotation():
    R, vr, vt = radial_tangential(
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 2.0, 0.0]),
        np.array([1.0, 1.0, 3.0]),
        np.array([0.0, 0.0, 4.0]),
    )
    np.testing.assert_allclose(R, [1, 2, 0])
    np.testing.assert_allclose(vr, [1, 0, 3])
    np.testing.assert_allclose(vt, [0, -1, 4])
