"""The ``threads`` knob: the stars stage's chunks on a thread pool, the same results bit for bit.

Scenes from ``measure_helpers`` (exact pixel-integrated PSFs, Poisson and read noise),
crowded enough that the stamps of stars of one colour share corner pixels (the colouring
separates stars by ``2 radius + 1`` px in distance, not per axis), with small chunks so
that every colour has many. The tables must be identical for 1, 2 and 3 threads and
agree with the rendered truth; a spy on the pool shows two threads at work at once.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from measure_helpers import (
    Detector,
    SynthPSF,
    mag_to_flux,
    noisy_frame,
    render_image,
    robust_sigma,
    true_epsf,
    write_frames,
)
from test_measure_crowded_convergence import DET, PSF, RN2, SHAPE  # the crowded scene's frame

from mavispm.core import cores
from mavispm.core.errors import ConfigError
from mavispm.measure.stars import chunk_pool
from mavispm.measure.stars.batched_fit import FLAG_FAILED, FitOptions, fit_stars
from mavispm.measure.stars.cli import validate_settings
from mavispm.measure.stars.crlb import crlb
from mavispm.measure.stars.measure_frame import measure_frame, read_frame


def _crowded(seed=4, n=200):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(6, SHAPE[1] - 7, n), rng.uniform(6, SHAPE[0] - 7, n)
    mag = rng.uniform(17, 25, n)
    image, sat = noisy_frame(render_image(SHAPE, x, y, mag_to_flux(mag), PSF), DET, rng)
    return image * DET.gain, sat, x, y, mag


def _fit(threads, image, sat, x0, y0):
    options = FitOptions(
        iterations=15, relative_tolerance=0.2, chunk=8, flux_passes=3,
        flux_refresh=True, check_cut_steps=True, crowded_window=4, threads=threads,
        bisect_reversals=True,
    )  # fmt: skip
    psf = true_epsf(PSF, SHAPE)
    return fit_stars(
        image, psf, x0, y0, read_noise_var=RN2, sky0=DET.sky, saturated=sat, options=options
    )


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape
    if a.dtype.kind == "f":  # bit for bit, NaN included
        return np.array_equal(a.view(f"u{a.itemsize}"), b.view(f"u{b.itemsize}"))
    return np.array_equal(a, b)


def test_fit_is_the_same_bit_for_bit_on_1_2_3_threads_and_near_the_truth():
    image, sat, x, y, mag = _crowded()
    rng = np.random.default_rng(11)
    x0, y0 = x + rng.normal(0, 0.1, len(x)), y + rng.normal(0, 0.1, len(x))
    # the scene is the one the test is about: same-colour stamps sharing pixels
    r = 5
    sep_x, sep_y = np.abs(x[:, None] - x), np.abs(y[:, None] - y)
    corner = (np.hypot(sep_x, sep_y) >= 2 * r + 1) & (sep_x <= 2 * r) & (sep_y <= 2 * r)
    assert corner.sum() > 20
    fits = {t: _fit(t, image, sat, x0, y0) for t in (1, 2, 3)}
    for name in ("x", "y", "flux", "sky", "x_err", "y_err", "flux_err", "sky_err", "chi2", "flag",
                 "crowding", "correlated_gain", "halo_share", "model_image", "sky_slope"):  # fmt: skip
        for t in (2, 3):
            assert _same(getattr(fits[1], name), getattr(fits[t], name)), (name, t)
    assert fits[1].iterations == fits[2].iterations == fits[3].iterations
    # and the fit is a good one: against the rendered truth, at the Cramér-Rao bound
    fit = fits[1]
    good = (mag < 22) & ((fit.flag & FLAG_FAILED) == 0)
    assert good.sum() > 50
    bound = crlb(true_epsf(PSF, SHAPE), x[good], y[good], mag_to_flux(mag[good]), DET.sky, RN2)
    z = np.r_[(fit.x[good] - x[good]) / bound[:, 0], (fit.y[good] - y[good]) / bound[:, 1]]
    assert 0.7 < robust_sigma(z) < 1.5
    zr = np.r_[(fit.x[good] - x[good]) / fit.x_err[good], (fit.y[good] - y[good]) / fit.y_err[good]]
    assert 0.7 < robust_sigma(zr) < 1.5


@pytest.fixture(scope="module")
def crowded_frame(tmp_path_factory):
    rng = np.random.default_rng(7)
    n = 400
    shape = (300, 300)
    x, y = rng.uniform(6, shape[1] - 6, n), rng.uniform(6, shape[0] - 6, n)
    mag = 16 + 10 * rng.uniform(0, 1, n) ** 0.6
    path = tmp_path_factory.mktemp("threads") / "frame.h5"
    write_frames(path, shape, x, y, mag, SynthPSF(1.3, gradient=0.25, profile="moffat"), seed=3)
    return read_frame(path)


def _stage(frame, threads):
    settings = validate_settings(
        {"psf_grid": 2, "psf_stars_per_node": 25, "psf_star_min_snr": 50.0, "epsf_iterations": 3,
         "chunk": 16, "threads": threads}
    )  # fmt: skip
    return measure_frame(frame, settings, seed=1)[0]


def test_stage_table_is_the_same_bit_for_bit_on_1_2_3_threads(crowded_frame):
    tables = {t: _stage(crowded_frame, t) for t in (1, 2, 3)}
    assert "err_epsf" in tables[1].colnames  # the ePSF error model ran (its shifts chunked)
    for t in (2, 3):
        assert tables[t].colnames == tables[1].colnames
        for name in tables[1].colnames:
            assert _same(tables[1][name], tables[t][name]), (name, t)
    # against the rendered truth: the bright stars well measured, errors honest
    stars = tables[1]
    truth = crowded_frame.truth
    ok = (np.asarray(stars["flag"]) & 48) == 0
    bright = ok & (truth["mag"].value < 21)
    dx = np.asarray(stars["x_pix"])[bright] - np.asarray(truth["x_pix"])[bright]
    assert bright.sum() > 40 and robust_sigma(dx) < 0.05
    err = stars["x_err"].value[bright] / crowded_frame.pixel_scale  # [arcsec] -> [pix]
    assert 0.5 < robust_sigma((dx - np.median(dx)) / err) < 1.6


class _SpyPool(ThreadPoolExecutor):
    """Records the pools made; the first two tasks of each must meet at a barrier (two
    threads running at once, or a BrokenBarrierError)."""

    made: list[int] = []
    idents: set[int] = set()

    def __init__(self, max_workers=None, **kw):
        _SpyPool.made.append(max_workers)
        self._barrier = threading.Barrier(2, timeout=20)
        self._started = 0
        super().__init__(max_workers=max_workers, **kw)

    def submit(self, fn, /, *args, **kwargs):
        self._started += 1
        meet = self._started <= 2

        def task(*a, **k):
            _SpyPool.idents.add(threading.get_ident())
            if meet:
                self._barrier.wait()
            return fn(*a, **k)

        return super().submit(task, *args, **kwargs)


def test_more_than_one_thread_is_used(monkeypatch):
    monkeypatch.setattr(chunk_pool, "ThreadPoolExecutor", _SpyPool)
    _SpyPool.made.clear()
    _SpyPool.idents.clear()
    image, sat, x, y, _ = _crowded(n=120)
    _fit(1, image, sat, x, y)
    assert _SpyPool.made == []  # one thread: no pool
    _fit(2, image, sat, x, y)
    assert _SpyPool.made and set(_SpyPool.made) == {2}
    assert len(_SpyPool.idents) == 2 and threading.get_ident() not in _SpyPool.idents
    # 0: every core this process may use
    _SpyPool.made.clear()
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    _fit(0, image, sat, x, y)
    assert set(_SpyPool.made) == {3}


def test_threads_knob_is_validated():
    assert validate_settings({}).threads == 0
    assert validate_settings({"knobs": {"threads": 2}}).threads == 2
    for bad in (-1, 1.5, "two"):
        with pytest.raises(ConfigError, match="threads"):
            validate_settings({"threads": bad})
    with pytest.raises(ValueError):
        chunk_pool.resolve_threads(-2)


def test_psfr_stage_is_the_same_bit_for_bit_on_1_2_3_threads(tmp_path):
    """The PSF-R build (its nodes' ePSFs and kernel fits on the pool) and the stage."""
    from measure_helpers import grid_positions
    from test_measure_psfr import PRIOR_SIGMA, SETTINGS, write_prior
    from test_measure_psfr import PSF as PSFR_PSF
    from test_measure_psfr import SHAPE as PSFR_SHAPE

    rng = np.random.default_rng(11)
    x, y = grid_positions(PSFR_SHAPE, 11, 8, rng, jitter=2.0)
    mag = rng.uniform(17.0, 24.0, len(x))
    write_frames(tmp_path / "f.h5", PSFR_SHAPE, x, y, mag, PSFR_PSF, Detector(), seed=5)
    write_prior(tmp_path / "prior.h5", PRIOR_SIGMA)
    frame = read_frame(tmp_path / "f.h5")
    tables = {}
    for t in (1, 2, 3):
        cfg = {**SETTINGS, "psf_prior": str(tmp_path / "prior.h5"), "chunk": 32, "threads": t}
        stars, attrs, _ = measure_frame(frame, validate_settings(cfg), seed=0)
        assert attrs["psf_model"] == "psfr"
        tables[t] = stars
    for t in (2, 3):
        for name in tables[1].colnames:
            assert _same(tables[1][name], tables[t][name]), (name, t)
    # against the truth: the bright stars near the bound
    stars = tables[1]
    ok = (np.asarray(stars["flag"]) & 48) == 0
    b = ok & (mag < 20)
    dx = np.asarray(stars["x_pix"])[b] - x[b]
    crlb_pix = np.median(stars["crlb_x"].value[b]) / frame.pixel_scale
    assert b.sum() > 50 and robust_sigma(dx) < 1.5 * crlb_pix


def test_error_model_shifts_are_the_same_bit_for_bit_on_1_2_3_threads():
    """``epsf_difference_shifts`` in chunks on the pool: identical rows, and the known
    shift (ePSF b is ePSF a moved by +0.02 px in x) recovered."""
    from test_measure_error_model import _gaussian_epsf

    from mavispm.measure.stars.error_model import epsf_difference_shifts
    from mavispm.measure.stars.variable_psf import constant_epsf

    psf_a = constant_epsf(_gaussian_epsf(0.0), 4)
    psf_b = constant_epsf(_gaussian_epsf(0.02), 4)
    rng = np.random.default_rng(2)
    n = 150
    x, y = rng.uniform(10, 190, n), rng.uniform(10, 190, n)
    flux = 10 ** rng.uniform(4, 6, n)
    args = (psf_a, psf_a, psf_b, x, y, flux, np.full(n, 50.0), 36.0, 5, 16)
    out = {t: epsf_difference_shifts(*args, threads=t) for t in (1, 2, 3)}
    assert _same(out[1], out[2]) and _same(out[1], out[3])
    np.testing.assert_allclose(out[1][:, 0], 0.02, rtol=0.05)
    np.testing.assert_allclose(out[1][:, 1], 0.0, atol=1e-4)
