"""Star renderer: flux, centroid, brute-force reference, knobs and numerical edges."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from render_helpers import brute_force_stamp, make_optics

from mavispm.simulate.render.stamps import RenderParams, StarRenderer

SCALE = 7.5  # mas


#: Blur-kernel covariances [mas^2] of the mixing-kernel tests: round, tilted, zero,
#: wide, elongated, nearly singular and (last, first test only) very wide.
KERNEL_COVARIANCES = np.asarray(
    [
        [[20.0, 6.0], [6.0, 12.0]],
        [[80.0, -30.0], [-30.0, 50.0]],
        [[0.0, 0.0], [0.0, 0.0]],
        [[400.0, 100.0], [100.0, 90.0]],
        [[5.0, 0.0], [0.0, 300.0]],
        [[60.0, 59.0], [59.0, 60.0]],
        [[9000.0, 8900.0], [8900.0, 9000.0]],
    ]
)


@pytest.fixture(scope="module")
def airy_optics():
    return make_optics("airy")  # symmetric nodes


@pytest.fixture(scope="module")
def variable_optics():
    return make_optics("airy", stretch=0.06)  # PSF elongates with field x


@pytest.fixture(scope="module")
def renderer(airy_optics):
    return StarRenderer(airy_optics.psf_grid, SCALE, RenderParams())


def _centroid(stamp, x0, y0):
    yy, xx = np.mgrid[0 : stamp.shape[0], 0 : stamp.shape[1]]
    total = stamp.sum()
    return (stamp * xx).sum() / total + x0, (stamp * yy).sum() / total + y0


@settings(max_examples=40, deadline=None)
@given(
    fx=st.floats(-0.5, 0.5),
    fy=st.floats(-0.5, 0.5),
    x=st.floats(-2.5, 2.5),
    y=st.floats(-2.5, 2.5),
)
def test_centroid_of_symmetric_psf_matches_truth(renderer, airy_optics, fx, fy, x, y):
    cov = np.array([[[30.0, 0.0], [0.0, 30.0]]])
    xp, yp = 40.0 + fx, 17.0 + fy
    stamps, x0, y0 = renderer.render_stamps(32, [xp], [yp], [x], [y], cov, [1.0])
    cx, cy = _centroid(stamps[0], x0[0], y0[0])
    assert abs(cx - xp) < 5e-4 and abs(cy - yp) < 5e-4
    assert abs(stamps[0].sum() - 1.0) < 1e-4


@pytest.mark.parametrize(
    "x,y,xp,yp,cov",
    [
        (0.7, -1.3, 20.37, 19.81, [[29.2, 1.5], [1.5, 27.2]]),
        (-1.9, 1.1, 11.5, 12.02, [[45.0, -8.0], [-8.0, 25.0]]),
        (0.0, 0.0, 7.0, 9.0, [[0.0, 0.0], [0.0, 0.0]]),  # singular kernel: the bare PSF
    ],
)
def test_matches_brute_force_reference(variable_optics, x, y, xp, yp, cov):
    r = StarRenderer(variable_optics.psf_grid, SCALE, RenderParams(oversampling=2))
    cov = np.array(cov)
    stamps, _, _ = r.render_stamps(32, [xp], [yp], [x], [y], cov[None], [1.0])
    ref = brute_force_stamp(variable_optics.psf_grid, x, y, cov, xp, yp, SCALE, 32)
    assert np.abs(stamps[0] - ref).max() <= 1e-3 * ref.max()


def test_no_oversampling_is_measurably_worse(variable_optics):
    """oversampling=1 ignores aliasing: the knob must matter (and 2 must be better)."""
    cov = np.array([[[0.0, 0.0], [0.0, 0.0]]])
    errs = []
    for k in (1, 2):
        r = StarRenderer(variable_optics.psf_grid, SCALE, RenderParams(oversampling=k))
        stamps, x0, y0 = r.render_stamps(32, [10.31], [9.77], [0.5], [0.5], cov, [1.0])
        cx, cy = _centroid(stamps[0], x0[0], y0[0])
        errs.append(np.hypot(cx - 10.31, cy - 9.77))
    assert errs[1] < 1e-4
    assert errs[0] > 3 * errs[1]


def test_float32_and_nearest_knobs(airy_optics):
    cov = np.array([[[25.0, 0.0], [0.0, 25.0]]])
    args = ([10.2], [10.9], [0.4], [0.4], cov, [1e6])
    ref, _, _ = StarRenderer(airy_optics.psf_grid, SCALE).render_stamps(24, *args)
    f32, _, _ = StarRenderer(
        airy_optics.psf_grid, SCALE, RenderParams(dtype="float32")
    ).render_stamps(24, *args)
    assert f32.dtype == np.float32
    assert np.abs(f32 - ref).max() < 1e-5 * ref.max()
    near = StarRenderer(airy_optics.psf_grid, SCALE, RenderParams(psf_interpolation="nearest"))
    out, _, _ = near.render_stamps(24, *args)
    assert abs(out.sum() - 1e6) < 1e-4 * 1e6


def test_stamp_sizes_grow_with_flux_and_are_bounded(renderer):
    flux = np.array([0.0, 1e2, 1e4, 1e6, 1e8, 1e10])
    sizes = renderer.stamp_sizes(flux, 10.0, np.full(6, 5.0))
    assert np.all(np.diff(sizes) >= 0)
    assert sizes[0] >= renderer.params.min_stamp
    assert sizes[-1] == renderer.max_stamp(5.0) > sizes[1]
    # the cube (129 mas) plus kernel fits in the largest stamp
    assert renderer.max_stamp(5.0) * SCALE >= 129 + 10 * 5.0


def test_bright_star_wing_below_threshold_at_stamp_edge(renderer):
    """The light beyond a star's stamp (wrapped inside) is below the threshold."""
    cov = np.array([[[30.0, 0.0], [0.0, 30.0]]])
    noise, flux = 10.0, 1e7
    m = int(renderer.stamp_sizes([flux], noise, [5.5])[0])
    big = renderer.max_stamp(5.5) * 2
    stamp = np.zeros((1, big, big))
    renderer.render(stamp[0], [big / 2], [big / 2], [0.0], [0.0], cov, [flux], [big], noise)
    c = big // 2
    inner = stamp[0][c - m // 2 : c + m // 2, c - m // 2 : c + m // 2]
    outside = stamp[0].copy()
    outside[c - m // 2 : c + m // 2, c - m // 2 : c + m // 2] = 0
    assert outside.max() < renderer.params.stamp_threshold * noise
    assert inner.sum() > flux * 0.99


def test_square_wing_gets_square_stamp_holding_it():
    """An AO-like PSF (core + a square halo out to the control radius): the stamp is
    sized on the square radius, smaller than the disc a radial criterion needs, and
    the light beyond it (truth: the star rendered on a stamp four times wider) stays
    below the threshold."""
    from render_helpers import AnalyticPSFGrid

    half_side = 150.0  # mas: the square halo's half side (20 pixels)

    def profile(dx, dy, nx, ny):
        core = np.exp(-(dx**2 + dy**2) / (2 * 6.0**2))
        square = (np.maximum(abs(dx), abs(dy)) <= half_side) * 1e-4
        return core + square

    nodes = np.array([0.0])
    grid = AnalyticPSFGrid(profile, nodes, nodes, n=129, pixel_scale=3.75)
    r = StarRenderer(grid, SCALE, RenderParams())
    cov = np.array([[[20.0, 0.0], [0.0, 20.0]]])
    noise, flux = 1.0, 1e5
    m = int(r.stamp_sizes([flux], noise, [np.sqrt(20.0)], [0.0], [0.0])[0])
    big = 4 * m
    image = np.zeros((big, big))
    c = big // 2
    r.render(image, [c + 0.3], [c - 0.2], [0.0], [0.0], cov, [flux], [big], noise)
    threshold = r.params.stamp_threshold * noise
    lit = np.argwhere(image > threshold) - c
    disc = np.hypot(lit[:, 0], lit[:, 1]).max()  # radius of the lit disc, pixels
    assert m / 2 < disc  # a disc-sized stamp would be larger
    outside = image.copy()
    outside[c - m // 2 : c + m // 2, c - m // 2 : c + m // 2] = 0
    assert 0 < outside.max() < threshold


def test_render_clips_stamps_at_edges_and_skips_outside(renderer):
    """A small frame equals the matching crop of a larger frame (edges, corners)."""
    cov = np.tile(np.diag([30.0, 30.0]), (5, 1, 1))
    xp = np.array([0.0, 5.3, -40.0, 20.0, 31.4])
    yp = np.array([0.0, 30.0, 5.0, 20.0, -3.2])
    flux = np.array([1.0, 2.0, 3.0, 0.0, 5.0])
    sizes = np.full(5, 24)
    small = np.zeros((32, 32))
    rendered = renderer.render(small, xp, yp, xp * 0, yp * 0, cov, flux, sizes)
    assert rendered.tolist() == [True, True, False, True, True]
    big = np.zeros((160, 160))
    renderer.render(big, xp + 64, yp + 64, xp * 0, yp * 0, cov, flux, sizes)
    assert np.allclose(small, big[64:96, 64:96], rtol=0, atol=1e-6)
    assert np.isfinite(small).all()
    assert abs(big.sum() - 11.0) < 1e-5


@pytest.mark.parametrize("real,cplx", [(np.float32, np.complex64), (np.float64, np.complex128)])
def test_compiled_kernel_matches_numpy_reference(real, cplx):
    from mavispm.simulate.render.stamp_kernels import mix_kernel_fold, mix_kernel_fold_numpy

    rng = np.random.default_rng(1)
    s, n, nodes, n_out = 7, 300, 9, 50
    transforms = (rng.normal(size=(nodes, n)) + 1j * rng.normal(size=(nodes, n))).astype(cplx)
    node = rng.integers(0, nodes, (s, 4))
    w = rng.random((s, 4)).astype(real)
    coef = (-rng.random((s, 3)) * 500).astype(real)
    u = rng.normal(0, 0.05, n).astype(real)
    v = rng.normal(0, 0.05, n).astype(real)
    phx = np.exp(1j * rng.random((s, 20))).astype(cplx)
    phy = np.exp(1j * rng.random((s, 40))).astype(cplx)
    col, row = rng.integers(0, 20, n), rng.integers(0, 40, n)
    target = rng.integers(0, n_out, n)  # several samples fold onto one frequency
    a = np.zeros((s, n_out), dtype=cplx)
    b = np.zeros((s, n_out), dtype=np.complex128)
    step = np.zeros(n, dtype=bool)  # scattered samples: no runs of columns
    mix_kernel_fold(transforms, node, w, coef, u, v, 0.0, step, phx, phy, col, row, target, a)
    mix_kernel_fold_numpy(transforms, node, w, coef, u, v, 0.0, step, phx, phy, col, row, target, b)
    tol = 1e-5 if real is np.float32 else 1e-12
    assert np.abs(a - b).max() <= tol * np.abs(b).max()


@pytest.mark.parametrize("real,cplx", [(np.float32, np.complex64), (np.float64, np.complex128)])
@pytest.mark.parametrize("n_j", [1, 3, 4])
@pytest.mark.parametrize("wide", [False, True])
def test_run_kernel_matches_numpy_reference(real, cplx, n_j, wide):
    """The run-wise pass (the renderer's) against an exp per sample and sparse products:
    a stamp plan's layout (rows of a disc, the fold's two column blocks, several samples
    folding onto one frequency), narrow to extreme anisotropic kernels (the last one's
    exponent falls below -700 at the runs' ends, and the factor exp(q0 + i d1) of the
    factorised Gaussian would overflow along others: the exact-exp path); any number of
    nodes (four: the one-pass mixing). ``wide``: kernels of sigma 60-200 mas."""
    from mavispm.simulate.render.stamp_kernels import (
        fold_runs,
        mix_kernel_fold_numpy,
        mix_kernel_fold_runs,
        mix_scratch,
    )
    from mavispm.simulate.render.stamps import _folding_frequencies

    m, scale = 112, 7.5
    fy, fx = _folding_frequencies(m, 2)
    df = 1.0 / (m * scale)
    rows, cols = np.nonzero(np.hypot(fy[:, None], fx[None, :]) * df < 0.09)
    u, v = fx[cols] * df, fy[rows] * df
    target = ((rows % m) * (m // 2 + 1) + (cols % (m // 2 + 1))).astype(np.int64)
    runs = fold_runs(cols, rows, target, fx)
    assert runs[:, 4].sum() == len(u) and runs[:, 4].max() > 50
    assert len(np.unique(target)) < len(target)  # aliases fold onto shared frequencies
    rng = np.random.default_rng(7)
    cov = KERNEL_COVARIANCES
    if wide:
        cov = np.asarray([[[v, 0.3 * v], [0.3 * v, 0.8 * v]] for v in (4e3, 1e4, 2e4, 4e4)])
    s, nodes, n = len(cov), 6, len(u)
    transforms = (rng.normal(size=(nodes, n)) + 1j * rng.normal(size=(nodes, n))).astype(cplx)
    node = rng.integers(0, nodes, (s, n_j))
    w = rng.random((s, n_j)).astype(real)
    coef = (cov.reshape(s, 4)[:, [0, 1, 3]] * [1.0, 2.0, 1.0] * (-2.0 * np.pi**2)).astype(real)
    phx = np.exp(2j * np.pi * rng.random((s, len(fx)))).astype(cplx)
    phy = np.exp(2j * np.pi * rng.random((s, len(fy)))).astype(cplx)
    a = np.zeros((s, m * (m // 2 + 1)), dtype=cplx)
    a[:, 3] = 1.0  # added into
    b = np.zeros((s, m * (m // 2 + 1)), dtype=np.complex128)
    b[:, 3] = 1.0
    args = (fx * df, fy * df, df, phx, phy, runs, a.view(real))
    mix_kernel_fold_runs(transforms, node, w, coef, *args, mix_scratch(transforms, fx, runs, real))
    step = np.zeros(n, dtype=bool)
    ref = (u, v, df, step, phx, phy, cols, rows, target, b)
    mix_kernel_fold_numpy(transforms, node, w, coef.astype(np.float64), *ref)
    tol = 1e-6 if real is np.float32 else 1e-12
    for k in range(s):  # each star against its own scale (the wide kernels are tiny)
        assert np.abs(a[k] - b[k]).max() <= tol * np.abs(b[k]).max(), k


@pytest.mark.parametrize("real,cplx", [(np.float32, np.complex64), (np.float64, np.complex128)])
def test_compiled_kernel_recurrence_along_columns_matches_numpy_reference(real, cplx):
    """Samples on a frequency grid in runs of consecutive columns (a stamp plan's layout:
    rows of a disc, the fold's two column blocks), wide and narrow anisotropic kernels:
    the compiled pass's Gaussian recurrence along the runs against an exp per sample."""
    from mavispm.simulate.render.stamp_kernels import mix_kernel_fold, mix_kernel_fold_numpy
    from mavispm.simulate.render.stamps import _column_steps, _folding_frequencies

    m, scale = 144, 7.5
    fy, fx = _folding_frequencies(m, 2)
    df = 1.0 / (m * scale)
    rows, cols = np.nonzero(np.hypot(fy[:, None], fx[None, :]) * df < 0.0705)
    u, v = fx[cols] * df, fy[rows] * df
    step = _column_steps(fx[cols], rows)
    assert step.mean() > 0.9  # long runs (up to ~75 steps)
    rng = np.random.default_rng(4)
    s, nodes, n = 6, 5, len(u)
    transforms = (rng.normal(size=(nodes, n)) + 1j * rng.normal(size=(nodes, n))).astype(cplx)
    node = rng.integers(0, nodes, (s, 4))
    w = rng.random((s, 4)).astype(real)
    cov = KERNEL_COVARIANCES[:6]
    coef = (cov.reshape(s, 4)[:, [0, 1, 3]] * [1.0, 2.0, 1.0] * (-2.0 * np.pi**2)).astype(real)
    phx = np.exp(1j * rng.random((s, len(fx)))).astype(cplx)
    phy = np.exp(1j * rng.random((s, len(fy)))).astype(cplx)
    target = ((rows % m) * (m // 2 + 1) + (cols % (m // 2 + 1))).astype(np.int64)
    a = np.zeros((s, m * (m // 2 + 1)), dtype=cplx)
    b = np.zeros((s, m * (m // 2 + 1)), dtype=np.complex128)
    args = (u.astype(real), v.astype(real), df, step, phx, phy, cols, rows, target)
    mix_kernel_fold(transforms, node, w, coef, *args, a)
    mix_kernel_fold_numpy(transforms, node, w, coef, *args, b)
    tol = 1e-6 if real is np.float32 else 1e-12
    for i in range(s):  # each star against its own largest value
        assert np.abs(a[i] - b[i]).max() <= tol * np.abs(b[i]).max()


@pytest.mark.parametrize("cplx", [np.complex64, np.complex128])
def test_phase_ramps_match_complex_exponential(cplx):
    """The recurrence-built ramps against numpy's exp of every phase (long ramps of a
    512-pixel stamp's folding frequencies, both signs, shifts across the stamp)."""
    from mavispm.simulate.render.stamps import _folding_frequencies, _phase_ramps

    m, scale = 512, 7.5
    df = 1.0 / (m * scale)
    fy, fx = _folding_frequencies(m, 2)
    shift = np.random.default_rng(5).uniform(0, m * scale, 9)
    for freq in (fx, fy):
        got = _phase_ramps(shift, freq, df, cplx)
        assert got.dtype == cplx
        want = np.exp(-2j * np.pi * df * np.outer(shift, freq))
        tol = 3e-7 if cplx is np.complex64 else 1e-12
        assert np.abs(got - want).max() < tol


def test_compiled_stamp_adder_clips_like_slicing():
    from mavispm.simulate.render.stamp_kernels import add_stamps

    rng = np.random.default_rng(3)
    image = rng.random((20, 30))
    expected = image.copy()
    stamps = rng.random((4, 8, 8)).astype(np.float32)
    x0 = np.array([-3, 25, 5, -10], dtype=np.int64)
    y0 = np.array([-2, 15, 6, 0], dtype=np.int64)  # last one misses the image
    for stamp, cx, cy in zip(stamps, x0, y0):
        ya, yb, xa, xb = max(cy, 0), min(cy + 8, 20), max(cx, 0), min(cx + 8, 30)
        if ya < yb and xa < xb:
            expected[ya:yb, xa:xb] += stamp[ya - cy : yb - cy, xa - cx : xb - cx]
    add_stamps(image, stamps, x0, y0)
    assert np.allclose(image, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("n,m,ratio", [(427, 128, 4), (427, 16, 4), (21, 10, 4), (35, 24, 1)])
def test_fft_node_transforms_equal_direct_dft(n, m, ratio):
    """Wrapping + FFT gives the exact DFT, also when the PSF is wider than the stamp."""
    from mavispm.simulate.render.stamps import (
        _folding_frequencies,
        _node_transforms_dft,
        _node_transforms_fft,
    )

    cube = np.random.default_rng(n + m).random((3, n, n))
    fy, fx = _folding_frequencies(m, 2)
    period = m * ratio
    direct = _node_transforms_dft(cube, 1.0 / period, fy, fx)
    # alone, and sharing the FFTs of a period 4 times longer (sampled every 4th frequency)
    (fast,) = _node_transforms_fft(cube, [(period, fy, fx)])
    _, shared = _node_transforms_fft(cube, [(4 * period, fy, fx), (period, fy, fx)])
    for result in (fast, shared):
        assert np.abs(result - direct).max() <= 1e-12 * np.abs(direct).max()


def test_wing_envelope_cache_equals_fresh_computation(airy_optics, tmp_path):
    from mavispm.simulate.render.stamps import _wing_envelope

    first = StarRenderer(airy_optics.psf_grid, SCALE, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("stampenv*-*.npz"))) == 1
    again = StarRenderer(airy_optics.psf_grid, SCALE, cache_dir=tmp_path)
    cube = np.asarray(airy_optics.psf_grid.cube, float)
    fresh = _wing_envelope(cube.reshape(-1, *cube.shape[2:]), first.psf_pixel_scale, SCALE)
    for a, b, c in zip(first._envelope, again._envelope, fresh):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, c)
    flux = np.array([1e2, 1e4, 1e6])
    np.testing.assert_array_equal(
        again.stamp_sizes(flux, 1.0, np.full(3, 5.0)), first.stamp_sizes(flux, 1.0, np.full(3, 5.0))
    )


@settings(max_examples=60, deadline=None)
@given(
    flux=st.lists(st.one_of(st.just(0.0), st.floats(1.0, 1e8)), min_size=1, max_size=200),
    size=st.integers(1, 64),
    f64=st.one_of(st.just(np.inf), st.floats(1.0, 1e8)),
)
def test_flux_batches_cover_stars_in_order_and_keep_accuracy_classes(flux, size, f64):
    """Batches are consecutive, bounded, span <= BATCH_FLUX_SPAN, never straddle float64,
    and as large as those rules allow: a batch ends only when it is full, when the next
    star is BATCH_FLUX_SPAN above its faintest, or when the next star needs float64."""
    from mavispm.simulate.render.stamps import BATCH_FLUX_SPAN, _flux_batches

    flux = np.sort(np.asarray(flux))
    idx = np.arange(len(flux)) + 7
    batches = _flux_batches(idx, flux, size, f64)
    assert np.array_equal(np.concatenate(batches), idx)
    # brute force, star by star: a star joins the open batch while it has room, is below
    # the batch's faintest x BATCH_FLUX_SPAN and on the same side of the float64 flux
    expected, open_batch = [], []
    for i, f in enumerate(flux):
        if open_batch:
            lo = max(flux[open_batch[0]], 1e-300)
            joins = len(open_batch) < size and (
                f < lo * BATCH_FLUX_SPAN and f < f64 if lo < f64 else f <= lo * BATCH_FLUX_SPAN
            )
            if not joins:
                expected.append(open_batch)
                open_batch = []
        open_batch.append(i)
    expected.append(open_batch)
    assert [len(b) for b in batches] == [len(e) for e in expected]
    for b in batches:
        f = flux[b - 7]
        assert len(b) == 1 or f.max() <= f.min() * BATCH_FLUX_SPAN
        assert (f >= f64).all() or (f < f64).all()
    for b, after in zip(batches[:-1], batches[1:]):
        f, nxt = flux[b - 7], flux[after[0] - 7]
        full = len(b) == size
        assert full or nxt >= f.min() * BATCH_FLUX_SPAN or f.max() < f64 <= nxt


def test_mixed_flux_field_within_threshold_of_high_accuracy_render(airy_optics):
    """Faint and very bright stars in one call: every pixel within the noise budget.

    Reference: the same stars rendered one by one in float64 with no spectrum floor
    (no floor or precision is chosen per batch there); the batched default render may
    differ from it by at most ``stamp_threshold`` x noise per pixel.
    """
    rng = np.random.default_rng(3)
    n, noise = 60, 0.3
    flux = 10 ** rng.uniform(2, 7.5, n)
    xp, yp = rng.uniform(20, 140, n), rng.uniform(20, 140, n)
    xf, yf = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
    cov = np.tile(np.diag([20.0, 12.0]), (n, 1, 1))
    fast = StarRenderer(airy_optics.psf_grid, SCALE, RenderParams(batch_size=16))
    sizes = fast.stamp_sizes(flux, noise, np.full(n, 4.5), xf, yf)
    image = np.zeros((160, 160))
    fast.render(image, xp, yp, xf, yf, cov, flux, sizes, noise_sigma=noise)
    exact = StarRenderer(
        airy_optics.psf_grid, SCALE, RenderParams(dtype="float64", spectrum_floor=0.0)
    )
    ref = np.zeros((160, 160))
    for i in range(n):
        exact.render(ref, xp[i : i + 1], yp[i : i + 1], xf[i : i + 1], yf[i : i + 1],
                     cov[i : i + 1], flux[i : i + 1], sizes[i : i + 1])  # fmt: skip
    assert np.abs(image - ref).max() < fast.params.stamp_threshold * noise
    assert abs(image.sum() - ref.sum()) < 1e-6 * flux.sum()


@pytest.mark.parametrize("threads", [1, 3])
def test_reused_batch_buffers_give_the_stamps_of_fresh_arrays(airy_optics, threads):
    """Many small batches of three stamp sizes through the reused buffers (more batches
    than buffers, sizes growing and shrinking): the image equals the sum of each star's
    stamp computed alone into fresh arrays."""
    rng = np.random.default_rng(8)
    n = 40
    xp, yp = rng.uniform(20, 80, n), rng.uniform(20, 80, n)
    xf, yf = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
    cov = np.tile(np.diag([20.0, 12.0]), (n, 1, 1))
    flux = 10 ** rng.uniform(1, 4, n)
    sizes = rng.choice([16, 24, 32], n)
    r = StarRenderer(airy_optics.psf_grid, SCALE, RenderParams(batch_size=3, threads=threads))
    image = np.zeros((100, 100))
    r.render(image, xp, yp, xf, yf, cov, flux, sizes)
    ref = np.zeros((100, 100))
    for i in range(n):
        m = int(sizes[i])
        one = [a[i : i + 1] for a in (xp, yp, xf, yf, cov, flux)]
        stamp, x0, y0 = r.render_stamps(m, *one)
        ref[y0[0] : y0[0] + m, x0[0] : x0[0] + m] += stamp[0]
    assert np.abs(image - ref).max() < 1e-6 * flux.max()


@pytest.mark.parametrize("cplx", [np.complex64, np.complex128])
def test_batch_transform_columns_equal_the_plan_columns(airy_optics, tmp_path, cplx):
    """The batches' node transforms, taken from the kept copy of the columns in use
    (extended as batches need more, from a plan memory-mapped from the disk cache),
    equal the plan's columns cast to the batch's type, C-contiguous."""
    StarRenderer(airy_optics.psf_grid, SCALE, RenderParams(), tmp_path).plan(24)  # on disk
    r = StarRenderer(airy_optics.psf_grid, SCALE, RenderParams(), tmp_path)
    plan = r.plan(24)
    n = plan.transforms.shape[1]
    rng = np.random.default_rng(5)
    first = np.sort(rng.choice(n, n // 3, replace=False))
    selections = [
        first,
        first[::2],  # a subset
        np.sort(rng.choice(n, n // 2, replace=False)),  # partly new columns
        np.arange(n),  # all
        first[:1],
    ]
    for sel in selections:
        got = r._typed_columns(plan, cplx, sel)
        assert got.flags.c_contiguous and got.dtype == cplx
        assert np.array_equal(got, np.asarray(plan.transforms)[:, sel].astype(cplx))


@settings(max_examples=80, deadline=None)
@given(
    height=st.integers(2, 64),
    ny=st.integers(1, 400),
    data=st.data(),
)
def test_bands_of_one_parity_touch_disjoint_image_rows(height, ny, data):
    """The band layout of the fused render + add: every star in one band, the even bands
    then the odd ones, left to right inside a band, and two bands of the same parity never
    reach the same image row (so they can be added in parallel in any order), for stamps
    up to the band height centred anywhere, also beyond the image. Checked against the
    stamps' rows."""
    from mavispm.simulate.render.stamps import _band_order

    n = data.draw(st.integers(1, 60))
    cy = np.asarray(data.draw(st.lists(st.integers(-height, ny + height), min_size=n, max_size=n)))
    cx = np.asarray(data.draw(st.lists(st.integers(-50, 50), min_size=n, max_size=n)))
    m = np.asarray(data.draw(st.lists(st.integers(1, height // 2), min_size=n, max_size=n))) * 2
    n_bands = max(1, -(-ny // height))
    order, bounds = _band_order(cx, cy, height, n_bands)
    assert sorted(order) == list(range(n))
    # the even bands first, then the odd ones, each a consecutive run of stars
    ranked = list(range(0, n_bands, 2)) + list(range(1, n_bands, 2))
    assert bounds[ranked[0], 0] == 0 and bounds[ranked[-1], 1] == n
    for a, b in zip(ranked[:-1], ranked[1:]):
        assert bounds[a, 1] == bounds[b, 0]
    rows = []  # image rows each band's stamps reach
    for k in range(n_bands):
        members = order[bounds[k, 0] : bounds[k, 1]]
        assert np.all(np.diff(cx[members]) >= 0)
        assert np.all(np.clip(cy[members] // height, 0, n_bands - 1) == k)
        reach = set()
        for i in members:
            reach |= set(range(max(cy[i] - m[i] // 2, 0), min(cy[i] + m[i] // 2, ny)))
        rows.append(reach)
    for k in range(n_bands):
        for j in range(k + 2, n_bands, 2):
            assert not rows[k] & rows[j], (k, j)


@settings(max_examples=150, deadline=None)
@given(counts=st.lists(st.integers(0, 30), min_size=1, max_size=8), parts=st.integers(1, 4))
def test_band_groups_split_one_parity_at_band_boundaries_into_balanced_runs(counts, parts):
    """A parity's bands are handed to the threads as at most one run of consecutive bands
    per thread: the runs cover its stars in order, each is non-empty and cut at a band
    boundary (so runs touch disjoint rows), and the largest holds at most one band more
    than the best cut into ``parts`` runs (truth: every way of cutting, brute force)."""
    from itertools import combinations

    from mavispm.simulate.render.stamps import _band_groups

    assume(sum(counts) > 0)
    start = 7  # the parity's stars start after the other parity's
    edges = start + np.concatenate([[0], np.cumsum(counts)])
    runs = np.stack([edges[:-1], edges[1:]], axis=1)
    groups = _band_groups(runs, parts)
    assert len(groups) <= parts
    # the parity is split between threads exactly when it can be: > 1 part, > 1 non-empty band
    assert (len(groups) > 1) == (parts > 1 and np.count_nonzero(counts) > 1)
    assert groups[0][0] == start and groups[-1][1] == edges[-1]
    for (_, hi), (lo2, _) in zip(groups[:-1], groups[1:]):
        assert hi == lo2
    assert all(hi > lo and lo in set(edges) for lo, hi in groups)
    inner = sorted(set(edges[1:-1]))
    best = min(
        max(np.diff([start, *cut, edges[-1]]))
        for k in range(min(parts - 1, len(inner)) + 1)
        for cut in combinations(inner, k)
    )
    assert max(hi - lo for lo, hi in groups) <= best + max(counts)


def test_banded_render_equals_the_sum_of_single_stamps_on_any_thread_count(airy_optics):
    """Many bands (a tall image, stamps of three sides), stars on and beyond every edge,
    batches of a few stars and of more than SPLIT_BANDS_STARS (bands on several threads):
    the image is the sum of each star's stamp rendered alone and added by slicing (to
    float64 round-off), the same bit for bit on 1, 2 and 3 threads."""
    rng = np.random.default_rng(11)
    n, ny, nx = 300, 260, 70
    xp, yp = rng.uniform(-12, nx + 12, n), rng.uniform(-12, ny + 12, n)
    xf, yf = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
    cov = np.tile(np.diag([20.0, 12.0]), (n, 1, 1))
    flux = 10 ** rng.uniform(2, 2.9, n)  # one flux class: batches of batch_size stars
    sizes = rng.choice([16, 24, 32], n)
    images = []
    for threads in (1, 2, 3):
        for batch in (7, 100):
            r = StarRenderer(
                airy_optics.psf_grid, SCALE, RenderParams(batch_size=batch, threads=threads)
            )
            image = np.zeros((ny, nx))
            r.render(image, xp, yp, xf, yf, cov, flux, sizes)
            images.append(image)
    for k in (2, 4):  # the same batches on 2 and 3 threads
        np.testing.assert_array_equal(images[0], images[k])
        np.testing.assert_array_equal(images[1], images[k + 1])
    ref = np.zeros((ny + 64, nx + 64))  # margin: stamps beyond the edges, cropped after
    for i in range(n):
        m = int(sizes[i])
        one = [a[i : i + 1] for a in (xp, yp, xf, yf, cov, flux)]
        stamp, x0, y0 = r.render_stamps(m, *one)
        ref[y0[0] + 32 : y0[0] + 32 + m, x0[0] + 32 : x0[0] + 32 + m] += stamp[0]
    ref = ref[32 : 32 + ny, 32 : 32 + nx]
    for image in images[:2]:
        assert np.abs(image - ref).max() <= 1e-13 * flux.max()


@pytest.mark.parametrize(
    "cov", [[[4.0, 0.0], [0.0, 4.0]], [[9.0, 3.0], [3.0, 2.0]], [[1.5, 0.0], [0.0, 6.0]]]
)
def test_blurred_wing_envelope_bounds_the_blurred_psf(cov):
    """The blurred envelope that sizes the stamps bounds the PSF convolved with a Gaussian
    kernel (any covariance with the given largest sigma) at every pixel's square radius.
    Truth: a PSF with a core, a square plateau cut sharply (as the MAVIS database's taper)
    and a faint ring, convolved directly with the Gaussian density on the pixel lattice
    (a linear convolution; 1-pixel PSF samples)."""
    from mavispm.simulate.render.stamps import BLUR_SIGMA_STEP, _sizing_envelopes, _wing_envelope

    n = 81
    yy, xx = np.mgrid[0:n, 0:n] - (n - 1) / 2
    cheb = np.maximum(abs(xx), abs(yy))
    psf = np.exp(-(xx**2 + yy**2) / 8.0) + 1e-3 * (cheb <= 25) + 2e-4 * (abs(cheb - 32) < 1)
    psf /= psf.sum()
    radii, env = _wing_envelope(psf[None], 1.0, 1.0)
    cov = np.asarray(cov)
    sigma = float(np.sqrt(np.linalg.eigvalsh(cov)[-1]))
    steps = int(np.ceil(sigma / BLUR_SIGMA_STEP))
    r_out, bound = _sizing_envelopes(radii, env, steps, BLUR_SIGMA_STEP)[-1]
    assert np.all(np.diff(bound[0]) <= 0)
    h = 40  # kernel half side: 12 sigma
    ky, kx = np.mgrid[-h : h + 1, -h : h + 1]
    icov = np.linalg.inv(cov)
    quad = icov[0, 0] * kx**2 + 2 * icov[0, 1] * kx * ky + icov[1, 1] * ky**2
    kernel = np.exp(-0.5 * quad) / (2 * np.pi * np.sqrt(np.linalg.det(cov)))
    size = n + 2 * h
    spec = np.fft.rfft2(psf, (size, size)) * np.fft.rfft2(kernel, (size, size))
    blurred = np.fft.irfft2(spec, (size, size))  # linear: no wrap-around
    yq, xq = np.mgrid[0:size, 0:size] - (size - 1) / 2
    r_q = np.maximum(abs(xq), abs(yq))
    k = np.minimum(np.floor(r_q / 0.5).astype(int), len(r_out) - 1)
    assert np.all(blurred <= bound[0][k] * (1 + 1e-9) + 1e-15)
    # and it is the blur that the bound follows: the unblurred envelope is exceeded
    # just beyond the plateau's sharp edge
    k0 = np.minimum(np.floor(r_q / 0.5).astype(int), len(radii) - 1)
    assert np.any(blurred > env[0][k0] * 1.1 + 1e-15)


def test_stamp_holds_the_blurred_wing_and_no_more():
    """A PSF whose wing ends sharply (a square plateau, like the MAVIS PSF database's
    tapered edge) under a wide kernel: the stamp reaches past the plateau by what the
    blurred edge needs (~3 sigma at this flux), not by a fixed 4 sigma margin, and the
    light beyond it (truth: the star on a stamp four times wider) stays below the
    threshold."""
    from render_helpers import AnalyticPSFGrid

    half_side = 150.0  # mas: 20 pixels

    def profile(dx, dy, nx, ny):
        core = np.exp(-(dx**2 + dy**2) / (2 * 6.0**2))
        return core + (np.maximum(abs(dx), abs(dy)) <= half_side) * 1e-4

    nodes = np.array([0.0])
    grid = AnalyticPSFGrid(profile, nodes, nodes, n=129, pixel_scale=3.75)
    r = StarRenderer(grid, SCALE, RenderParams())
    sigma = 3.0 * SCALE  # mas
    cov = np.array([[[sigma**2, 0.0], [0.0, sigma**2]]])
    noise, flux = 1.0, 1e5
    m = int(r.stamp_sizes([flux], noise, [sigma], [0.0], [0.0])[0])
    # the plateau (20 px) + ~3 sigma (9 px) + 1.5: 64 px; with 4 sigma added to the
    # unblurred radius (20 + 12 + 1.5) it was 80
    assert m <= 64
    big = 4 * m
    image = np.zeros((big, big))
    c = big // 2
    r.render(image, [c + 0.3], [c - 0.2], [0.0], [0.0], cov, [flux], [big], noise)
    outside = image.copy()
    outside[c - m // 2 : c + m // 2, c - m // 2 : c + m // 2] = 0
    assert 0 < outside.max() < r.params.stamp_threshold * noise


@pytest.mark.parametrize("cplx", [np.complex64, np.complex128])
@pytest.mark.parametrize("m", [112, 120])
def test_inverse_rfft2_into_matches_numpy_irfft2(cplx, m):
    """The stamps' inverse transform (scipy's pocketfft module loaded on its own) against
    numpy's ``irfft2`` of the same folded spectra: the same values, bit for bit; the fast
    path is the one taken here (scipy is installed; the warm frames program imports no
    ``scipy.fft``: ``test_startup.py``)."""
    from mavispm.simulate.render import stamp_kernels
    from mavispm.simulate.render.stamp_kernels import inverse_rfft2_into

    rng = np.random.default_rng(m)
    mh = m // 2 + 1
    spec = (rng.normal(size=(5, m, mh)) + 1j * rng.normal(size=(5, m, mh))).astype(cplx)
    want = np.fft.irfft2(spec, s=(m, m), axes=(1, 2)).astype(spec.real.dtype)
    work = spec.copy()
    got = np.empty((5, m, m), dtype=spec.real.dtype)
    inverse_rfft2_into(work, got, m)
    assert np.array_equal(got, want)
    assert stamp_kernels._pocketfft_module  # loaded and checked
