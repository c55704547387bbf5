"""Blind PSF-aware detection on frames whose PSF has a speckled ring.

The frame is synthesised here (independent of the project's renderer): every
star has a Gaussian core plus a ring of six lobes at 4.5 pixels holding 6 % of
its light, the structure that made a plain peak finder report false stars
around bright ones. The truth list scores the detections.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from measure_helpers import Detector, mag_to_flux, noisy_frame, write_frames

from mavispm.core.products import read_product
from mavispm.measure.stars import psf_detection
from mavispm.measure.stars.cli import run_stage
from mavispm.measure.stars.detection import detection_scores

SHAPE = (220, 220)
FAST = {"psf_grid": 2, "psf_stars_per_node": 12, "psf_star_min_snr": 50.0, "epsf_iterations": 5}
SIGMA = 1.1
RING = (4.5, 0.7, 0.15)  # radius [pix], width [pix], flux fraction
LOBES = (8, 2)  # number of speckle lobes on the ring, sharpness (power of the modulation)


#: Mean of the lobe modulation over the ring (normalises the ring's light).
LOBE_MEAN = float(np.mean((1 + np.cos(LOBES[0] * np.linspace(0, 2 * np.pi, 4096))) ** LOBES[1]))


def _prf(dx, dy):
    """Core + speckled ring, unit flux, sampled at pixel centres (sub-sampled 4 x 4)."""
    total = 0.0
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    for ox in sub:
        for oy in sub:
            x, y = dx + ox, dy + oy
            r = np.hypot(x, y)
            core = np.exp(-0.5 * r**2 / SIGMA**2) / (2 * np.pi * SIGMA**2)
            lobes = (1 + np.cos(LOBES[0] * np.arctan2(y, x))) ** LOBES[1] / LOBE_MEAN
            ring = lobes * np.exp(-0.5 * ((r - RING[0]) / RING[1]) ** 2)
            ring /= 2 * np.pi * RING[0] * RING[1] * np.sqrt(2 * np.pi)
            total = total + (1 - RING[2]) * core + RING[2] * ring
    return total / 16


def _render(x, y, flux, rad=9):
    img = np.zeros(SHAPE)
    for xi, yi, fi in zip(x, y, flux):
        cx, cy = int(np.rint(xi)), int(np.rint(yi))
        x0, x1 = max(cx - rad, 0), min(cx + rad + 1, SHAPE[1])
        y0, y1 = max(cy - rad, 0), min(cy + rad + 1, SHAPE[0])
        cols, rows = np.arange(x0, x1) - xi, np.arange(y0, y1) - yi
        img[y0:y1, x0:x1] += fi * _prf(cols[None, :], rows[:, None])
    return img


@pytest.fixture(scope="module")
def ring_frame(tmp_path_factory):
    rng = np.random.default_rng(8)
    n = 160
    x, y = rng.uniform(6, 214, n), rng.uniform(6, 214, n)
    mag = np.concatenate([rng.uniform(15.5, 18.0, 40), rng.uniform(18.0, 25.0, n - 40)])
    path = tmp_path_factory.mktemp("det") / "ring.h5"
    det = Detector(saturation=1e9)
    write_frames(path, SHAPE, x, y, mag, SYNTH, det=det, seed=4)
    # replace the image by the ringed PSF's (same noise model)
    image, sat = noisy_frame(_render(x, y, mag_to_flux(mag)), det, rng)
    import h5py

    with h5py.File(path, "a") as f:
        f["image"][...] = image
        f["saturated"][...] = sat
    return path, x, y, mag


class _Synth:  # write_frames needs a PSF to render a placeholder image
    sigma, gradient, profile = SIGMA, 0.0, "gaussian"

    def widths(self, x, y, shape):
        return np.full(np.shape(x), SIGMA), np.full(np.shape(x), SIGMA)

    def prf(self, dx, dy, sx, sy):
        return _prf(dx, dy)


SYNTH = _Synth()


@pytest.mark.slow  # two whole blind stages (~25 s on an idle machine)
def test_psf_detector_rejects_ring_structure(ring_frame, tmp_path, monkeypatch):
    path, x, y, mag = ring_frame
    cfg = {**FAST, "blind": True, "detection_fwhm": "2.6 pix"}
    # the ePSF describes the speckled ring imperfectly: subtracting stars and
    # detecting on the residuals without the measured model error and the local
    # noise scale (and without the wing term beyond the footprint) finds the ring's
    # left-overs as stars
    with monkeypatch.context() as m:
        m.setattr(psf_detection, "model_error_profile", lambda *a, **k: np.zeros(32))
        m.setattr(psf_detection, "noise_scale", lambda snr, tile: np.ones_like(snr))
        plain = run_stage(path, {**cfg, "detection_wing_radius": 0}, tmp_path / "plain.h5")
    plain_false = (np.asarray(read_product(plain, "measured").tables["stars"]["flag"]) & 16) != 0
    assert plain_false.mean() > 0.2
    out = run_stage(path, cfg, tmp_path / "psf.h5")
    prod = read_product(out, "measured")
    assert prod.attrs["start"] == "detected"
    false = (np.asarray(prod.tables["stars"]["flag"]) & 16) != 0
    assert false.mean() <= 0.05
    assert prod.attrs["detect_false_fraction_v26"] <= 0.05
    by_mag = json.loads(prod.attrs["detect_scores"])["by_mag"]
    hi = by_mag["edges"][1:]
    found = np.asarray(by_mag["n_found"])
    true = np.asarray(by_mag["n_true"])
    bright = np.array([h is not None and h <= 20 for h in hi])
    mid = np.array([h == 22 for h in hi])
    assert found[bright].sum() >= 0.85 * true[bright].sum()  # flux SNR > 300
    assert found[mid].sum() >= 0.8 * true[mid].sum()  # flux SNR 50-300, some in rings


def test_detection_scores_by_bin():
    """Counts per bin on a hand-made list: two true stars found, one missed, one false."""
    xt, yt = np.array([10.0, 50.0, 90.0]), np.array([10.0, 50.0, 90.0])
    mag = np.array([18.5, 23.0, 26.5])
    x, y = np.array([10.2, 50.1, 130.0]), np.array([10.0, 49.8, 130.0])
    flux = 10 ** (-0.4 * (np.array([18.5, 23.0, 21.0]) - 30.0))
    r_true, r_det = np.array([0.5, 1.5, 3.0]), np.array([0.5, 1.5, 5.0])
    s = detection_scores(x, y, flux, xt, yt, mag, 1.0, r_det, r_true)
    assert s["zero_point"] == pytest.approx(30.0)
    assert s["false_fraction_v26"] == pytest.approx(1 / 3)
    m = s["by_mag"]
    assert sum(m["n_true"]) == 3 and sum(m["n_found"]) == 2
    assert m["n_false"][m["edges"].index(20.0)] == 1  # the false one at m = 21
    r = s["by_radius"]
    assert r["n_false"][r["edges"].index(4.0)] == 1 and r["n_found"][0] == 1
