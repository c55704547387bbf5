"""The vectorising exponential against numpy's (an independent library implementation)."""

import numba
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.dynamics.vector_exp import exp_nonpositive


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
