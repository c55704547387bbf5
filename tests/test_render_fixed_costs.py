"""The per-frame fixed costs of ``simulate frames`` against brute-force references.

* the halo's cloud-in-cell deposit (one ``np.bincount``) against a point-by-point loop;
* the wrapped halo kernel against ``np.roll`` of the zero-padded kernel;
* the halo's convolution in one real grid and one spectrum against numpy's ``rfft2`` /
  ``irfft2`` (bit for bit), allocating only the spectrum;
* the halo's bilinear interpolation (rows shared between fine rows, optionally
  filling the frame with the sky in the same pass) against per-pixel interpolation;
* the compiled float32 standard normals of the noise draw against numpy's sampler,
  and the stack noise drawn with them against the same draw made with numpy.
"""

from __future__ import annotations

import tracemalloc
import zlib

import numpy as np
import pytest
from render_helpers import chunk_normals

from mavispm.simulate.render import detector
from mavispm.simulate.render.halo_convolution import (
    _bilinear_into,
    _convolve_spectrum,
    _linear_interpolation_weights,
    _wrap_kernel,
    add_bilinear,
    deposit_cic,
    halo_field,
)


def _cic_loop(shape, x, y, w):
    field = np.zeros(shape)
    ny, nx = shape
    for xi, yi, wi in zip(x, y, w):
        x0, y0 = int(np.floor(xi)), int(np.floor(yi))
        fx, fy = xi - x0, yi - y0
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                if 0 <= x0 + dx < nx and 0 <= y0 + dy < ny:
                    field[y0 + dy, x0 + dx] += wi * wx * wy
    return field


@pytest.mark.parametrize("strided, low", [(False, -2.0), (True, -2.0), (False, 5.0), (True, 5.0)])
def test_cic_deposit_equals_point_by_point_loop(strided, low):
    rng = np.random.default_rng(4)
    shape = (23, 31)
    n = 400
    # some cells partly or wholly outside; low = 5: none in the first rows
    x = rng.uniform(low, shape[1] + 1.0, n)
    y = rng.uniform(low, shape[0] + 1.0, n)
    x[:20], y[:20] = 7.25, 3.5  # many points in one cell
    x[20], y[20] = shape[1] - 1.0, shape[0] - 1.0  # on the last pixel centre
    w = rng.uniform(0.1, 5.0, n)
    if strided:  # a view that is not C-contiguous
        base = np.zeros((shape[0], 2 * shape[1]))
        field = base[:, ::2]
    else:
        field = np.zeros(shape)
    field += 1.0  # added into, not overwritten
    deposit_cic(field, x, y, w)
    ref = _cic_loop(shape, x, y, w) + 1.0
    np.testing.assert_allclose(field, ref, rtol=1e-13, atol=1e-13)


def test_cic_deposit_of_nothing_or_only_outside_points_leaves_the_field():
    field = np.full((5, 6), 2.0)
    deposit_cic(field, np.zeros(0), np.zeros(0), np.zeros(0))
    deposit_cic(field, np.array([-5.0, 40.0]), np.array([1.0, 2.0]), np.array([1.0, 1.0]))
    np.testing.assert_array_equal(field, 2.0)


@pytest.mark.parametrize("kshape, fshape", [((5, 7), (12, 9)), ((9, 9), (9, 9)), ((3, 1), (4, 6))])
def test_wrapped_kernel_equals_rolled_padding(kshape, fshape):
    kernel = np.random.default_rng(1).random(kshape)
    padded = np.zeros(fshape)
    padded[: kshape[0], : kshape[1]] = kernel
    ref = np.roll(padded, (-(kshape[0] // 2), -(kshape[1] // 2)), axis=(0, 1))
    np.testing.assert_array_equal(_wrap_kernel(kernel, fshape), ref)


def _bilinear_reference(coarse, ylo, yfrac, xlo, xfrac):
    """Per-pixel bilinear interpolation, the arithmetic of the original kernel."""
    ncy, ncx = coarse.shape
    r0, c0 = ylo[:, None], xlo[None, :]
    r1, c1 = np.minimum(r0 + 1, ncy - 1), np.minimum(c0 + 1, ncx - 1)
    fx, fy = xfrac[None, :], yfrac[:, None]
    top = coarse[r0, c0] + fx * (coarse[r0, c1] - coarse[r0, c0])
    bot = coarse[r1, c0] + fx * (coarse[r1, c1] - coarse[r1, c0])
    return top + fy * (bot - top)


@pytest.mark.parametrize("b", [1, 3, 8])
def test_bilinear_pass_equals_per_pixel_interpolation(b):
    rng = np.random.default_rng(b)
    ny, nx = 37, 45
    ncy, ncx = -(-ny // b), -(-nx // b)
    coarse = rng.random((ncy, ncx))
    ylo, yfrac = _linear_interpolation_weights(ny, ncy, b)
    xlo, xfrac = _linear_interpolation_weights(nx, ncx, b)
    ref = _bilinear_reference(coarse, ylo, yfrac, xlo, xfrac)
    out = np.full((ny, nx), 0.5)
    add_bilinear(out, coarse, ylo, yfrac, xlo, xfrac)
    np.testing.assert_array_equal(out, 0.5 + ref)  # same operations: the same bits
    filled = np.full((ny, nx), np.nan)
    _bilinear_into(filled, coarse, ylo, yfrac, xlo, xfrac, 0.5, False, np.empty((2, nx)))
    np.testing.assert_array_equal(filled, 0.5 + ref)
    # rows in any order (the shared coarse rows are recomputed when the row changes)
    perm = rng.permutation(ny)
    shuffled = np.zeros((ny, nx))
    _bilinear_into(
        shuffled, coarse, ylo[perm], yfrac[perm], xlo, xfrac, 0.0, True, np.empty((2, nx))
    )
    np.testing.assert_array_equal(shuffled, ref[perm])


class _BoxHalo:
    """A halo whose kernel is a normalised box (any centred kernel will do)."""

    def kernel(self, pixel_scale_mas):
        k = np.zeros((9, 9))
        k[2:7, 3:6] = 1.0
        return k / k.sum()


@pytest.mark.parametrize("b", [1, 4])
def test_halo_field_fill_equals_fill_then_add(b):
    rng = np.random.default_rng(2)
    shape = (48, 40)
    x = rng.uniform(-3, shape[1] + 3, 30)
    y = rng.uniform(-3, shape[0] + 3, 30)
    flux = rng.uniform(1, 100, 30)
    added = np.full(shape, 7.0)
    halo_field(x, y, flux, shape, _BoxHalo(), 7.5, b, out=added)
    filled = halo_field(x, y, flux, shape, _BoxHalo(), 7.5, b, out=np.empty(shape), fill=7.0)
    np.testing.assert_array_equal(filled, added)
    assert (added > 7.0).mean() > 0.3  # the halo lights much of the frame
    # no star near the frame: the sky alone
    empty = halo_field(
        np.array([1e4]), np.array([1e4]), np.ones(1), shape, _BoxHalo(), 7.5, b, fill=3.0
    )
    np.testing.assert_array_equal(empty, 3.0)


@pytest.mark.parametrize("fshape", [(240, 256), (225, 250)])
def test_halo_convolution_in_two_buffers_equals_numpys_2d_transforms(fshape):
    """The halo's convolution (one-axis passes into one real grid and one spectrum) equals
    ``irfft2(rfft2(field, fshape) * spectrum, fshape)`` bit for bit; given the grid it
    allocates the spectrum alone (numpy's 2-D transforms make a fresh array per pass)."""
    rng = np.random.default_rng(5)
    field = rng.uniform(0, 1e4, (fshape[0] - 31, fshape[1] - 17))
    kspec = np.fft.rfft2(rng.uniform(0, 1, fshape))
    ny, nx = field.shape
    want = np.fft.irfft2(np.fft.rfft2(field, fshape) * kspec, fshape)[:ny, :nx]
    np.testing.assert_array_equal(_convolve_spectrum(field, kspec, fshape), want)
    grid = np.zeros(fshape)
    grid[:ny, :nx] = field
    tracemalloc.start()
    try:
        got = _convolve_spectrum(grid[:ny, :nx], kspec, fshape, grid=grid)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(got, want)
    assert np.shares_memory(got, grid)
    assert kspec.nbytes <= peak < 1.25 * kspec.nbytes


#: The first noise chunk of epoch "e0", seed 0 (the frames command's generator): numba's
#: own float32 sampler (its wedge test rounds ``exp`` to float32) leaves numpy's stream
#: at draw 64,137 of it.
_FRAMES_E0_CHUNK0 = np.random.SeedSequence([0, zlib.crc32(b"e0")]).spawn(1)[0]


@pytest.mark.skipif(not detector._COMPILED_NORMALS, reason="numba without Generator access")
@pytest.mark.parametrize("seed", [0, 1, _FRAMES_E0_CHUNK0])
def test_compiled_float32_normals_are_numpys(seed):
    # ~2e6 draws pass through the ziggurat's wedge and tail tests many times
    ours, numpys = np.random.default_rng(seed), np.random.default_rng(seed)
    got = chunk_normals(ours, 2_000_000)
    ref = numpys.standard_normal(2_000_000, dtype=np.float32)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, ref)
    assert ours.random() == numpys.random()  # the generator continues where numpy's would


def test_stack_noise_equals_the_draw_made_with_numpys_sampler():
    rng = np.random.default_rng(8)
    n = 2 * detector.NOISE_CHUNK + 1000  # three chunks, the last partial
    mean = rng.uniform(0.0, 60.0, n)
    mean[::97] = rng.uniform(500.0, 3000.0, mean[::97].size)  # where the skew correction acts
    settings = detector.DetectorSettings(nx=n, ny=1, read_noise=3.0)
    nexp, skew, poisson = 120, 0.01, 0.1
    got, sat = detector.expose_stack(
        mean.reshape(1, n), nexp, settings, np.random.default_rng(5), True, skew, 2, poisson
    )
    # the reference: one numpy generator per chunk, spawned as expose_stack does
    var_rn = nexp * settings.read_noise**2
    ref = np.empty(n, dtype=np.float32)
    parent = np.random.default_rng(5)
    starts = range(0, n, detector.NOISE_CHUNK)
    for start, crng in zip(starts, parent.spawn(len(starts))):
        sl = slice(start, start + detector.NOISE_CHUNK)
        z = crng.standard_normal(mean[sl].size, dtype=np.float32)
        lam = np.maximum(mean[sl], 0.0) * nexp
        sd = np.sqrt(lam + var_rn)
        g = lam / sd**3
        a = np.where(g >= skew, g / 6.0, 0.0)
        ref[sl] = lam + sd * (z + a * (z * z - 1.0)) / np.sqrt(1.0 + 2.0 * a * a)
    assert not sat.any()
    assert np.any(mean * nexp / (mean * nexp + var_rn) ** 1.5 >= skew)  # the tier is used
    # the same normals: equal to float32 rounding of the formula
    np.testing.assert_allclose(got.ravel(), ref, rtol=1e-6, atol=1e-3)


def test_stack_without_noiseless_has_the_same_image_and_truth():
    import astropy.units as u
    from render_helpers import random_epoch, tiptilt_halo_optics

    from mavispm.simulate.render import cli
    from mavispm.simulate.render.frame import render_stack
    from mavispm.simulate.render.scene import scene_from_mapping

    optics = tiptilt_halo_optics()
    scene = scene_from_mapping({"detector": {"nx": 72, "ny": 64}, "nexp": 4})
    t = random_epoch(12, 0.25, 0.2)
    args = (t, 0.0 * u.yr, scene, optics)
    full = render_stack(*args, cli.epoch_rng(5, "e0"))
    lean = render_stack(*args, cli.epoch_rng(5, "e0"), noiseless=False)
    assert lean.noiseless is None
    assert np.array_equal(full.adu, lean.adu)
    assert np.array_equal(full.saturated, lean.saturated)
    for name in full.truth.colnames:
        assert np.array_equal(full.truth[name], lean.truth[name])
    # the kept noise-free stack is nexp sub-exposures: the image of the noise-free scene
    quiet = scene_from_mapping({"detector": {"nx": 72, "ny": 64}, "nexp": 4, "noise": False})
    clean = render_stack(t, 0.0 * u.yr, quiet, optics, cli.epoch_rng(5, "e0"))
    ok = ~clean.saturated  # the noise-free image is clipped at saturation
    assert ok.mean() > 0.9
    np.testing.assert_allclose(full.noiseless[ok], clean.adu[ok], rtol=1e-6)


def test_in_place_taper_equals_the_tapered_copy():
    from mavispm.simulate.optics.model import taper_grid
    from mavispm.simulate.optics.psf_grid import PSFGrid
    from mavispm.simulate.optics.seeing_halo import Halo

    rng = np.random.default_rng(6)
    n = 21
    cube = rng.random((2, 3, n, n))
    grid = PSFGrid(cube, np.arange(3.0), np.arange(2.0), 3.75, 550.0, np.ones((2, 3)))
    halo = Halo(np.linspace(0, 100, 50), np.ones(50), 10.0, 30.0, 40.0, 0.1)
    # brute force: each stamp times 1 - ramp, over its own sum
    yy, xx = np.mgrid[:n, :n] - n // 2
    radius = np.hypot(xx, yy) * 3.75  # mas
    from mavispm.simulate.optics.seeing_halo import ramp

    taper = 1.0 - ramp(radius, halo.ramp_start, halo.ramp_end)
    ref = cube * taper
    ref /= ref.sum(axis=(-2, -1), keepdims=True)
    copy = taper_grid(grid, halo)
    np.testing.assert_allclose(copy.cube, ref, rtol=1e-12)
    assert np.array_equal(grid.cube, cube) and copy.cube is not cube  # left alone
    same = taper_grid(grid, halo, in_place=True)
    assert same.cube is cube  # tapered where it was
    np.testing.assert_array_equal(same.cube, copy.cube)


def test_cached_tapered_cube_is_the_brute_force_taper_mapped_from_the_cache(tmp_path):
    """``cached_taper`` keeps the tapered cube next to the grid's cache file: the first
    call tapers (equal to a per-stamp brute force) and saves it, the next maps it
    read-only from there (the grid's own cube is not used: here it is another one), a
    grid file written again is tapered again; ``read_grid(mapped=True)`` maps the cube of
    a ``psfgrid`` product with the values ``read_grid`` reads."""
    import os

    from mavispm.simulate.optics.model import cached_taper
    from mavispm.simulate.optics.psf_grid import GridResult, PSFGrid, read_grid, write_grid
    from mavispm.simulate.optics.seeing_halo import Halo, ramp

    rng = np.random.default_rng(7)
    n = 21
    cube = rng.random((2, 3, n, n))
    grid = PSFGrid(cube.copy(), np.arange(3.0), np.arange(2.0), 3.75, 550.0, np.ones((2, 3)))
    halo = Halo(np.linspace(0, 100, 50), np.ones(50), 10.0, 30.0, 40.0, 0.1)
    yy, xx = np.mgrid[:n, :n] - n // 2
    ref = np.empty_like(cube)
    for iy in range(2):
        for ix in range(3):
            t = cube[iy, ix] * (1.0 - ramp(np.hypot(xx, yy) * 3.75, 10.0, 30.0))
            ref[iy, ix] = t / t.sum()
    path = tmp_path / "psfgrid-abc.h5"
    write_grid(path, GridResult(grid, np.arange(4.0), np.ones(4)), "abc")
    read, mapped = read_grid(path), read_grid(path, mapped=True)
    assert isinstance(mapped.grid.cube, np.memmap) and not mapped.grid.cube.flags.writeable
    np.testing.assert_array_equal(mapped.grid.cube, read.grid.cube)
    np.testing.assert_array_equal(mapped.grid.cube, cube)

    first = cached_taper(mapped.grid, halo, path)
    np.testing.assert_allclose(first.cube, ref, rtol=1e-12)
    np.testing.assert_array_equal(mapped.grid.cube, cube)  # the mapped file left alone
    assert len(list(tmp_path.glob("psftaper-*.npy"))) == 1
    flipped = np.ascontiguousarray(cube[:, :, ::-1, :])  # another cube (the taper is even)
    garbage = PSFGrid(flipped, grid.nodes_x, grid.nodes_y, 3.75, 550.0, grid.strehl)
    again = cached_taper(garbage, halo, path)
    assert not again.cube.flags.writeable  # mapped from the cache file
    np.testing.assert_array_equal(again.cube, first.cube)
    # the grid written again (a new modification time): tapered again, not the stale cube
    write_grid(path, GridResult(garbage, np.arange(4.0), np.ones(4)), "abc")
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    fresh = cached_taper(read_grid(path, mapped=True).grid, halo, path)
    np.testing.assert_allclose(fresh.cube, ref[:, :, ::-1, :], rtol=1e-12)
    assert len(list(tmp_path.glob("psftaper-*.npy"))) == 2


def test_cached_halo_kernel_transform_equals_the_fresh_one(tmp_path):
    from mavispm.simulate.optics.seeing_halo import Halo
    from mavispm.simulate.render import halo_convolution as hc

    radius = np.linspace(0.0, 4000.0, 400)
    halo = Halo(radius, np.exp(-radius / 500.0), 100.0, 200.0, 6000.0, 0.1)
    rng = np.random.default_rng(9)
    shape = (90, 70)
    x, y = rng.uniform(-5, 75, 40), rng.uniform(-5, 95, 40)
    flux = rng.uniform(1.0, 1e4, 40)
    args = (x, y, flux, shape)
    fresh = halo_field(*args, halo, 7.5, 8)
    hc._SPECTRA.clear()
    first = halo_field(*args, halo, 7.5, 8, cache_dir=tmp_path)  # computes and stores
    assert len(list(tmp_path.glob("halospec-*.npz"))) == 1
    hc._SPECTRA.clear()
    loaded = halo_field(*args, halo, 7.5, 8, cache_dir=tmp_path)  # read back from the file
    np.testing.assert_array_equal(first, fresh)
    np.testing.assert_array_equal(loaded, fresh)
    # brute force: the convolution of the deposited fluxes with the kernel, linear
    # (scipy), away from the rim, interpolated back as halo_field does
    import scipy.signal

    b = 8
    kernel = halo.kernel(7.5 * b)
    hk = kernel.shape[0] // 2
    ncy, ncx = -(-shape[0] // b), -(-shape[1] // b)
    padded = np.zeros((ncy + 2 * hk, ncx + 2 * hk))
    deposit_cic(padded, (x + 0.5) / b - 0.5 + hk, (y + 0.5) / b - 0.5 + hk, flux)
    coarse = scipy.signal.fftconvolve(padded, kernel, mode="same")[hk : hk + ncy, hk : hk + ncx]
    ylo, yf = _linear_interpolation_weights(shape[0], ncy, b)
    xlo, xf = _linear_interpolation_weights(shape[1], ncx, b)
    ref = _bilinear_reference(coarse / b**2, ylo, yf, xlo, xf)
    np.testing.assert_allclose(loaded, ref, rtol=0, atol=1e-10 * ref.max())
    # another halo (its fraction only) is not served the stored transform
    other = Halo(radius, halo.profile, 100.0, 200.0, 6000.0, 0.2)
    hc._SPECTRA.clear()
    doubled = halo_field(*args, other, 7.5, 8, cache_dir=tmp_path)
    np.testing.assert_allclose(doubled, 2 * fresh, rtol=1e-12)
    assert len(list(tmp_path.glob("halospec-*.npz"))) == 2


def test_stamp_plans_keyed_by_the_cached_cube_only_for_that_read_only_object(tmp_path, monkeypatch):
    """The tapered cube mapped from its cache file keys the renderer's stamp plans by the
    file's key (its bytes are not hashed); any other cube (a grid replaced with a flipped
    cube, a view, a writable copy, a read-only array whose memory can be written) is
    hashed as before, with the same key as a plain array, and renders its own content
    even where the cached cube's plans are on disk (truth: the same cube rendered
    without a cache). A writable cube cannot carry a key at all."""
    import dataclasses

    from render_helpers import make_optics

    from mavispm.core.array_cache import content_key
    from mavispm.simulate.optics.model import cached_taper
    from mavispm.simulate.optics.psf_grid import GridResult, PSFGrid, read_grid, write_grid
    from mavispm.simulate.optics.seeing_halo import Halo
    from mavispm.simulate.render import stamps
    from mavispm.simulate.render.stamps import StarRenderer

    fake = make_optics("airy", nodes=2, half_field=2.0, n=65, psf_scale=3.75).psf_grid
    nodes = np.array([-2.0, 2.0])
    grid = PSFGrid(np.array(fake.cube), nodes, nodes, 3.75, 550.0, np.ones((2, 2)))
    halo = Halo(np.linspace(0, 400, 50), np.ones(50), 60.0, 110.0, 120.0, 0.1)
    path = tmp_path / "psfgrid-abc.h5"
    write_grid(path, GridResult(grid, np.arange(4.0), np.ones(4)), "abc")
    made = cached_taper(read_grid(path, mapped=True).grid, halo, path)  # tapers, saves
    mapped = cached_taper(read_grid(path, mapped=True).grid, halo, path)
    key = mapped.cube_key
    assert made.cube_key == key  # the saved cube, keyed like the next process's
    assert key is not None and not mapped.cube.flags.writeable
    assert (tmp_path / f"{key}.npy").exists()

    hashed = []
    real = stamps.content_key

    def spy(*parts):
        hashed.append(any(isinstance(p, np.ndarray) and p.size >= 4 * 65 * 65 for p in parts))
        return real(*parts)

    monkeypatch.setattr(stamps, "content_key", spy)
    xp, yp = np.array([30.3, 61.7, 95.1]), np.array([40.6, 70.2, 88.9])
    xf, yf = np.array([-1.5, 0.2, 1.7]), np.array([1.1, -0.4, 0.9])
    cov = np.tile(np.diag([9.0, 12.0]), (3, 1, 1))
    flux = np.array([1e3, 3e4, 2e5])

    def render(g, cache):
        r = StarRenderer(g, 7.5, cache_dir=cache)
        img = np.zeros((128, 128))
        r.render(img, xp, yp, xf, yf, cov, flux, np.full(3, 48), noise_sigma=5.0)
        return r, img

    cache = tmp_path / "plans"
    first, img = render(mapped, cache)
    assert hashed == [False]  # keyed by the file's key, the cube's bytes not read
    np.testing.assert_array_equal(img, render(mapped, None)[1])
    _, again = render(mapped, cache)  # from the plans on disk
    np.testing.assert_array_equal(again, img)

    plain = np.array(mapped.cube)  # the same values, writable
    p = first.params
    legacy = real(
        stamps.PLAN_CACHE_VERSION,
        [3.75, 7.5, p.oversampling, p.spectrum_floor, stamps.PLAN_FLOOR_DECADES],
        plain.reshape(-1, 65, 65),
    )
    frozen = np.ascontiguousarray(plain[:, :, ::-1, :])  # other values, read-only flag
    frozen.flags.writeable = False
    # its memory can be written again (a writable copy, a flag turned off): no key
    for cube in (plain, frozen):
        assert dataclasses.replace(mapped, cube=cube).with_cube_key(key).cube_key is None
    others = {
        "copy": plain,
        "frozen copy": frozen,
        "view": mapped.cube[:],
        "flipped view": mapped.cube[:, :, ::-1, :],
        "other cube": np.ascontiguousarray(np.array(fake.cube)[:, :, :, ::-1]),
    }
    for name, cube in others.items():
        hashed.clear()
        other = dataclasses.replace(mapped, cube=cube)
        r, img = render(other, cache)
        assert hashed == [True], name
        if name in ("copy", "view"):
            assert r._cache_key == legacy, name
        else:
            assert r._cache_key != first._cache_key, name
        np.testing.assert_array_equal(img, render(other, None)[1], err_msg=name)
    assert content_key is real
