"""The blind detector's fused significance map against its direct forms: the array
expressions the detector used before (ndimage correlations, the running-median
background, the variance terms) and a per-pixel sum written out here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from mavispm.measure.stars import psf_detection
from mavispm.measure.stars.detection_maps import residual_image, residual_significance


def _images(shape, seed):
    """A sky-subtracted frame with stars, a model of most of them (wrong by a few per
    cent, negative wings), and model-error and wing images."""
    rng = np.random.default_rng(seed)
    ny, nx = shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    data = rng.normal(0.0, 12.0, shape)
    model = np.zeros(shape)
    for _ in range(max(3, ny * nx // 400)):
        x0, y0, f = rng.uniform(0, nx), rng.uniform(0, ny), 10 ** rng.uniform(2, 5)
        star = f * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2) / 1.3**2) / (2 * np.pi * 1.69)
        data += star
        if rng.uniform() < 0.8:  # the rest are left to be found
            model += 1.03 * star - 0.002 * f * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2) / 16)
    error = 0.03 * np.abs(model)
    wing = ndimage.uniform_filter(np.abs(model), 9) * 1e-2
    return data, model, error, wing


def _asymmetric_kernel(rng):
    k = np.abs(rng.normal(size=(7, 7)))
    k[0, 6] += 2.0  # a corner weight: a transposed or flipped kernel gives another map
    return k / k.sum()


@pytest.mark.parametrize("shape", [(83, 120), (40, 33), (9, 11)])
def test_residual_significance_equals_the_array_expressions(shape):
    """The fused pass against ``significance(local_background_subtracted(...), var, K)``
    for the bright pass (no model: the data's photon noise, Gaussian kernel, 27 px
    median) and the residual passes (with and without the wing, 9 px median, none), to
    rounding."""
    base = 150.0
    rng = np.random.default_rng(7)
    data, model, error, wing = _images(shape, seed=sum(shape))
    kern = _asymmetric_kernel(rng)
    gauss = psf_detection._gaussian_kernel(2.5)
    bright = psf_detection.significance(
        psf_detection.local_background_subtracted(data, 27), base + np.clip(data, 0, None), gauss
    )
    cases = [(bright, residual_significance(data, base, gauss, 27))]
    for box in (9, 0):
        resid = psf_detection.local_background_subtracted(data - model, box)
        for w in (None, wing):
            structure = error if w is None else error + w
            var = base + np.clip(model, 0, None) + structure**2
            direct = psf_detection.significance(resid, var, kern)
            cases.append((direct, residual_significance(data, base, kern, box, model, error, w)))
    for direct, fused in cases:
        assert fused.shape == shape
        scale = np.max(np.abs(direct))
        assert scale > 5.0  # the stars left in the residual stand out
        assert np.max(np.abs(fused - direct)) <= 1e-13 * scale


def test_residual_significance_equals_a_per_pixel_sum():
    """At chosen pixels (corners, edges, the interior), ``sum K r / sqrt(sum K^2 var)``
    over the kernel window written out, outside the frame counting as 0; no median."""
    rng = np.random.default_rng(8)
    shape = (30, 41)
    data, model, error, wing = _images(shape, seed=3)
    kern = _asymmetric_kernel(rng)
    base = 90.0
    got = residual_significance(data, base, kern, 0, model, error, wing)
    resid = data - model
    var = base + np.clip(model, 0, None) + (error + wing) ** 2
    h = 3
    for i, j in [(0, 0), (0, 40), (29, 0), (29, 40), (1, 17), (15, 2), (12, 22), (28, 39)]:
        num = den = 0.0
        for a in range(-h, h + 1):
            for b in range(-h, h + 1):
                r, c = i + a, j + b
                if 0 <= r < shape[0] and 0 <= c < shape[1]:
                    num += kern[a + h, b + h] * resid[r, c]
                    den += kern[a + h, b + h] ** 2 * var[r, c]
        assert got[i, j] == pytest.approx(num / np.sqrt(den), rel=1e-12, abs=1e-12)


def test_residual_significance_is_zero_where_the_variance_is_zero():
    data = np.zeros((12, 14))
    data[6, 7] = 5.0
    got = residual_significance(data, 0.0, np.ones((3, 3)) / 9, 0)
    assert got[6, 7] > 0 and got[0, 0] == 0.0 and np.all(np.isfinite(got))
    assert np.count_nonzero(got) == 9  # the variance is the data's positive part only


@pytest.mark.parametrize("box", [9, 27, 0])
def test_residual_image_equals_the_array_expression_bit_for_bit(box):
    data, model, _, _ = _images((61, 90), seed=4)
    direct = psf_detection.local_background_subtracted(data - model, box)
    got = residual_image(data, model, box)
    assert np.array_equal(got, direct)
    if box:  # the running median was removed: not the plain residual
        assert np.max(np.abs(got - (data - model))) > 1.0
