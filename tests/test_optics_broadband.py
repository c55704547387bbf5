"""Broadband PSFs from monochromatic slices (simulate/optics/broadband.py).

References: the photon-weighted mean and variance of the refraction come from an
independent adaptive quadrature (scipy.integrate.quad over the Planck photon spectrum
times the Bessell V response), not from the module's wavelength grid; the rendered
broadband star is compared with a real-space brute-force sum of shifted monochromatic
Airy stamps.
"""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
import scipy.integrate
from hypothesis import given, settings
from hypothesis import strategies as st
from render_helpers import AnalyticPSFGrid, airy, brute_force_stamp, epoch_table, make_optics

from mavispm.core.errors import ConfigError
from mavispm.simulate.optics.broadband import (
    BroadbandSettings,
    broadband_psf,
    colour_bins,
    slice_spectrum,
    slice_wavelengths,
)
from mavispm.simulate.optics.refraction import (
    BESSELL_V,
    RefractionSettings,
    refraction,
    star_displacement,
)

H_C_OVER_K = 6.62607015e-34 * 2.99792458e8 / 1.380649e-23  # m K


def quad_moments(teff, s: RefractionSettings):
    """Photon-weighted mean and variance of the ADC-residual DAR shift [arcsec] (quad)."""
    ref = refraction(s.reference_wavelength, s)

    def photons(lam):
        resp = np.interp(lam, BESSELL_V[:, 0], BESSELL_V[:, 1])
        return resp * lam**-4 / np.expm1(H_C_OVER_K / (lam * 1e-9 * teff))

    def shift(lam):
        return s.adc_residual * (refraction(lam, s) - ref)

    pts = list(BESSELL_V[:, 0])
    kw = dict(points=pts, limit=200, epsabs=0, epsrel=1e-11)
    a, b = BESSELL_V[0, 0], BESSELL_V[-1, 0]
    norm = scipy.integrate.quad(photons, a, b, **kw)[0]
    m1 = scipy.integrate.quad(lambda x: photons(x) * shift(x), a, b, **kw)[0] / norm
    m2 = scipy.integrate.quad(lambda x: photons(x) * (shift(x) - m1) ** 2, a, b, **kw)[0] / norm
    return m1, m2


def moments(img, scale):
    """Centroid and central second-moment matrix of an image [mas, mas^2]."""
    n = img.shape[0]
    off = (np.arange(n) - (n - 1) / 2) * scale
    yy, xx = np.meshgrid(off, off, indexing="ij")
    t = img.sum()
    cx, cy = (img * xx).sum() / t, (img * yy).sum() / t
    dx, dy = xx - cx, yy - cy
    cov = np.array([[(img * dx * dx).sum(), (img * dx * dy).sum()], [0, (img * dy * dy).sum()]])
    cov[1, 0] = cov[0, 1]
    return cx, cy, cov / t


def gaussian_slices(lam, n=401, scale=1.0):
    """Normalised Gaussian 'monochromatic PSFs' with sigma proportional to wavelength."""
    off = (np.arange(n) - (n - 1) / 2) * scale
    yy, xx = np.meshgrid(off, off, indexing="ij")
    sig = 8.0 * np.asarray(lam) / 550.0
    cube = np.exp(-0.5 * (xx**2 + yy**2)[None] / sig[:, None, None] ** 2)
    return cube / cube.sum(axis=(1, 2), keepdims=True), sig


DAR = RefractionSettings(enabled=True, zenith_angle=45.0, adc_residual=0.3, zenith_direction=0.0)


def test_one_slice_without_shift_is_the_monochromatic_psf_exactly():
    cube, _ = gaussian_slices([550.0], n=65)
    out = broadband_psf(cube, 1.0, [1.0], [[0.0, 0.0]])
    assert np.array_equal(out, cube[0])
    # several identical slices without refraction: the same PSF (to round-off)
    same = np.repeat(cube, 4, axis=0)
    spec = slice_spectrum([4000.0], RefractionSettings(), 4)
    assert np.all(spec.shifts == 0) and np.all(spec.variance == 0)
    out4 = broadband_psf(same, 1.0, spec.weights[0], np.zeros((4, 2)))
    assert np.abs(out4 - cube[0]).max() < 1e-14


@pytest.mark.parametrize("teff", [3200.0, 9000.0, 30000.0])
@pytest.mark.parametrize("k", [1, 3, 5])
def test_centroid_and_spread_match_quadrature(teff, k):
    """Centroid = photon-weighted mean DAR; zenith variance grows by the in-band variance."""
    lam = slice_wavelengths(DAR, k)
    cube, sig = gaussian_slices(lam)
    spec = slice_spectrum([teff], DAR, k)
    w, d_mas = spec.weights[0], spec.shifts[0] * 1000
    theta = np.radians(30.0)
    e = np.array([np.cos(theta), np.sin(theta)])
    cov = spec.variance[0] * 1e6 * np.outer(e, e)
    img = broadband_psf(cube, 1.0, w, d_mas[:, None] * e[None], cov)
    cx, cy, c2 = moments(img, 1.0)
    m1, m2 = quad_moments(teff, DAR)
    assert abs(m1) > 2e-3  # a real shift: mas
    assert np.hypot(cx, cy) * np.sign(cx) == pytest.approx(m1 * 1000, rel=1e-4)
    assert cy / cx == pytest.approx(np.tan(theta), rel=1e-6)
    # along the zenith: sum_k w_k sigma_k^2 + in-band variance; across it: sigma only
    mono = np.sum(w * sig**2)
    across = np.array([-e[1], e[0]])
    # (the 0.5 nm band grid integrates to ~4e-5 of the quadrature)
    assert e @ c2 @ e == pytest.approx(mono + m2 * 1e6, rel=1e-4)
    assert across @ c2 @ across == pytest.approx(mono, rel=1e-7)
    assert across @ c2 @ e == pytest.approx(0.0, abs=1e-8 * mono)
    assert spec.total_variance[0] * 1e6 == pytest.approx(m2 * 1e6, rel=1e-4)


def test_mean_is_the_star_displacement():
    teff = np.array([3000.0, 4500.0, 7000.0, 40000.0, np.nan])
    for k in (1, 2, 4, 7):
        spec = slice_spectrum(teff, DAR, k, epoch=None)
        dx, dy = star_displacement(teff, DAR)
        assert np.allclose(spec.mean, dx, rtol=0, atol=1e-12)  # arcsec
        assert np.allclose(spec.weights.sum(axis=1), 1.0)
    # more stars than one block of the work arrays: the blocks join seamlessly
    many = np.random.default_rng(0).uniform(3000.0, 30000.0, 25000)
    spec = slice_spectrum(many, DAR, 3)
    assert np.allclose(spec.mean, star_displacement(many, DAR)[0], rtol=0, atol=1e-12)


def test_slice_wavelengths_split_the_band():
    lam = slice_wavelengths(DAR, 4)
    assert np.all(np.diff(lam) > 0)
    assert 490 < lam[0] < lam[-1] < 640
    assert slice_wavelengths(DAR, 1)[0] == pytest.approx(
        np.trapezoid(BESSELL_V[:, 1] * BESSELL_V[:, 0], BESSELL_V[:, 0])
        / np.trapezoid(BESSELL_V[:, 1], BESSELL_V[:, 0]),
        abs=0.05,
    )


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=0, max_size=40),
    st.integers(1, 10),
)
def test_colour_bins_cover_every_star(values, n):
    index, rep = colour_bins(values, n)
    assert len(index) == len(values)
    if values:
        assert set(index) == set(range(len(rep)))
        assert len(rep) <= n
        v = np.asarray(values)
        for b, r in enumerate(rep):
            assert index[r] == b
            assert v[index == b].min() <= v[r] <= v[index == b].max()


def test_settings_are_checked():
    from mavispm.simulate.optics.model import validate_settings

    with pytest.raises(ValueError, match="slices"):
        BroadbandSettings(slices=0)
    with pytest.raises(ConfigError, match="broadband.slices"):
        validate_settings({"broadband": {"slices": 3}, "refraction": {"band": "monochromatic"}})
    with pytest.raises(ConfigError, match="broadband.slices"):
        validate_settings({"broadband": {"slices": 3}, "psf": {"mode": "file", "file": "x.fits"}})


# ---------------------------------------------------------------- rendering
SCALE = 7.5


def airy_slices(lam, nodes=(0.0,), n=129):
    """Analytic monochromatic Airy grids (lambda/D scaled) at wavelengths ``lam`` [nm]."""
    grids = []
    for wl in lam:
        lod = 0.55e-6 / 8.0 * 206264806.247 * wl / 550.0

        def profile(dx, dy, nx, ny, lod=lod):
            return airy(np.hypot(dx, dy), lam_over_d=lod)

        grids.append(AnalyticPSFGrid(profile, np.asarray(nodes), np.asarray(nodes), n=n))
    return grids


def test_rendered_star_is_the_sum_of_shifted_slices():
    """Renderer (slices mixed at the stamp frequencies) vs a real-space brute force."""
    from mavispm.simulate.render.stamps import RenderParams, StarRenderer

    lam = slice_wavelengths(DAR, 3)
    grids = airy_slices(lam)
    weights = np.array([0.2, 0.5, 0.3])
    shifts = np.array([[2.0, -1.0], [0.0, 0.4], [-1.5, 1.2]])  # mas
    cov = np.array([[9.0, 1.0], [1.0, 6.0]])
    r = StarRenderer(
        grids[0], SCALE, RenderParams(dtype="float64"), slice_cubes=[g.cube for g in grids]
    )
    xp, yp = 16.1, 15.8
    stamps, x0, y0 = r.render_stamps(
        32, [xp], [yp], [0.0], [0.0], cov[None], [1.0], spectrum=(weights, shifts)
    )
    ref = sum(
        wk * brute_force_stamp(g, 0.0, 0.0, cov, xp + sx / SCALE, yp + sy / SCALE, SCALE, 32)
        for wk, g, (sx, sy) in zip(weights, grids, shifts)
    )
    assert np.abs(stamps[0] - ref).max() <= 1e-3 * ref.max()
    with pytest.raises(ValueError, match="spectrum"):
        r.render_stamps(32, [xp], [yp], [0.0], [0.0], cov[None], [1.0])


def _frame_moments(optics, table):
    from mavispm.simulate.render.frame import render_frame
    from mavispm.simulate.render.scene import scene_from_mapping

    scene = scene_from_mapping(
        {"noise": False, "nexp": 1, "detector": {"nx": 96, "ny": 64}, "render": {"halo": False}}
    )
    frame = render_frame(table, 0 * u.yr, scene, optics, None)
    img = frame.noiseless - frame.attrs["sky"].value
    yy, xx = np.indices(img.shape)
    out = []
    for xp, yp in zip(frame.truth["x_pix"], frame.truth["y_pix"]):
        box = (np.abs(xx - round(xp)) < 20) & (np.abs(yy - round(yp)) < 20)
        t = img[box].sum()
        cx, cy = (img * xx)[box].sum() / t, (img * yy)[box].sum() / t
        out.append((cx, cy, (img * (xx - cx) ** 2)[box].sum() / t))
    return np.array(out), frame


def test_frames_spread_each_star_along_the_zenith():
    """Noise-free frames with 4 slices: each image centroid sits at its quadrature mean
    DAR and its variance along the zenith (+x) exceeds the unrefracted one by the
    quadrature in-band variance."""
    from mavispm.simulate.optics.model import validate_settings

    table = epoch_table([-0.15, 0.15], [0.0, 0.0], [16.0, 16.0])
    table["teff"] = [3500.0, 20000.0] * u.K
    refr = RefractionSettings(enabled=True, zenith_angle=45.0, adc_residual=0.3, zenith_direction=0)
    k = 4
    lam = slice_wavelengths(refr, k)

    def optics(refraction):
        o = make_optics("gaussian", nodes=1, blur_sigma=0.0)
        o.tiptilt.sxx = o.tiptilt.syy = 4.0
        o.tiptilt.sxy = 0.0
        cube, _ = gaussian_slices(lam, n=129)
        o.psf_slices = cube[:, None, None]
        o.settings = validate_settings(
            {"broadband": {"slices": k, "colour_bins": 2}, "refraction": refraction}
        )
        return o

    base = {
        "zenith_angle": "45 deg",
        "adc_residual": 0.3,
        "zenith_direction": "0 deg",
        "enabled": False,
    }
    off, _ = _frame_moments(optics(base), table)
    on, frame = _frame_moments(optics({**base, "enabled": True}), table)
    pix = SCALE
    for i, teff in enumerate([3500.0, 20000.0]):
        m1, m2 = quad_moments(teff, refr)
        assert (on[i, 0] - off[i, 0]) * pix == pytest.approx(m1 * 1000, abs=2e-3)
        assert (on[i, 2] - off[i, 2]) * pix**2 == pytest.approx(m2 * 1e6, rel=2e-3)
    expected = [quad_moments(t, refr)[0] for t in (3500.0, 20000.0)]
    assert np.allclose(frame.truth["dar_x"].to_value(u.arcsec), expected, rtol=1e-4)


def test_one_slice_renders_todays_stamps_bit_for_bit():
    """A sliced renderer with one slice, weight 1 and no shift gives today's stamps."""
    from mavispm.simulate.render.stamps import StarRenderer

    grid = make_optics("airy").psf_grid
    cov = np.array([[[9.0, 1.0], [1.0, 6.0]]] * 2)
    args = (32, [16.1, 12.7], [15.8, 17.2], [0.3, -1.1], [0.9, 0.2], cov, [1.0, 3e4])
    plain = StarRenderer(grid, SCALE).render_stamps(*args)[0]
    one = StarRenderer(grid, SCALE, slice_cubes=[grid.cube])
    sliced = one.render_stamps(*args, spectrum=([1.0], [[0.0, 0.0]]))[0]
    assert np.array_equal(plain, sliced)


def test_build_optics_computes_one_grid_per_slice(tmp_path):
    """Diffraction-limited slices: peak of a unit-sum PSF scales as lambda^-2."""
    from optics_helpers import small_table

    from mavispm.simulate.optics.model import build_optics, validate_settings

    table = small_table(mode="diffraction", n_nodes=1)
    table["broadband"] = {"slices": 3}
    table["refraction"] = {"enabled": True}
    table["halo"] = {"enabled": False}
    optics = build_optics(validate_settings(table), cache_dir=tmp_path, progress=False)
    lam = slice_wavelengths(RefractionSettings(enabled=True), 3)
    assert np.allclose(optics.slice_wavelengths, lam)
    assert optics.psf_slices.shape == (3,) + optics.psf_grid.cube.shape
    assert np.allclose(optics.psf_slices.sum(axis=(-2, -1)), 1.0)
    peak = optics.psf_slices.max(axis=(1, 2, 3, 4))
    # (1%: the 3.75 mas pixels sample the ~14 mas core below its true peak)
    assert peak / peak[0] == pytest.approx((lam[0] / lam) ** 2, rel=1e-2)
    one = build_optics(validate_settings(small_table(mode="diffraction", n_nodes=1)), tmp_path)
    assert one.psf_slices is None


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.floats(0.0, 1.0), min_size=1, max_size=5).filter(lambda w: sum(w) > 1e-3),
    st.floats(-20.0, 20.0),
    st.floats(0.0, 50.0),
)
def test_broadband_psf_conserves_flux_and_moves_the_centroid(w, shift, spread):
    """Any weights, shifts and spread: unit flux, centroid at the weighted mean shift.
    (201 px: the widest case, sigma ~11 px shifted by 20 px, keeps > 7 sigma inside the
    image; at 161 px its truncated wing moved the centroid by 1e-6 px.)"""
    k = len(w)
    cube, _ = gaussian_slices(np.linspace(500.0, 600.0, k), n=201)
    w = np.asarray(w) / np.sum(w)
    shifts = np.column_stack([shift * np.linspace(-1, 1, k), 0.5 * shift * np.ones(k)])
    img = broadband_psf(cube, 1.0, w, shifts, np.diag([spread, 0.0]))
    assert img.sum() == pytest.approx(1.0, abs=1e-12)
    cx, cy, _ = moments(img, 1.0)
    assert cx == pytest.approx(w @ shifts[:, 0], abs=1e-6)
    assert cy == pytest.approx(w @ shifts[:, 1], abs=1e-6)


def test_without_refraction_the_slices_still_follow_each_stars_colour():
    """Refraction off, 2 colour bins: the two hot stars share the narrower (bluer) kernel,
    the two cool ones the wider, whatever their order in the catalogue."""
    from mavispm.simulate.optics.model import validate_settings

    table = epoch_table([-0.3, -0.1, 0.1, 0.3], [0.0] * 4, [16.0] * 4)
    table["teff"] = [20000.0, 3500.0, 20000.0, 3500.0] * u.K
    o = make_optics("gaussian", nodes=1, blur_sigma=0.0)
    o.tiptilt.sxx = o.tiptilt.syy = 1.0
    o.tiptilt.sxy = 0.0
    lam = slice_wavelengths(RefractionSettings(), 4)
    o.psf_slices = gaussian_slices(lam, n=129)[0][:, None, None]
    o.settings = validate_settings({"broadband": {"slices": 4, "colour_bins": 2}})
    m, _ = _frame_moments(o, table)
    assert m[0, 2] == pytest.approx(m[2, 2], rel=1e-4)  # (pixel phases differ)
    assert m[1, 2] == pytest.approx(m[3, 2], rel=1e-4)
    assert m[1, 2] > 1.02 * m[0, 2]  # the cool stars' photons are redder: wider slices
