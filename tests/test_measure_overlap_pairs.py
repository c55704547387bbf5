"""The batched fitter's overlapping pairs come from the stars on the frame only.

The fitter parks the stars off the frame at one position; searched with the others they
formed a clique of ``K^2 / 2`` pairs and ``K`` colours that every sweep looped over, and
the fit's cost grew as ``N^2`` (issue 14, item 4; docs/measure-scale.md). The reference
is a brute-force distance matrix.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.measure.stars import batched_fit
from mavispm.measure.stars.variable_psf import constant_epsf


def _brute_pairs(x, y, keep, distance):
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    i, j = np.nonzero(np.triu(d <= distance, 1) & keep[:, None] & keep[None, :])
    return set(zip(i.tolist(), j.tolist(), strict=True))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 200), st.integers(0, 2**31 - 1), st.floats(5.0, 80.0))
def test_overlap_pairs_are_the_close_pairs_of_the_kept_stars(n, seed, spread):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, spread, n), rng.uniform(0, spread, n)
    keep = rng.random(n) < 0.7
    got = batched_fit.overlap_pairs(x, y, keep, 11.0)
    assert got.shape == (len(got), 2)
    assert np.all(got[:, 0] < got[:, 1])
    assert len(set(map(tuple, got.tolist()))) == len(got)
    assert set(map(tuple, got.tolist())) == _brute_pairs(x, y, keep, 11.0)


def _gaussian_frame(x, y, flux, shape, sigma, sky, seed):
    """Poisson image [electron] of circular Gaussian stars on a flat sky."""
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    light = np.zeros(shape)
    for xi, yi, fi in zip(x, y, flux, strict=True):
        light += fi * np.exp(-0.5 * ((cols - xi) ** 2 + (rows - yi) ** 2) / sigma**2)
    expected = sky + light / (2 * np.pi * sigma**2)
    return np.random.default_rng(seed).poisson(expected).astype(float)


def test_stars_off_the_frame_add_no_pairs_and_do_not_change_the_fit(monkeypatch):
    """60 stars off a 64 x 64 frame beside 40 on it: the colouring sees only the on-frame
    stars' close pairs (the old search gave it the 60 * 59 / 2 = 1,770 pairs of the parked
    stars as well), and the on-frame stars' results equal a fit without the others."""
    rng = np.random.default_rng(3)
    n_on, n_off, shape, sigma = 40, 60, (64, 64), 1.2
    x_on, y_on = rng.uniform(14, 50, n_on), rng.uniform(14, 50, n_on)
    flux_on = rng.uniform(2e3, 2e4, n_on)
    image = _gaussian_frame(x_on, y_on, flux_on, shape, sigma, 50.0, seed=4)
    x = np.r_[x_on, rng.uniform(-40, -5, n_off)]
    y = np.r_[y_on, rng.uniform(-40, 100, n_off)]
    off = np.arange(-24, 25) / 2
    r2 = off[None, :] ** 2 + off[:, None] ** 2
    psf = constant_epsf(np.exp(-0.5 * r2 / sigma**2) / (2 * np.pi * sigma**2), 2)
    seen = []
    colour_graph = batched_fit.colour_graph

    def recording(n, pairs):
        seen.append(np.array(pairs))
        return colour_graph(n, pairs)

    monkeypatch.setattr(batched_fit, "colour_graph", recording)
    common = dict(read_noise_var=25.0, sky0=50.0)
    both = batched_fit.fit_stars(image, psf, x, y, **common)
    on = np.arange(len(x)) < n_on
    pairs = seen[0]
    assert on[pairs].all()
    assert set(map(tuple, pairs.tolist())) == _brute_pairs(x, y, on, 11.0)
    assert len(pairs) > 0
    alone = batched_fit.fit_stars(image, psf, x_on, y_on, **common)
    assert np.all(both.flag[~on] & batched_fit.FLAG_FAILED)
    for name in ("x", "y", "flux", "sky", "x_err", "flag"):
        np.testing.assert_array_equal(getattr(both, name)[on], getattr(alone, name), err_msg=name)
