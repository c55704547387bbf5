"""The compiled stamp evaluation of the variable ePSF against independent references.

References: scipy's ``map_coordinates`` (its own cubic B-spline evaluation of the
same prefiltered samples, float64), central finite differences of it for the
derivatives, and the numpy path (float32 gathers, so agreement to ~1e-6).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from mavispm.measure.stars.variable_psf import (
    StampGeometry,
    constant_epsf,
    gridded_epsf,
    polynomial_from_basis,
    sample_epsf,
)

OS = 2


def _gaussian_epsf(sx, sy, size=25, oversampling=OS):
    from scipy.special import ndtr

    def prf(dx, dy):
        fx = ndtr((dx + 0.5) / sx) - ndtr((dx - 0.5) / sx)
        fy = ndtr((dy + 0.5) / sy) - ndtr((dy - 0.5) / sy)
        return fx * fy

    return sample_epsf(prf, size, oversampling)


def _grid_psf():
    nodes = np.array([0.0, 400.0, 800.0])
    stack = [_gaussian_epsf(1.0 + 0.1 * i, 1.1 + 0.05 * j) for j in range(3) for i in range(3)]
    return gridded_epsf(np.array(stack), nodes, nodes, OS)


def _reference(psf, x0, y0, geom):
    """Value of each stamp pixel from map_coordinates on the star's mixed spline."""
    idx, w = psf.mixing(x0, y0)
    out = np.zeros((len(x0), geom.size, geom.size))
    for k in range(len(x0)):
        coef = np.tensordot(w[k], psf._coef[idx[k]], axes=1)
        u = (geom.columns()[k] - x0[k]) * psf.oversampling + psf._centre[0]
        v = (geom.rows()[k] - y0[k]) * psf.oversampling + psf._centre[1]
        vv, uu = np.meshgrid(v, u, indexing="ij")
        out[k] = ndimage.map_coordinates(
            coef, [vv.ravel(), uu.ravel()], order=3, prefilter=False, mode="grid-constant"
        ).reshape(geom.size, geom.size)
    return out


def _stars(rng, n, lo=20.0, hi=780.0):
    x = rng.uniform(lo, hi, n)
    y = rng.uniform(lo, hi, n)
    # stamps centred up to a pixel off the star (as after a fit's moves)
    geom = StampGeometry(
        np.rint(x + rng.uniform(-1, 1, n)).astype(np.intp),
        np.rint(y + rng.uniform(-1, 1, n)).astype(np.intp),
        5,
    )
    return x, y, geom


def test_values_match_map_coordinates():
    psf = _grid_psf()
    x, y, geom = _stars(np.random.default_rng(0), 40)
    value, _, _ = psf.evaluate(x, y, geom)
    ref = _reference(psf, x, y, geom)
    assert np.max(np.abs(value - ref)) <= 1e-12 * np.max(np.abs(ref))


def test_derivatives_match_finite_differences():
    psf = _grid_psf()
    x, y, geom = _stars(np.random.default_rng(1), 20)
    mix = psf.mixing(x, y)  # held fixed, as the fitter does
    _, dvx, dvy = psf.evaluate(x, y, geom, mix=mix)
    h = 1e-5
    for d, (ex, ey) in ((dvx, (h, 0.0)), (dvy, (0.0, h))):
        plus = psf.evaluate(x + ex, y + ey, geom, mix=mix, derivatives=False)
        minus = psf.evaluate(x - ex, y - ey, geom, mix=mix, derivatives=False)
        fd = (plus - minus) / (2 * h)
        assert np.max(np.abs(d - fd)) <= 1e-8 * np.max(np.abs(fd))


@pytest.mark.parametrize("kind", ["constant", "grid", "polynomial"])
def test_compiled_equals_numpy_path(kind):
    if kind == "constant":
        psf = constant_epsf(_gaussian_epsf(1.2, 1.3), OS)
    elif kind == "grid":
        psf = _grid_psf()
    else:
        rng = np.random.default_rng(5)
        basis = np.array([_gaussian_epsf(1.2, 1.2)] + [1e-3 * rng.normal(size=(51, 51))] * 5)
        psf = polynomial_from_basis(basis, 2, (800, 800), OS)
    x, y, geom = _stars(np.random.default_rng(2), 300)
    got = psf.evaluate(x, y, geom)
    ref = psf.evaluate_numpy(x, y, geom)
    for a, b in zip(got, ref):
        assert a.shape == b.shape and a.dtype == np.float64
        assert np.max(np.abs(a - b)) <= 2e-6 * np.max(np.abs(b))
    only = psf.evaluate(x, y, geom, derivatives=False)
    np.testing.assert_array_equal(only, got[0])


def test_stamp_beyond_the_epsf_reads_zero():
    """A stamp far larger than the ePSF footprint: outside pixels are exactly zero and
    the sum over the stamp is the flux fraction of the ePSF (1 for a 25 px footprint)."""
    psf = constant_epsf(_gaussian_epsf(1.0, 1.0, size=9), OS)
    x, y = np.array([100.3]), np.array([50.7])
    geom = StampGeometry(np.array([100]), np.array([51]), 12)
    value, dvx, dvy = psf.evaluate(x, y, geom)
    assert np.all(value[0, :, :3] == 0.0) and np.all(value[0, :, -3:] == 0.0)
    assert np.all(dvx[0, :3] == 0.0) and np.all(dvy[0, -3:] == 0.0)
    np.testing.assert_allclose(value.sum(), 1.0, atol=2e-3)


def test_empty_input():
    psf = _grid_psf()
    geom = StampGeometry(np.zeros(0, np.intp), np.zeros(0, np.intp), 5)
    value, dvx, dvy = psf.evaluate(np.zeros(0), np.zeros(0), geom)
    assert value.shape == dvx.shape == dvy.shape == (0, 11, 11)


@settings(max_examples=40, deadline=None)
@given(
    st.floats(-3.0, 803.0),
    st.floats(-3.0, 803.0),
    st.integers(-2, 2),
    st.integers(-2, 2),
)
def test_edges_and_phases_match_map_coordinates(x, y, ox, oy):
    """Any position (frame edges, outside the grid nodes, any pixel phase) and stamp offset."""
    psf = _grid_psf()
    xs, ys = np.array([x]), np.array([y])
    geom = StampGeometry(np.array([int(np.rint(x)) + ox]), np.array([int(np.rint(y)) + oy]), 4)
    value = psf.evaluate(xs, ys, geom, derivatives=False)
    ref = _reference(psf, xs, ys, geom)
    assert np.max(np.abs(value - ref)) <= 1e-12 * max(np.max(np.abs(ref)), 1e-300)


@pytest.mark.parametrize("gradient", [False, True])
def test_fused_normal_equations_equal_numpy(gradient):
    """The fused weights, residuals, J W J^T and J W r against the explicit numpy algebra."""
    from mavispm.measure.stars.crlb import fisher_matrix, jacobian, sky_plane_basis
    from mavispm.measure.stars.stamp_kernel import normal_equations

    rng = np.random.default_rng(7)
    psf = _grid_psf()
    x, y, geom = _stars(rng, 200)
    v, dvx, dvy = (a.reshape(200, -1) for a in psf.evaluate(x, y, geom))
    flux = rng.uniform(1e3, 1e6, 200)
    sky = rng.uniform(10, 500, 200)
    slope = rng.normal(0, 5, (200, 2))
    own = flux[:, None] * v
    model_all = own + rng.uniform(0, 300, own.shape)
    valid = rng.uniform(size=own.shape) > 0.05
    data = model_all + sky[:, None] + rng.normal(0, 30, own.shape)
    basis = sky_plane_basis(geom.size)
    a, b, w, r = normal_equations(
        v, dvx, dvy, data, model_all, own, valid, flux, sky, slope if gradient else None, basis, 9.0
    )
    back = sky[:, None] + (slope @ basis if gradient else 0.0)
    r_ref = data - model_all - back
    w_ref = valid / (np.maximum(model_all + back, 0.0) + 9.0)
    s = geom.size
    jac = jacobian(flux, *(q.reshape(-1, s, s) for q in (v, dvx, dvy)), sky_gradient=gradient)
    np.testing.assert_allclose(r, r_ref, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(w, w_ref, rtol=1e-12)
    np.testing.assert_allclose(a, fisher_matrix(jac, w_ref), rtol=1e-10)
    np.testing.assert_allclose(
        b, np.einsum("nkm,nm->nk", jac, w_ref * r_ref), rtol=1e-8, atol=1e-12
    )
