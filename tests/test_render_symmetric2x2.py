"""Closed-form 2 x 2 eigenvalues against LAPACK (numpy.linalg.eigvalsh)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.simulate.render.symmetric2x2 import eigvals_2x2


def test_matches_eigvalsh_on_covariances():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5000, 2, 2)) * rng.uniform(0.01, 100, (5000, 1, 1))
    cov = a @ np.swapaxes(a, 1, 2)  # positive semi-definite, widely spread scales
    cov[:10] = np.eye(2) * 4.0  # isotropic (double eigenvalue)
    cov[10:20, 1, 1] = 0.0  # singular
    cov[10:20, 0, 1] = cov[10:20, 1, 0] = 0.0
    lo, hi = eigvals_2x2(cov)
    ref = np.linalg.eigvalsh(cov)
    scale = np.abs(cov).max(axis=(1, 2))
    assert np.all(np.abs(lo - ref[:, 0]) <= 1e-14 * scale)
    assert np.all(np.abs(hi - ref[:, 1]) <= 1e-14 * scale)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-1e6, 1e6, allow_nan=False),
    st.floats(-1e6, 1e6, allow_nan=False),
    st.floats(-1e6, 1e6, allow_nan=False),
)
def test_any_symmetric_matrix(a, d, b):
    m = np.array([[[a, b], [b, d]]])
    lo, hi = eigvals_2x2(m)
    ref = np.linalg.eigvalsh(m)[0]
    tol = 1e-12 * max(abs(a), abs(b), abs(d), 1e-300)
    assert lo[0] <= hi[0]
    assert abs(lo[0] - ref[0]) <= tol and abs(hi[0] - ref[1]) <= tol
