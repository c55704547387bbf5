"""The fitter's greedy colouring: valid (no overlapping stamps share a colour) and equal
to a plain-Python greedy colouring in the same (degree) order."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.measure.stars.batched_fit import colour_stars


def _reference(x, y, distance):
    n = len(x)
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    adj = (d <= distance) & ~np.eye(n, dtype=bool)
    order = np.argsort(-adj.sum(axis=1), kind="stable")
    colour = np.full(n, -1)
    for i in order:
        used = set(colour[adj[i]].tolist())
        c = 0
        while c in used:
            c += 1
        colour[i] = c
    return colour, adj


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 300), st.integers(0, 2**31 - 1), st.floats(1.0, 40.0))
def test_colouring_is_valid_and_greedy(n, seed, spread):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, spread, n), rng.uniform(0, spread, n)
    got = colour_stars(x, y, 11.0)
    if n < 2:
        assert got.tolist() == [0] * n
        return
    ref, adj = _reference(x, y, 11.0)
    i, j = np.nonzero(adj)
    assert np.all(got[i] != got[j])
    np.testing.assert_array_equal(got, ref)
