"""Integration: measure a frame made by the project's renderer with the real optics model."""

from __future__ import annotations

import json

import astropy.units as u
import numpy as np
import pytest
from optics_helpers import small_table
from render_helpers import epoch_table

from mavispm.core.catalogue import write_catalogue
from mavispm.core.products import read_product
from mavispm.measure.stars.cli import run_stage
from mavispm.measure.stars.measure_frame import MEASURED_SPEC

render_cli = pytest.importorskip("mavispm.simulate.render.cli")


def _render(tmp, cache, noise: bool):
    """The 49-star frame (7 x 7 jittered grid, m = 17-22) rendered with the real optics."""
    rng = np.random.default_rng(2)
    # 7 x 7 jittered grid over the 200 x 200 px (1.5 arcsec) frame
    g = (np.arange(7) - 3) * 0.19
    xx, yy = np.meshgrid(g, g)
    n = xx.size
    x = xx.ravel() + rng.uniform(-0.02, 0.02, n)
    y = yy.ravel() + rng.uniform(-0.02, 0.02, n)
    mag = rng.uniform(17.0, 22.0, n)
    cat = tmp / "cat.h5"
    write_catalogue(cat, {"e0": epoch_table(x, y, mag)})
    scene = {"noise": noise, "nexp": 2, "detector": {"nx": 200, "ny": 200}, "optics": small_table()}
    return render_cli.run_stage(cat, "e0", scene, tmp / "frames.h5", 3, cache_dir=cache)


@pytest.fixture(scope="module")
def psf_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("psf_cache")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, psf_cache):
    return _render(tmp_path_factory.mktemp("rendered"), psf_cache, noise=True)


@pytest.fixture(scope="module")
def rendered_noise_free(tmp_path_factory, psf_cache):
    return _render(tmp_path_factory.mktemp("rendered_nf"), psf_cache, noise=False)


SETTINGS = {
    "psf_variation": "constant",
    "psf_stars_per_node": 20,
    "psf_star_min_snr": 30.0,
    "psf_star_isolation": "8 pix",
    "epsf_size": 21,
}

#: Systematic allowance [mas] on the offsets: the level at which the renderer and
#: the fitter agree (the renderer's own PSF sampled as an ePSF gives < 0.01 mas on
#: the noise-free frame, docs/measure.md). The ePSF built from the noise-free frame
#: now gives error-weighted means of -0.008 +- 0.004 (x) / +0.004 +- 0.004 (y) mas;
#: +0.048 / +0.056 mas while the builder refitted and stacked its PSF stars with a
#: constant sky and the final fit used a sky plane.
SYSTEMATIC_MAS = 0.01


def _offsets(frames, tmp_path):
    out = run_stage(frames, SETTINGS, tmp_path / "measured.h5", seed=0)
    product = read_product(out, "measured", specs={"stars": MEASURED_SPEC})
    stars = product.tables["stars"]
    good = (np.asarray(stars["flag"]) & (2 | 16 | 32)) == 0  # unsaturated, matched, fitted
    return product, stars, good


def test_measure_rendered_frame(rendered, tmp_path):
    product, stars, good = _offsets(rendered, tmp_path)
    # 49 PSF stars fill 2 x 2 pixel phases well but not 4 x 4: x4 leaves the bright
    # stars at ~5 x CRLB here, x2 at ~1.3 x (docs/measure.md); "auto" chooses x2
    assert json.loads(product.attrs["epsf"])["oversampling"] == 2
    # the seeing halo (~40 % of the light here) lies outside the ePSF footprint: the
    # Cramer-Rao bound uses the flux the ePSF describes, not the total
    assert 0.3 < product.attrs["epsf_flux_fraction"] < 0.65
    truth = read_product(rendered, "frames").tables["truth"]
    assert len(stars) == len(truth)
    assert good.mean() > 0.9
    dx = (stars["x"] - stars["x_true"]).to_value(u.mas)[good]
    dy = (stars["y"] - stars["y_true"]).to_value(u.mas)[good]
    # no offset beyond the known systematic: the rendered PSF is centro-symmetric
    # about the truth. The bound on each median is 3 sigma of a median from the
    # data's own scatter (1.2533 std / sqrt(N)) plus the measured systematic
    # (SYSTEMATIC_MAS). The ePSF's own noise is common to all stars and not in
    # std / sqrt(N): render seeds 3 (this one), 4 and 5 gave medians x / y of
    # -0.012 / +0.027, -0.006 / -0.001, -0.041 / +0.030 mas against bounds of
    # 0.06-0.09 mas (std 0.10-0.15 mas); +0.040 / +0.080, +0.049 / +0.040,
    # +0.007 / +0.059 before the builder used the final fit's sky plane.
    # Before it subtracted each PSF star's local background: 0.1-0.5 mas.
    for d in (dx, dy):
        bound = 3 * 1.2533 * np.std(d) / np.sqrt(d.size) + SYSTEMATIC_MAS
        assert abs(np.median(d)) < bound, (np.median(d), bound)
    assert np.std(dx) < 0.2 and np.std(dy) < 0.2
    mag = stars["mag"].value[good]
    err_x = stars["x_err"].to_value(u.mas)[good]
    err_y = stars["y_err"].to_value(u.mas)[good]
    # the reported errors describe the scatter (calibrated normalised residuals);
    # (the ~1.4 at the faint end is also there when fitting with the true PSF)
    for sel in (mag < 19, mag > 20.5):
        z = np.concatenate([dx[sel] / err_x[sel], dy[sel] / err_y[sel]])
        assert 0.7 < np.std(z) < 1.7
    # bright stars (PSF stars themselves) come close to their Cramer-Rao bound: the
    # ePSF is built from these 49 stars, so its own noise adds; over 8 noise
    # realisations of this frame (exact Poisson and the tiered noise alike) the ~10
    # bright stars gave rms / CRLB = 1.3-2.05. The frame's median offset (a common
    # shift from the ePSF's noise and residual bias, up to ~2 x CRLB) is removed
    # first: the median test above bounds it
    bright = mag < 19
    scatter = np.concatenate([dx[bright] - np.median(dx), dy[bright] - np.median(dy)])
    rms = np.sqrt(np.mean(scatter**2))
    assert rms < 2.5 * np.median(stars["crlb_x"].to_value(u.mas)[good][bright])


def _weighted_offset(stars, good, axis):
    """Error-weighted mean offset [mas] and its sandwich uncertainty (the residuals' scatter)."""
    d = (stars[axis] - stars[f"{axis}_true"]).to_value(u.mas)[good]
    w = 1.0 / stars[f"{axis}_err"].to_value(u.mas)[good] ** 2
    mean = np.sum(w * d) / np.sum(w)
    return mean, np.sqrt(np.sum(w**2 * (d - mean) ** 2)) / np.sum(w)


def test_measure_rendered_noise_free_offset(rendered_noise_free, tmp_path):
    """Noise-free frame: error-weighted mean offset within 3 sigma + SYSTEMATIC_MAS.

    Any offset beyond the renderer / fitter agreement is the ePSF built from the
    frame; the old +0.048 / +0.056 mas (x / y) fails here.
    """
    _, stars, good = _offsets(rendered_noise_free, tmp_path)
    assert good.mean() > 0.9
    for axis in ("x", "y"):
        mean, sigma = _weighted_offset(stars, good, axis)
        assert abs(mean) < 3 * sigma + SYSTEMATIC_MAS, (axis, mean, sigma)
