"""The blind detector's PSF-wing term: structure beyond the ePSF footprint is not a star.

Unit tests check :func:`psf_detection.wing_profile` against an injected ring structure
of known amplitude and :func:`psf_detection.wing_image` against a brute-force sum; the
slow test renders a reduced NGC 3201 frame with the project's MAVIS optics (every
default term, typical tip-tilt asterism) and scores the detections against its truth.
"""

from __future__ import annotations

import numpy as np
import pytest

from mavispm.measure.stars import psf_detection

SHAPE = (260, 260)


def _structure(x, y, flux, amplitude, rng):
    """Gaussian speckle field of standard deviation A(r) F per pixel around each star."""
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]].astype(float)
    img = np.zeros(SHAPE)
    for xi, yi, fi in zip(x, y, flux):
        r = np.hypot(xx - xi, yy - yi)
        k = np.clip(r.astype(int), 0, len(amplitude) - 1)
        img += np.where(r < len(amplitude), fi * amplitude[k] * rng.normal(size=SHAPE), 0.0)
    return img


def test_wing_profile_recovers_an_injected_structure_not_the_neighbours():
    rng = np.random.default_rng(3)
    r_out, r_in = 40, 12
    radii = np.arange(r_out + 1)
    amplitude = np.where(radii >= r_in, 2e-4 * np.exp(-(radii - r_in) / 15.0), 0.0)
    x = np.array([60.0, 190.0, 70.0, 200.0, 130.0])
    y = np.array([60.0, 70.0, 190.0, 195.0, 130.0])
    flux = np.array([4e6, 3e6, 2e6, 5e6, 1e6])
    noise = rng.normal(0, 10.0, SHAPE)
    var = np.full(SHAPE, 100.0)
    resid = _structure(x, y, flux, amplitude, rng) + noise
    # neighbours' left-overs: 60 compact blobs 30x the structure (a minority of pixels)
    bx, by = rng.uniform(0, SHAPE[1], 60), rng.uniform(0, SHAPE[0], 60)
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]]
    for xi, yi in zip(bx, by):
        resid += 6e3 * np.exp(-0.5 * ((xx - xi) ** 2 + (yy - yi) ** 2) / 1.2**2)
    s = psf_detection.wing_profile(resid, var, x, y, flux, r_in, r_out)
    assert np.all(s[:r_in] == 0)
    ok = (radii >= r_in + 2) & (radii <= 30)  # the structure is well above the noise
    ratio = s[ok] / amplitude[ok]
    assert abs(np.median(ratio) - 1.0) < 0.1
    assert np.all(np.abs(ratio - 1.0) < 0.3)
    # pure noise gives (almost) nothing: the noise variance is removed
    s0 = psf_detection.wing_profile(noise, var, x, y, flux, r_in, r_out)
    assert np.median(s0[r_in:]) < 0.05 * amplitude[r_in]


def _faint_unfitted_stars(shape, n, rng):
    """Light of ``n`` stars no fit holds yet (Gaussian, sigma 1.2 px, 200-2000 e peak)."""
    img = np.zeros(shape)
    for xi, yi, a in zip(
        rng.uniform(0, shape[1], n), rng.uniform(0, shape[0], n), rng.uniform(200, 2000, n)
    ):
        cx, cy = int(xi), int(yi)
        ys = np.arange(max(cy - 6, 0), min(cy + 7, shape[0]))
        xs = np.arange(max(cx - 6, 0), min(cx + 7, shape[1]))
        g = np.exp(-0.5 * ((xs[None, :] - xi) ** 2 + (ys[:, None] - yi) ** 2) / 1.2**2)
        img[np.ix_(ys, xs)] += a * g
    return img


def test_wing_profile_is_zero_without_wings_despite_light_no_fit_holds():
    """A frame without wings whose annuli hold the light of stars not yet fitted (the
    bright pass fits only the bright stars): the excess does not grow with the star's
    flux, so it is no wing. Before the fix (2026-12-02) the median over stars of the
    excess gave ~1e-4 per pixel on such frames and the detector lost faint stars."""
    rng = np.random.default_rng(8)
    shape = (420, 420)
    r_out, r_in = 40, 12
    amplitude_max = 1e-4  # of the wing injected below
    gx, gy = np.meshgrid(np.linspace(60, 360, 5), np.linspace(60, 360, 4))
    x, y = gx.ravel() + rng.uniform(-4, 4, 20), gy.ravel() + rng.uniform(-4, 4, 20)
    flux = 10 ** rng.uniform(5.0, 6.5, 20)  # V ~17-21 against a sky of 100 e
    var = np.full(shape, 100.0)
    noise = rng.normal(0, 10.0, shape)
    faint = _faint_unfitted_stars(shape, 900, rng)  # ~1 per 14 x 14 px, as in a cluster
    s = psf_detection.wing_profile(noise + faint, var, x, y, flux, r_in, r_out)
    assert np.all(s[:r_in] == 0)
    # the old estimator: median over annuli 1.3e-5, none zero; now (3-sigma gate, the
    # contamination's excess is heavy-tailed) 4 of 29 annuli pass at 0.4-0.6e-5
    assert np.median(s[r_in:]) == 0
    assert np.count_nonzero(s) <= 0.15 * (r_out + 1 - r_in)
    assert np.max(s) < 0.1 * amplitude_max
    # the same light around stars that do have a wing: the wing is still measured
    radii = np.arange(r_out + 1)
    amplitude = np.where(radii >= r_in, amplitude_max * np.exp(-(radii - r_in) / 15.0), 0.0)
    yy, xx = np.mgrid[: shape[0], : shape[1]].astype(float)
    wing = np.zeros(shape)
    for xi, yi, fi in zip(x, y, flux):
        r = np.hypot(xx - xi, yy - yi)
        k = np.clip(r.astype(int), 0, r_out)
        wing += np.where(r < r_out, fi * amplitude[k] * rng.normal(size=shape), 0.0)
    s = psf_detection.wing_profile(noise + faint + wing, var, x, y, flux, r_in, r_out)
    ok = (radii >= r_in) & (radii <= 30)
    ratio = s[ok] / amplitude[ok]
    assert abs(np.median(ratio) - 1.0) < 0.15


def test_wing_image_is_the_sum_of_the_stars_profiles():
    rng = np.random.default_rng(5)
    profile = np.concatenate([np.zeros(6), np.linspace(3e-4, 1e-5, 15)])
    x = rng.uniform(-5, SHAPE[1] + 5, 12)  # some stars off the frame's edge
    y = rng.uniform(-5, SHAPE[0] + 5, 12)
    flux = rng.uniform(1e4, 1e6, 12)
    flux[0] = 0.0
    img = psf_detection.wing_image(SHAPE, x, y, flux, profile)
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]]
    brute = np.zeros(SHAPE)
    r_out = len(profile) - 1
    for xi, yi, fi in zip(x, y, flux):
        cx, cy = np.rint(xi), np.rint(yi)  # stars are placed on their nearest pixel
        r = np.hypot(xx - cx, yy - cy)
        brute += np.where(r <= r_out, fi * profile[np.clip(r.astype(int), 0, r_out)], 0.0)
    assert np.allclose(img, brute, rtol=1e-12, atol=1e-9)
    # stars whose wing peaks below the threshold are left out
    faint = psf_detection.wing_image(SHAPE, x, y, flux, profile, min_amplitude=1e9)
    assert not np.any(faint)


@pytest.mark.slow  # renders a 1000 x 1000 frame (PSF grid ~1 min uncached), three blind stages
def test_rendered_ngc3201_frame_false_detections_below_five_percent():
    import mavispm

    cat = mavispm.simulate_cluster(
        {
            "preset": "ngc3201",
            "imbh_mass": 0,
            "n_stars": 560,
            "field_size": "7.5 arcsec",
            "epochs": [0],
        },
        seed=77,
    )
    scene = {
        "nexp": 120,
        "exptime": "30 s",
        "detector": {"nx": 1000, "ny": 1000},
        "optics": {"tiptilt": {"asterism": "typical"}},
    }
    frame = mavispm.render_epoch(cat, "e0", scene, mavispm.build_optics(scene["optics"]), seed=5)

    def blind(wing, halo):
        settings = {"blind": True, "detection_wing_radius": wing}
        settings["knobs"] = {"wing_threshold": halo}  # the fitter's light outside stamps
        return mavispm.measure_stars(frame, settings)[0].meta

    bare, off, on = blind(0.0, 0.0), blind(0.0, 3.0), blind(48.0, 3.0)
    # measured 2026-12-02 (V < 26): neither term 84 false (12.5 %), 483 matched; the
    # fitter's halo model alone 18 (3.2 %), 482 (47, 6.1 %, while every detector pass
    # measured its own halo profile: the first pass's, of the bright stars alone, removes
    # more); with the wing term too 15 (3.2 %), 499. Since the halo model uses the frame's
    # profile at every radius (2026-12-02, helper scale3): neither 81 (12.5 %), 483; the
    # halo model alone 14 (2.6 %), 481 (main: 18, 482); both 16 (3.4 %), 499 (main: 14,
    # 498): the halo model now removes most of what the wing term removed, whose part is
    # the completeness (+18 matched) at up to a few more false detections
    assert bare["detect_false_fraction_v26"] > 0.08  # the structure both terms are for
    assert off["detect_n_false"] <= 0.5 * bare["detect_n_false"]  # the halo model's part
    assert on["detect_false_fraction_v26"] <= 0.05
    assert on["detect_n_false"] <= 0.25 * bare["detect_n_false"]
    assert on["detect_n_matched"] >= off["detect_n_matched"] + 10  # the wing term's part
