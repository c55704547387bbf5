"""PSF-R model (prior from the optics' PSF grid + fitted kernel), docs/measure.md.

References are independent of the code under test: the analytic pixel-integrated
Gaussian (error functions), the independent frame synthesiser of
``measure_helpers`` and the truth table of the frames.
"""

from __future__ import annotations

import json

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable
from measure_helpers import (
    Detector,
    SynthPSF,
    gaussian_cube,
    grid_positions,
    write_frames,
    write_prior,
)
from scipy.special import ndtr

from mavispm.core.errors import InputError
from mavispm.core.products import read_product, write_product
from mavispm.measure.stars.cli import run_stage
from mavispm.measure.stars.error_model import estimate_error_model
from mavispm.measure.stars.psf_reconstruction import (
    NodeTransform,
    blur_core,
    model_epsf,
    read_prior,
    stretch_psf,
)

SCALE = 7.36  # detector pixel [mas] (measure_helpers.Detector)
SUB = SCALE / 4  # prior sampling [mas]


def test_model_epsf_is_the_pixel_integrated_convolution():
    """Gaussian prior (x) Gaussian kernel (x) pixel box against the error-function PRF."""
    s0, cxx, cyy = 5.0, 30.0, 12.0  # mas, mas^2
    node = NodeTransform.of(gaussian_cube(s0), SUB)
    epsf = model_epsf(node, (cxx, cyy, 0.0), SCALE, 15, 4)
    sx, sy = np.sqrt(s0**2 + cxx) / SCALE, np.sqrt(s0**2 + cyy) / SCALE  # pixels
    off = (np.arange(epsf.shape[0]) - (epsf.shape[0] - 1) / 2) / 4
    fx = ndtr((off + 0.5) / sx) - ndtr((off - 0.5) / sx)
    fy = ndtr((off + 0.5) / sy) - ndtr((off - 0.5) / sy)
    exact = fy[:, None] * fx[None, :]
    assert np.max(np.abs(epsf - exact)) < 1e-4 * exact.max()
    # a kernel with a correlation term: the PRF is no longer separable, the moments tell
    tilted = model_epsf(node, (30.0, 30.0, 20.0), SCALE, 15, 4)
    xx, yy = np.meshgrid(off, off)
    w = tilted / tilted.sum()
    cov_xy = np.sum(w * xx * yy) * SCALE**2
    assert cov_xy == pytest.approx(20.0, rel=0.03)
    # a stretch k of the prior: the prior's sigma becomes k s0
    stretched = model_epsf(node, (cxx, cyy, 0.0, 1.1), SCALE, 15, 4)
    sx, sy = np.sqrt((1.1 * s0) ** 2 + cxx) / SCALE, np.sqrt((1.1 * s0) ** 2 + cyy) / SCALE
    fx = ndtr((off + 0.5) / sx) - ndtr((off - 0.5) / sx)
    fy = ndtr((off + 0.5) / sy) - ndtr((off - 0.5) / sy)
    exact = fy[:, None] * fx[None, :]
    assert np.max(np.abs(stretched - exact)) < 1e-4 * exact.max()


def test_stretch_psf_scales_the_width():
    psf = gaussian_cube(6.0)
    wide = stretch_psf(psf, 1.05)
    r = (np.arange(101) - 50) * SUB
    var = np.sum(wide.sum(axis=0) * r**2)
    assert np.sqrt(var) == pytest.approx(6.0 * 1.05, rel=2e-3)
    assert wide.sum() == pytest.approx(1.0)


def test_blur_core_moves_the_light():
    """Second moment of (1 - e) G(s0) + e G(s0) (x) G(b): s0^2 + e b^2 (analytic)."""
    s0, e, b = 6.0, 0.1, 15.0
    out = blur_core(gaussian_cube(s0, n=201), e, b / SUB)
    r = (np.arange(201) - 100) * SUB
    assert np.sum(out.sum(axis=0) * r**2) == pytest.approx(s0**2 + e * b**2, rel=2e-3)
    peak = (1 - e) + e * s0**2 / (s0**2 + b**2)  # the peak (Strehl) ratio of the two Gaussians
    assert out.max() / gaussian_cube(s0, n=201).max() == pytest.approx(peak, rel=0.01)


def test_model_error_floor_and_relative_chi2():
    """The PSF-R error terms: Fisher x max(chi2 / chi2_typ, 1) plus beta sigma_F^2 (chi2_typ - 1)."""
    rng = np.random.default_rng(0)
    flux = np.geomspace(1e3, 1e7, 400)
    typical = 1.0 + flux / 1e5  # chi^2 grows with flux (a symmetric misfit)
    chi2 = typical * rng.uniform(0.8, 1.25, flux.size)
    sig = 1.0 / np.sqrt(flux)
    ok = np.ones(flux.size, bool)
    plain = estimate_error_model(flux, chi2, ok, None, relative_chi2=True)
    assert np.all(plain.chi2_inflation == plain.chi2_ratio)  # not max(chi2, 1)
    assert np.median(plain.chi2_inflation[flux > 1e6]) < 1.2  # bright stars: ~1, not ~10-100
    beta = 0.02
    floor = estimate_error_model(
        flux, chi2, ok, None, relative_chi2=True, floor_fraction=beta, fisher_position=sig
    )
    want = np.sqrt(beta * np.maximum(typical - 1, 0)) * sig
    bright = flux > 1e5
    np.testing.assert_allclose(floor.position[bright], want[bright], rtol=0.2)


def test_prior_input_is_validated(tmp_path):
    good = tmp_path / "good.h5"
    write_prior(good, 5.0)
    prior = read_prior(good, (0.5, 1.5), (-1.0, 1.0), 0.0)
    assert prior.cube.shape[:2] == (3, 2)  # the nodes bracketing the frame
    assert list(prior.nodes_x) == [0.0, 2.0]
    no_cube = tmp_path / "no_cube.h5"
    write_product(
        no_cube,
        "psfgrid",
        arrays={"nodes_x": np.zeros(1), "nodes_y": np.zeros(1)},
        attrs={"pixel_scale": SUB * u.mas},
    )
    with pytest.raises(InputError, match=r"no_cube\.h5.*'cube' missing"):
        read_prior(no_cube, (-1, 1), (-1, 1), 0.0)
    bad_shape = tmp_path / "bad_shape.h5"
    write_product(
        bad_shape,
        "psfgrid",
        arrays={"cube": np.ones((2, 2, 10, 10)), "nodes_x": np.zeros(2), "nodes_y": np.zeros(2)},
        attrs={"pixel_scale": SUB * u.mas},
    )
    with pytest.raises(InputError, match=r"bad_shape\.h5.*'cube' has shape"):
        read_prior(bad_shape, (-1, 1), (-1, 1), 0.0)
    nan = tmp_path / "nan.h5"
    cube = np.broadcast_to(gaussian_cube(5.0), (1, 1, 101, 101)).copy()
    cube[0, 0, 3, 3] = np.nan
    write_product(
        nan,
        "psfgrid",
        arrays={"cube": cube, "nodes_x": np.zeros(1), "nodes_y": np.zeros(1)},
        attrs={"pixel_scale": SUB * u.mas},
    )
    with pytest.raises(InputError, match=r"nan\.h5.*NaN"):
        read_prior(nan, (-1, 1), (-1, 1), 0.0)
    frames = tmp_path / "frames.h5"
    write_frames(frames, (60, 60), [30.0], [30.0], [18.0], SynthPSF(1.2))
    with pytest.raises(InputError, match=r"frames\.h5.*needs psf_prior"):
        run_stage(frames, {"psf_model": "psfr"}, tmp_path / "m.h5")
    with pytest.raises(InputError, match=r"frames\.h5.*not a mavispm|frames\.h5.*psfgrid"):
        run_stage(frames, {"psf_model": "psfr", "psf_prior": str(frames)}, tmp_path / "m.h5")


# --- the synthetic field-variable frame: exact Gaussian PRFs, a narrower Gaussian prior --

SHAPE = (300, 300)
PSF = SynthPSF(1.2, gradient=0.2)  # sigma 0.96-1.44 px in x, 1.08-1.32 in y: elliptical
PRIOR_SIGMA = 0.7 * SCALE  # mas: the kernel must add the rest, different in x and y


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("psfr")
    rng = np.random.default_rng(11)
    x, y = grid_positions(SHAPE, 11, 8, rng, jitter=2.0)
    mag = rng.uniform(17.0, 24.0, len(x))
    frames = tmp / "frames.h5"
    write_frames(frames, SHAPE, x, y, mag, PSF, Detector(), seed=5)
    prior = tmp / "psfgrid.h5"
    write_prior(prior, PRIOR_SIGMA)
    return tmp, frames, prior


SETTINGS = {
    "psf_stars_per_node": 60,
    "psf_star_min_snr": 50.0,
    "psf_star_isolation": "6 pix",
    "epsf_size": 15,
    "stamp_radius": 4,
}


def _scores(path):
    t = QTable.read(path, path="stars")
    mag = t["mag"].to_value(u.mag)
    good = (t["flag"] & (1 | 2 | 16 | 32)) == 0
    out = {}
    for ax in "xy":
        d = (t[ax] - t[ax + "_true"]).to_value(u.mas)
        e = t[ax + "_err"].to_value(u.mas)
        c = t["crlb_" + ax].to_value(u.mas)
        for lo, hi in ((17, 20), (20, 22), (22, 24)):
            s = good & (mag >= lo) & (mag < hi)
            mad = 1.4826 * np.median(np.abs(d[s] - np.median(d[s])))
            r = (d[s] - np.median(d[s])) / e[s]
            out[(ax, lo)] = (mad / np.median(c[s]), np.std(r[np.abs(r) < 5]), s.sum())
    return out


def test_psfr_model_reaches_the_bound_with_honest_errors(synthetic):
    """Scored against the truth: scatter / CRLB and normalised residuals per bin.

    Prior and kernel are Gaussian here: the model can match the frame exactly."""
    tmp, frames, prior = synthetic
    cfg = {**SETTINGS, "psf_prior": str(prior)}
    out = run_stage(frames, cfg, tmp / "psfr.h5", seed=0)
    prod = read_product(out, "measured")
    assert prod.attrs["psf_model"] == "psfr"
    # the fitted model's widths against the analytic ones: the (stretched) prior's
    # variance plus the kernel's, sigma_true^2 (a Gaussian prior and a round kernel are
    # degenerate; the stretch's prior settles the split)
    model = json.loads(prod.attrs["psfr"])
    grid = model["grid"]
    fitted = np.array(model["kernels"]).reshape(grid, grid, 4)
    centres = (np.arange(grid) + 0.5) * SHAPE[0] / grid - 0.5  # the nodes (cell centres) [pixel]
    for j, yn in enumerate(centres):
        for i, xn in enumerate(centres):
            sx, sy = PSF.widths(xn, yn, SHAPE)
            cxx, cyy, cxy, stretch = fitted[j, i]
            prior_var = (1.03 * stretch * PRIOR_SIGMA) ** 2
            got = np.array([cxx, cyy]) + prior_var
            np.testing.assert_allclose(got, (np.array([sx, sy]) * SCALE) ** 2, rtol=0.05)
            assert abs(cxy) < 1.0  # no correlation term [mas^2]
    for (_ax, lo), (ratio, norm_std, n) in _scores(out).items():
        assert n >= 20
        limit = {17: 1.5, 20: 1.3, 22: 1.2}[lo]
        assert ratio <= limit, (lo, ratio)
        assert abs(norm_std - 1.0) <= 0.15, (lo, norm_std)


def test_nothing_from_the_truth_reaches_the_fit(synthetic, tmp_path):
    """Scoring columns of the truth and the optics' tip-tilt map change no measurement."""
    tmp, frames, prior = synthetic
    base = run_stage(frames, {**SETTINGS, "psf_prior": str(prior)}, tmp_path / "a.h5", seed=0)
    prod = read_product(frames, "frames")
    truth = prod.tables["truth"]
    rng = np.random.default_rng(1)
    truth["flux"] = truth["flux"] * rng.uniform(0.5, 2.0, len(truth))
    truth["mag"] = truth["mag"] + rng.uniform(-1, 1, len(truth)) * u.mag
    truth["x"] = truth["x"] + rng.normal(0, 1e-3, len(truth)) * u.arcsec
    truth["y"] = truth["y"] + rng.normal(0, 1e-3, len(truth)) * u.arcsec
    changed = tmp_path / "frames.h5"
    write_product(changed, "frames", tables={"truth": truth}, arrays=prod.arrays, attrs=prod.attrs)
    tt = tmp_path / "psfgrid_tt.h5"  # a prior carrying a (wrong) tip-tilt map: not read
    write_prior(
        tt,
        PRIOR_SIGMA,
        tt_sigma_major=np.full((3, 3), 9.0) * u.mas,
        tt_sigma_minor=np.full((3, 3), 1.0) * u.mas,
        tt_angle=np.full((3, 3), 30.0) * u.deg,
    )
    other = run_stage(changed, {**SETTINGS, "psf_prior": str(tt)}, tmp_path / "b.h5", seed=0)
    a = read_product(base, "measured").tables["stars"]
    b = read_product(other, "measured").tables["stars"]
    for col in ("x_pix", "y_pix", "flux", "x_err", "y_err", "chi2", "flag"):
        np.testing.assert_array_equal(np.asarray(a[col]), np.asarray(b[col]), err_msg=col)


# --- a frame of the project's renderer with every term on (slow) -----------------------


def _pooled(path):
    """Robust scatter / median CRLB and robust std (1.4826 MAD) of the normalised
    residuals per bin, x and y pooled (twice the samples of one axis)."""
    t = QTable.read(path, path="stars")
    mag = t["mag"].to_value(u.mag)
    good = (t["flag"] & (1 | 2 | 16 | 32)) == 0
    out = {}
    for lo, hi in ((17, 20), (20, 22), (22, 24)):
        s = good & (mag >= lo) & (mag < hi)
        ratio, norm = [], []
        for ax in "xy":
            d = (t[ax] - t[ax + "_true"]).to_value(u.mas)[s]
            d = d - np.median(d)
            ratio.append(d / np.median(t["crlb_" + ax].to_value(u.mas)[s]))
            norm.append(d / t[ax + "_err"].to_value(u.mas)[s])
        ratio, norm = np.concatenate(ratio), np.concatenate(norm)
        out[lo] = (1.4826 * np.median(np.abs(ratio)), 1.4826 * np.median(np.abs(norm)), s.sum())
    return out


def _every_term_frame(tmp_path, n_stars, field_arcsec, npix):
    """An NGC 3201 preset frame (seed 21) rendered with every term on (the default optics'
    11 x 11 Fourier PSF grid, tip-tilt with the typical asterism, blur, seeing halo,
    distortion, detector; 120 x 30 s): its ``frames`` product and the scene's optics."""
    render_cli = pytest.importorskip("mavispm.simulate.render.cli")
    from mavispm.simulate.cluster.cli import run_stage as cluster_stage
    from mavispm.simulate.optics.psf_grid import default_cache_dir

    cluster = {"preset": "ngc3201", "n_stars": n_stars, "field_size": f"{field_arcsec} arcsec"}
    cat = cluster_stage(cluster, tmp_path / "c.h5", 21)
    scene = {
        "exptime": "30 s",
        "nexp": 120,
        "detector": {"nx": npix, "ny": npix},
        "optics": {"tiptilt": {"asterism": "typical"}},
    }
    optics = render_cli.build_scene_optics(
        render_cli.validate_settings(scene), cache_dir=default_cache_dir()
    )
    frames = render_cli.run_stage(cat, "e0", scene, tmp_path / "frames.h5", 3, optics=optics)
    return frames, optics


@pytest.mark.slow
def test_psfr_on_a_rendered_frame_with_every_term(tmp_path):
    """The default 4000 x 4000 px (30") NGC 3201 frame rendered with every term on
    (11 x 11 Fourier PSF grid, tip-tilt with the typical asterism, blur, seeing halo,
    distortion, detector; 120 x 30 s): the PSF-R model against the truth, and against
    the frame-built ePSF. Uses (or computes) the default optics' PSF grid cache.

    The whole frame, not its 15" centre: the centre holds only ~60 stars at V 17-20,
    where the robust std of the normalised residuals has a ~10 % standard error, so a
    +-0.15 criterion there failed or passed by chance (0.81-0.93 on the same code paths,
    0.94-0.97 on the whole frame with ~240 stars; docs/measure.md)."""
    frames, optics = _every_term_frame(tmp_path, 3500, 30, 4000)
    prior = optics.cache_path  # the optics stage's PSF grid product (the PSF-R prior)
    psfr = _pooled(run_stage(frames, {"psf_prior": str(prior)}, tmp_path / "r.h5"))
    epsf = _pooled(run_stage(frames, {}, tmp_path / "e.h5"))
    for lo, limit in ((17, 1.5), (20, 1.3), (22, 1.2)):
        ratio, norm_std, n = psfr[lo]
        assert n >= 200
        assert ratio <= limit, (lo, ratio)
        assert abs(norm_std - 1.0) <= 0.15, (lo, norm_std)
    # the frame-built ePSF (no prior) was at 3.0 x CRLB at V 17-20, PSF-R well ahead;
    # with its nodes centred on all stars it meets the same targets (1.38 / 1.20 / 1.15
    # x pooled, normalised 0.95 / 0.93 / 1.00; docs/measure.md)
    for lo, limit in ((17, 1.5), (20, 1.3), (22, 1.2)):
        ratio, norm_std, n = epsf[lo]
        assert ratio <= limit, (lo, ratio)
        assert abs(norm_std - 1.0) <= 0.15, (lo, norm_std)


@pytest.mark.slow
def test_frame_built_epsf_on_a_rendered_frame_with_every_term(tmp_path):
    """A 2000 x 2000 px (15") NGC 3201 frame with every term on (1,750 stars, 120 x 30 s),
    measured without a prior (the frame-built ePSF, 3 x 3 nodes), against the truth.

    The neighbour-pass rebuild centres each node ePSF on its PSF stars' start positions,
    as the first build does. Anchored to the positions fitted with the first ePSF, it
    took over their errors (which that ePSF's interpolation between nodes had put
    there): 2.75 / 1.46 x CRLB at V 17-20 / 20-22 on this frame, then 2.06 / 1.24 (the
    4000 x 4000 px frame: 3.80 / 1.85, then 3.02 / 1.53; docs/measure.md), with
    conservative errors at the bright end (normalised residuals 0.64 at V 17-20).
    Each node is now centred after the fit on all well-measured stars near it
    (``epsf_centring = "all"``): 1.06 / 1.18 / 1.15 x, normalised residuals 0.79 /
    1.04 / 1.05; the limits are issue 14's targets (the old code fails V 17-20)."""
    frames, _ = _every_term_frame(tmp_path, 1750, 15, 2000)
    epsf = _pooled(run_stage(frames, {"psf_model": "epsf"}, tmp_path / "e.h5"))
    for lo, limit in ((17, 1.5), (20, 1.3), (22, 1.2)):
        ratio, norm_std, n = epsf[lo]
        assert n >= 100
        assert ratio <= limit, (lo, ratio)
        assert 0.7 <= norm_std <= 1.15, (lo, norm_std)  # neither too small nor too large
