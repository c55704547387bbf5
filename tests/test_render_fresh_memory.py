"""The frames program's fresh memory (helper render16) against independent references.

* the noise drawn over the image itself (``expose_stack(out=mean)``) equals the draw into
  a new array bit for bit, on every tier (Gaussian, skew-corrected, exact Poisson,
  per-sub-exposure saturation) and any thread count, and allocates no full-frame array
  (tracemalloc); ``render_stack`` without the noise-free stack draws it in place;
* the renderer's kept plan columns equal numpy's cast of the taken columns and are made
  without a complex128 copy of them; a batch that takes every kept column gets them
  without a copy;
* an all-False boolean array (the saturation mask) is stored as HDF5's fill value and
  reads back equal; a mask with a saturated pixel is written as before.
"""

from __future__ import annotations

import tracemalloc

import h5py
import numpy as np
import pytest

from mavispm.simulate.render import detector


def _scene_means(n: int, seed: int = 2) -> np.ndarray:
    """Sub-exposure means over the tiers: sky, skewed stars, exact tier, saturating cores."""
    rng = np.random.default_rng(seed)
    mean = rng.uniform(0.0, 60.0, n).astype(np.float32)
    mean[::97] = rng.uniform(500.0, 3000.0, mean[::97].size)  # skew-corrected tier
    mean[::1013] = rng.uniform(8e4, 2e5, mean[::1013].size)  # near and beyond saturation
    mean[5] = 0.0
    return mean


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("skew, poisson", [(0.01, 0.1), (0.0, None), (0.01, 0.012)])
def test_noise_drawn_over_the_image_equals_the_draw_into_a_new_array(threads, skew, poisson):
    n = 2 * detector.NOISE_CHUNK + 1000  # three chunks, the last partial
    settings = detector.DetectorSettings(nx=n, ny=1, read_noise=3.0, gain=1.7)
    mean = _scene_means(n).reshape(1, n)
    args = (24, settings)
    kw = dict(noise=True, skew_limit=skew, threads=threads, poisson_skew_limit=poisson)
    ref, ref_sat = detector.expose_stack(mean.copy(), *args, np.random.default_rng(5), **kw)
    image = mean.copy()
    got, sat = detector.expose_stack(image, *args, np.random.default_rng(5), out=image, **kw)
    assert got is image  # the stack is the image's memory
    assert ref_sat.any() and (~ref_sat).any()  # saturation acts per sub-exposure here
    np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32))
    np.testing.assert_array_equal(sat, ref_sat)
    # noise off: the clipped noise-free stack, in place too
    quiet = mean.copy()
    q_ref, q_sat_ref = detector.expose_stack(mean, *args, None, noise=False)
    q, q_sat = detector.expose_stack(quiet, *args, None, noise=False, out=quiet)
    assert q is quiet
    np.testing.assert_array_equal(q, q_ref)
    np.testing.assert_array_equal(q_sat, q_sat_ref)


def test_noise_drawn_over_the_image_allocates_no_frame():
    ny, nx = 2048, 2048  # 16 MB of float32 means, 16 chunks
    mean = _scene_means(ny * nx, seed=4).reshape(ny, nx)
    settings = detector.DetectorSettings(nx=nx, ny=ny)
    kw = dict(skew_limit=0.01, poisson_skew_limit=0.1, threads=2)
    detector.expose_stack(mean.copy(), 24, settings, np.random.default_rng(1), **kw)  # compiled
    peaks = {}
    for name in ("new", "in place"):
        image = mean.copy()
        tracemalloc.start()
        detector.expose_stack(
            image,
            24,
            settings,
            np.random.default_rng(1),
            out=image if name == "in place" else None,
            **kw,
        )
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    # a new stack: the float32 frame (16 MB) and the bool mask (4 MB); in place: the mask
    # and the buffers of the chunks being drawn (~2 MB each)
    assert peaks["new"] > mean.nbytes
    assert peaks["in place"] < 0.75 * mean.nbytes


def test_out_overlapping_the_means_otherwise_is_refused():
    buffer = np.ones(30, dtype=np.float32)
    mean, shifted = buffer[:24].reshape(4, 6), buffer[6:].reshape(4, 6)
    settings = detector.DetectorSettings(nx=6, ny=4)
    with pytest.raises(ValueError, match="overlaps"):
        detector.expose_stack(mean, 2, settings, np.random.default_rng(0), out=shifted)
    with pytest.raises(ValueError, match="float32"):
        detector.expose_stack(mean, 2, settings, np.random.default_rng(0), out=np.ones((4, 6)))


def test_stack_without_noiseless_draws_the_noise_over_the_image(monkeypatch):
    import astropy.units as u
    from render_helpers import random_epoch, tiptilt_halo_optics

    from mavispm.simulate.render import cli, frame
    from mavispm.simulate.render.scene import scene_from_mapping

    optics = tiptilt_halo_optics()
    ny = nx = 1024  # 4 MB float32 frame, 4 noise chunks
    scene = scene_from_mapping(
        {"detector": {"nx": nx, "ny": ny}, "nexp": 4, "render": {"threads": 1}}
    )
    t = random_epoch(12, 2.5)
    args = (t, 0.0 * u.yr, scene, optics)
    grown = []
    plain = frame.expose_stack

    def traced(*a, **k):  # the memory the noise draw adds at its peak
        tracemalloc.start()
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        try:
            return plain(*a, **k)
        finally:
            grown.append(tracemalloc.get_traced_memory()[1] - before)
            tracemalloc.stop()

    monkeypatch.setattr(frame, "expose_stack", traced)
    full = frame.render_stack(*args, cli.epoch_rng(5, "e0"), noiseless=True)
    lean = frame.render_stack(*args, cli.epoch_rng(5, "e0"), noiseless=False)
    np.testing.assert_array_equal(lean.adu, full.adu)
    frame_bytes = ny * nx * 4
    assert grown[0] > frame_bytes  # the noise-free stack kept: a new frame for the noise
    assert grown[1] < 0.6 * frame_bytes  # drawn over the image: the mask and chunk buffers


@pytest.mark.parametrize("cplx", [np.complex64, np.complex128])
def test_kept_plan_columns_are_the_cast_columns_without_a_complex128_copy(cplx):
    from types import SimpleNamespace

    from mavispm.simulate.render.stamps import StarRenderer

    rng = np.random.default_rng(6)
    nodes, samples = 49, 40_000
    transforms = rng.normal(size=(nodes, samples)) + 1j * rng.normal(size=(nodes, samples))
    plan = SimpleNamespace(m=64, transforms=transforms)
    cols = np.sort(rng.choice(samples, 30_000, replace=False))
    holder = SimpleNamespace(_typed={})
    tracemalloc.start()
    StarRenderer._keep_columns(holder, plan, cplx, cols)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    kept_plan, kept_cols, typed = holder._typed[(64, np.dtype(cplx).str)]
    assert kept_plan is plan
    np.testing.assert_array_equal(kept_cols, cols)
    assert typed.dtype == cplx and typed.flags.c_contiguous
    ref = transforms[:, cols].astype(cplx)  # numpy's cast of the taken columns
    np.testing.assert_array_equal(typed, ref)
    # the kept array and a row block of the cast: no copy of all the columns on the way
    assert peak < 1.2 * typed.nbytes
    # a batch taking every kept column gets the kept array; a subset is a copy of its columns
    holder.plan = lambda m: plan
    holder._keep_columns = lambda p, c, s: StarRenderer._keep_columns(holder, p, c, s)
    every = StarRenderer._typed_columns(holder, plan, cplx, cols)
    assert every is typed
    some = cols[::3]
    part = StarRenderer._typed_columns(holder, plan, cplx, some)
    assert not np.shares_memory(part, typed)
    np.testing.assert_array_equal(part, transforms[:, some].astype(cplx))


def test_all_false_mask_is_stored_as_the_fill_value(tmp_path):
    from mavispm.core.products import read_product, write_product

    clear = np.zeros((300, 400), dtype=bool)
    hit = clear.copy()
    hit[17, 230] = True
    image = np.arange(12.0, dtype=np.float32).reshape(3, 4)
    write_product(tmp_path / "p.h5", "frames", arrays={"clear": clear, "hit": hit, "image": image})
    with h5py.File(tmp_path / "p.h5") as f:
        assert f["clear"].id.get_storage_size() == 0  # nothing written
        assert f["hit"].id.get_storage_size() == hit.nbytes
        assert f["clear"].dtype == bool and f["clear"].shape == clear.shape
    back = read_product(tmp_path / "p.h5").arrays
    np.testing.assert_array_equal(back["clear"], clear)
    assert back["clear"].dtype == bool
    np.testing.assert_array_equal(back["hit"], hit)
    np.testing.assert_array_equal(back["image"], image)
