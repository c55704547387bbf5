"""Split rendering (inner stamps + outer convolution) against full stamps and brute force."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from render_helpers import brute_force_stamp, make_optics

from mavispm.simulate.render.outer_convolution import (
    GAUSS_CUT,
    OuterConvolver,
    _even_samples,
    deposit_gaussians,
    radial_taper,
    split_cube,
)
from mavispm.simulate.render.stamps import RenderParams, StarRenderer

SCALE = 7.5  # mas
NOISE = 0.3  # per-pixel noise sigma [electron]
THRESHOLD = RenderParams().stamp_threshold
#: 0.5 microarcsec in pixels
HALF_MICROARCSEC = 0.5e-3 / SCALE


@pytest.fixture(scope="module")
def optics():
    # 3 x 3 nodes over +-2" (cells of 267 px), PSF elongating with field x, 1.875 mas
    # samples (half a pixel = 2 samples: the sub-lattice transform)
    return make_optics("airy", stretch=0.06, psf_scale=1.875, n=193)


def _renderers(optics, **kw):
    base = RenderParams(split_min_stars=0, **kw)
    full = StarRenderer(optics.psf_grid, SCALE, replace(base, outer_convolution="off"))
    split = StarRenderer(optics.psf_grid, SCALE, replace(base, outer_convolution="on"))
    return full, split


def _render(r, shape, xp, yp, x, y, cov, flux, sizes_from=None, widest=False):
    img = np.zeros(shape)
    sig = np.sqrt(np.clip(np.linalg.eigvalsh(cov)[:, -1], 0, None))
    sizes = (sizes_from or r).stamp_sizes(flux, NOISE, sig, x, y)
    if widest:  # the PSF's whole extent: no light beyond the stamps
        sizes = np.full(len(flux), r.max_stamp(float(sig.max(initial=0.0))))
    r.render(img, xp, yp, x, y, cov, flux, sizes, noise_sigma=NOISE)
    return img


def _field(xp, yp, shape):
    """Field position [arcsec] of detector pixels (frame centred on the grid centre)."""
    return (xp - (shape[1] - 1) / 2) * SCALE / 1000, (yp - (shape[0] - 1) / 2) * SCALE / 1000


def test_split_parts_sum_to_the_node():
    cube = np.random.default_rng(0).random((2, 41, 41))
    inner, outer = split_cube(cube, 1.875, 7.5, 6.0)
    assert np.abs(inner + outer - cube).max() <= 1e-15
    assert inner[:, 20, 20].tolist() == cube[:, 20, 20].tolist() and not inner[:, 0, 0].any()
    r = np.array([0.0, 2.9, 3.0, 4.5, 6.0, 7.0])
    t = radial_taper(r, 6.0)
    assert t[0] == 1 and t[2] == 1 and t[-2] == 0 and t[-1] == 0 and abs(t[3] - 0.5) < 1e-12


def test_kernel_transform_is_the_dft_of_the_samples():
    """Sub-lattice FFTs (k = 2) equal a direct DFT of the fine samples at the grid frequencies."""
    rng = np.random.default_rng(1)
    n, k, ly, lx = 21, 2, 24, 30
    outer = rng.random((1, n, n))
    conv = OuterConvolver(outer, 7.5 / (2 * k), 7.5)
    got = conv.kernel_transform(0, ly, lx, np.complex128)
    off = (np.arange(n) - (n - 1) / 2) / k  # grid pixels from the optical axis
    fy, fx = np.fft.fftfreq(ly), np.fft.rfftfreq(lx)
    ey = np.exp(-2j * np.pi * np.outer(fy, off))
    ex = np.exp(-2j * np.pi * np.outer(off, fx))
    want = ey @ outer[0] @ ex
    want *= 4.0 * np.sinc(2 * fy)[:, None] * np.sinc(2 * fx)[None, :]
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()


@settings(max_examples=20, deadline=None)
@given(ly=st.integers(1, 40), lx=st.integers(1, 40), seed=st.integers(0, 99))
def test_even_samples_equal_the_full_inverse_transform(ly, lx, seed):
    ly, lx = 4 * ly, 4 * lx
    a = np.random.default_rng(seed).random((ly, lx))
    got = _even_samples(np.fft.rfft2(a), ly, lx)
    assert np.abs(got - a[::2, ::2]).max() < 1e-12


def test_split_equals_full_stamps_across_cells_and_edges(optics):
    """Many stars over a cell boundary, at frame edges and just outside: split == full."""
    rng = np.random.default_rng(2)
    shape = (260, 300)
    n = 60
    xp = rng.uniform(-10, shape[1] + 10, n)
    yp = rng.uniform(-10, shape[0] + 10, n)
    xp[:3] = [0.0, shape[1] - 1.0, 150.5]  # on the edge, on the edge, on a pixel boundary
    yp[:3] = [100.2, 3.7, 129.5]
    x, y = _field(xp, yp, shape)
    x = x + 1.0  # the frame straddles the node column at x = 0" ... and x = 2"
    x[3], y[3] = 0.0, 0.0  # a star exactly on a node (one weight 1)
    xp[3] = (shape[1] - 1) / 2 - 1000 / SCALE
    flux = 10 ** rng.uniform(2, 6.5, n)
    flux[4] = 0.0  # zero flux
    flux[5] = 1e9  # saturating: too bright for the outer convolution's noise budget
    cov = np.tile(np.array([[30.0, 4.0], [4.0, 24.0]]), (n, 1, 1))
    full, split = _renderers(optics)
    a = _render(full, shape, xp, yp, x, y, cov, flux)
    b = _render(split, shape, xp, yp, x, y, cov, flux, sizes_from=full)
    mask = split._split_mask(flux, cov, NOISE, flux > 0)
    assert mask.sum() >= 20 and not mask[5] and not mask[4]
    # pixel errors: far below the noise-relevant level the full stamps are cut at
    assert np.abs(a - b).max() < 0.5 * THRESHOLD * NOISE
    assert abs(a.sum() - b.sum()) < 1e-6 * a.sum()


def test_split_star_flux_and_centroid_exact(optics):
    """An isolated symmetric star: flux within 1e-6, centroid within 0.5 microarcsec."""
    sym = make_optics("airy", psf_scale=1.875, n=193)
    full, split = _renderers(sym)
    shape = (120, 120)
    for fx, fy in ((0.0, 0.0), (0.31, -0.42), (0.5, 0.5)):
        xp, yp = np.array([60.0 + fx]), np.array([59.0 + fy])
        cov = np.array([[[28.0, 0.0], [0.0, 28.0]]])
        img = _render(split, shape, xp, yp, np.array([0.0]), np.array([0.0]), cov, [1e5])
        assert abs(img.sum() / 1e5 - 1) < 1e-6
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
        cx, cy = (img * xx).sum() / img.sum(), (img * yy).sum() / img.sum()
        assert abs(cx - xp[0]) < HALF_MICROARCSEC and abs(cy - yp[0]) < HALF_MICROARCSEC


@pytest.mark.parametrize("psf_scale,n", [(1.875, 193), (3.75, 97)])
def test_split_matches_brute_force_reference(psf_scale, n):
    """Inner stamp + outer convolution against a direct real-space evaluation."""
    opt = make_optics("airy", stretch=0.06, psf_scale=psf_scale, n=n)
    _, split = _renderers(opt)
    m = 40
    x, y, xp, yp = 0.7, -1.3, 30.37, 29.81
    cov = np.array([[29.2, 1.5], [1.5, 27.2]])
    img = np.zeros((60, 60))
    split.render(img, [xp], [yp], [x], [y], cov[None], [1.0], [16], noise_sigma=None)
    ref = brute_force_stamp(opt.psf_grid, x, y, cov, xp, yp, SCALE, m)
    x0, y0 = round(xp) - m // 2, round(yp) - m // 2
    got = img[y0 : y0 + m, x0 : x0 + m]
    assert np.abs(got - ref).max() <= 1e-3 * ref.max()
    assert abs(got.sum() - ref.sum()) < 1e-4


@settings(max_examples=25, deadline=None)
@given(
    xp=st.floats(-8.0, 107.0),
    yp=st.floats(-8.0, 87.0),
    x=st.one_of(st.just(0.0), st.just(2.0), st.floats(-2.5, 2.5)),
    logf=st.one_of(st.just(-np.inf), st.floats(1.0, 10.0)),
)
def test_split_edges(optics, xp, yp, x, logf):
    """Edges: frame borders, stars outside, nodes and the grid's rim, zero / huge flux.

    Against full stamps of the PSF's whole extent (the stamps sized by the threshold
    may themselves differ from those by up to ~0.5 x threshold x noise at the edge)."""
    full, split = _shared(optics)
    shape = (80, 100)
    flux = np.array([0.0 if np.isinf(logf) else 10.0**logf])
    cov = np.array([[[26.0, -3.0], [-3.0, 31.0]]])
    args = (np.array([xp]), np.array([yp]), np.array([x]), np.array([0.3]), cov, flux)
    a = _render(full, shape, *args, widest=True)
    b = _render(split, shape, *args, sizes_from=full)
    assert np.abs(a - b).max() <= 0.5 * THRESHOLD * NOISE


_CACHE = {}


def _shared(optics):
    if "r" not in _CACHE:
        _CACHE["r"] = _renderers(optics)
    return _CACHE["r"]


def test_knob_validation_and_auto(optics):
    with pytest.raises(ValueError, match="outer_convolution"):
        RenderParams(outer_convolution="yes")
    with pytest.raises(ValueError, match="split_radius"):
        RenderParams(split_radius=1.0)
    # half a 7.36 mas pixel is not a whole number of 1.875 mas samples
    r = StarRenderer(optics.psf_grid, 7.36, RenderParams(outer_convolution="on"))
    with pytest.raises(ValueError, match="outer_convolution"):
        _render(r, (40, 40), np.array([20.0]), np.array([20.0]), np.zeros(1), np.zeros(1),
                np.array([[[25.0, 0], [0, 25.0]]]), np.array([1e4]))  # fmt: skip
    # auto below split_min_stars renders full stamps: bit for bit the same image
    auto = StarRenderer(optics.psf_grid, SCALE, RenderParams(split_min_stars=10))
    off = StarRenderer(optics.psf_grid, SCALE, RenderParams(outer_convolution="off"))
    args = (np.array([20.3, 30.0]), np.array([21.0, 9.0]), np.zeros(2), np.zeros(2),
            np.tile(np.eye(2) * 25.0, (2, 1, 1)), np.array([1e4, 1e3]))  # fmt: skip
    assert np.array_equal(_render(auto, (40, 40), *args), _render(off, (40, 40), *args))


def test_vectorised_stamp_sizes_equal_the_scalar_rule():
    from mavispm.simulate.render.stamps import _stamp_size_at_least, _stamp_sizes_at_least

    n = np.concatenate([np.linspace(0, 700, 7001), [511.5, 512, 512.0001, 513, 7.9]])
    for floor in (2, 16, 40):
        want = [_stamp_size_at_least(v, floor) for v in n]
        assert _stamp_sizes_at_least(n, floor).tolist() == want


@pytest.mark.parametrize(
    "cov", [[[4.0, 0.5], [0.5, 3.0]], [[9.0, -2.0], [-2.0, 5.0]], [[2.0, 1.9], [1.9, 2.0]]]
)
def test_gaussian_deposit_equals_direct_evaluation(cov):
    """The running-product deposit equals exp() at every sample (and sums to 1 when resolved)."""
    c = np.array(cov)
    inv = np.linalg.inv(c)
    norm = 1 / (2 * np.pi * np.sqrt(np.linalg.det(c)))
    h = int(np.ceil(7 * np.sqrt(c.max()))) + 1
    f = np.zeros((2, 64, 64))
    deposit_gaussians(
        f, np.array([[1, -1]]), np.array([[2.0, 5.0]]), np.array([31.3]), np.array([30.8]),
        np.array([[inv[0, 0], inv[0, 1], inv[1, 1]]]), np.array([norm]), np.array([h]),
        np.array([GAUSS_CUT]),
    )  # fmt: skip
    yy, xx = np.mgrid[0:64, 0:64]
    dx, dy = xx - 31.3, yy - 30.8
    q = inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy
    g = norm * np.exp(-0.5 * q)
    g *= (np.abs(xx - 31) <= h) & (np.abs(yy - 31) <= h)
    assert not f[0].any()
    inside = q < GAUSS_CUT**2  # the deposit keeps the samples inside this ellipse
    g_kept = g * (f[1] > 0)
    assert abs(f[1].sum() / 2.0 - 1) < 1e-12  # scaled to the star's flux exactly
    assert np.abs(f[1] - 2.0 * g_kept / g_kept.sum())[inside].max() < 1e-14
    if np.linalg.eigvalsh(c)[0] > 1.0:  # resolved: the scale is 1 to the Gaussian's aliasing
        assert abs(g_kept.sum() - 1) < 1e-9
        assert np.abs(f[1] - 2.0 * g).max() <= 2.0 * norm * np.exp(-0.5 * GAUSS_CUT**2) + 1e-11


def test_tilt_table_cache_equals_the_computed_table(tmp_path):
    """A frames process loads the tip-tilt table (no Bessel functions, no scipy.special)."""
    from mavispm.simulate.optics import model
    from mavispm.simulate.optics.tiptilt import TipTiltField

    s = model.validate_settings({})
    fresh = TipTiltField(s.tiptilt, s.atmosphere, s.pupil)
    first = TipTiltField(s.tiptilt, s.atmosphere, s.pupil, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("tiltcov-*.npz"))) == 1
    loaded = TipTiltField(s.tiptilt, s.atmosphere, s.pupil, cache_dir=tmp_path)
    x, y = np.array([0.0, 3.2, -11.0]), np.array([0.0, -7.5, 14.0])
    want = fresh.covariance(x, y)
    assert np.array_equal(first.covariance(x, y), want)
    assert np.array_equal(loaded.covariance(x, y), want)
    other = replace(s.atmosphere, seeing=s.atmosphere.seeing * 1.1)
    TipTiltField(s.tiptilt, other, s.pupil, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("tiltcov-*.npz"))) == 2  # other settings, other key


def test_shorter_gaussian_cut_keeps_the_flux():
    """A deposit cut at 4 sigma keeps its flux; it moves at most exp(-8) from wing to core."""
    c = np.array([[9.0, -2.0], [-2.0, 5.0]])
    inv = np.linalg.inv(c)
    norm = 1 / (2 * np.pi * np.sqrt(np.linalg.det(c)))
    args = (np.array([[0]]), np.array([[1.0]]), np.array([31.3]), np.array([30.8]),
            np.array([[inv[0, 0], inv[0, 1], inv[1, 1]]]), np.array([norm]), np.array([22]))  # fmt: skip
    short, full = np.zeros((1, 64, 64)), np.zeros((1, 64, 64))
    deposit_gaussians(short, *args, np.array([4.0]))
    deposit_gaussians(full, *args, np.array([GAUSS_CUT]))
    assert abs(short.sum() - 1) < 1e-12 and abs(full.sum() - 1) < 1e-12
    moved = np.abs(short - full).sum() / 2
    assert 1e-6 < moved <= np.exp(-8)
