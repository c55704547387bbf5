"""The vectorising exponential and logarithm against numpy's (an independent library
implementation) and mpmath."""

import mpmath
import numba
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.dynamics.vector_exp import exp_bounded, exp_nonpositive, log_positive


@numba.njit
def _exp_array(x):
    out = np.empty_like(x)
    for i in range(x.size):
        out[i] = exp_nonpositive(x[i])
    return out


def test_matches_numpy_on_the_whole_range():
    """Relative error <= 1e-15 (4.5 ulp) against numpy on [-708, 0] (dense grid, integers,
    odd multiples of ln 2 / 2: the range reduction's edges)."""
    x = np.concatenate(
        [
            -np.geomspace(1e-300, 708.0, 200_001),
            -np.arange(709.0),
            -np.log(2.0) * (np.arange(0, 1021) + 0.5),
            [0.0, -0.0],
        ]
    )
    x = x[x >= -708.0]
    rel = np.abs(_exp_array(x) / np.exp(x) - 1.0)
    assert rel.max() <= 1e-15


def test_clamps_below_the_smallest_normal_and_keeps_nan():
    """Arguments below -708 give exp(-708) (a floor callers test for), NaN stays NaN."""
    out = _exp_array(np.array([-708.0, -745.0, -1e6, -np.inf, np.nan]))
    assert np.all(out[1:4] == out[0])
    assert abs(out[0] / np.exp(-708.0) - 1.0) <= 1e-15
    assert np.isnan(out[4])


@settings(max_examples=300, deadline=None)
@given(st.floats(min_value=-708.0, max_value=0.0))
def test_any_nonpositive_argument(x):
    got = _exp_array(np.array([x]))[0]
    assert abs(got / np.exp(x) - 1.0) <= 1e-15


@numba.njit(error_model="numpy", fastmath={"contract"})
def _log_array(x):
    out = np.empty_like(x)
    for i in range(x.size):
        out[i] = log_positive(x[i])
    return out


@numba.njit(error_model="numpy", fastmath={"contract"})
def _exp_bounded_array(x):
    out = np.empty_like(x)
    for i in range(x.size):
        out[i] = exp_bounded(x[i])
    return out


def _mp(fn, x):
    return np.array([float(fn(mpmath.mpf(float(v)))) for v in x])


def test_log_is_within_one_ulp_of_mpmath():
    """ln x against mpmath (50 digits) from subnormal numbers to 1e308, densely near 1 (the
    reduction's edges sqrt(2)/2 and sqrt(2) included): at most one unit in the last place."""
    rng = np.random.default_rng(7)
    x = np.concatenate(
        [
            np.geomspace(5e-324, 1.7e308, 4001),
            rng.uniform(0.5, 2.0, 3000),
            1.0 + rng.uniform(-1e-8, 1e-8, 500),
            [np.sqrt(0.5), np.nextafter(np.sqrt(0.5), 0), np.sqrt(2.0), 2.0, 0.5, 1.0],
        ]
    )
    with mpmath.workdps(50):
        ref = _mp(mpmath.log, x)
    assert np.all(np.abs(_log_array(x) - ref) <= np.spacing(np.abs(ref)) + 1e-300)


def test_log_special_arguments():
    """0 -> -inf, +inf -> +inf, negative numbers and NaN -> NaN, 1 -> 0 exactly."""
    out = _log_array(np.array([0.0, np.inf, -1.0, -np.inf, np.nan, 1.0]))
    assert out[0] == -np.inf and out[1] == np.inf
    assert np.all(np.isnan(out[2:5])) and out[5] == 0.0


def test_bounded_exp_against_mpmath_and_its_clamps():
    """exp on [-708, 709] within 5e-16 of mpmath; arguments beyond are clamped, NaN stays."""
    x = np.concatenate([np.linspace(-708.0, 709.0, 20001), [0.0, 1e-300, -1e-300]])
    with mpmath.workdps(40):
        ref = _mp(mpmath.exp, x)
    assert np.max(np.abs(_exp_bounded_array(x) / ref - 1.0)) <= 5e-16
    out = _exp_bounded_array(np.array([-1e4, 1e4, np.inf, np.nan]))
    ends = _exp_bounded_array(np.array([-708.0, 709.0]))
    assert out[0] == ends[0] and out[1] == ends[1] == out[2] and np.isnan(out[3])
