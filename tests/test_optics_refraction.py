"""Differential atmospheric refraction against ERFA's independent refraction model."""

from __future__ import annotations

import erfa
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.config import from_mapping
from mavispm.core.errors import ConfigError
from mavispm.simulate.optics.refraction import (
    RefractionSettings,
    band_refraction,
    refraction,
    star_displacement,
)

ARCSEC = 180 / np.pi * 3600


def _erfa_refraction(wavelength_nm, s: RefractionSettings):
    """ERFA/SOFA refraction (Hohenkerk & Sinclair model via iauRefco) [arcsec]."""
    a, b = erfa.refco(s.pressure, s.temperature, s.relative_humidity, wavelength_nm / 1000)
    t = np.tan(np.radians(s.zenith_angle))
    return (a * t + b * t**3) * ARCSEC


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"zenith_angle": 50.0, "temperature": 0.0, "pressure": 780.0},
        {"relative_humidity": 0.8, "temperature": 20.0},
    ],
)
def test_refraction_and_dispersion_match_erfa(kw):
    s = RefractionSettings(enabled=True, **kw)
    lam = np.array([420.0, 500.0, 550.0, 650.0, 900.0])
    ours = refraction(lam, s)
    theirs = np.array([_erfa_refraction(w, s) for w in lam])
    assert np.allclose(ours, theirs, rtol=3e-3)
    # the dispersion between two wavelengths (what DAR is): 0.5% in dry air; ERFA takes
    # water vapour as non-dispersive, Filippenko's eq. 3 does not (+1.3% at 80%, 20 C)
    tol = 0.005 + 0.012 * s.relative_humidity * (s.temperature >= 15)
    assert ours[0] - ours[3] == pytest.approx(theirs[0] - theirs[3], rel=tol)


def test_band_mean_matches_erfa_weighted_over_a_black_body():
    """The photon-weighted mean over a flat band, with ERFA's refraction and an independent
    quadrature of the Planck photon spectrum (scipy-free trapezoid on a finer grid)."""
    s = RefractionSettings(enabled=True, band="tophat", band_min=480.0, band_max=680.0)
    lam = np.linspace(480.0, 680.0, 2001)
    r_erfa = np.array([_erfa_refraction(w, s) for w in lam[::50]])
    r_erfa = np.interp(lam, lam[::50], r_erfa)
    for teff in (3500.0, 6000.0, 20000.0):
        h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
        m = lam * 1e-9
        photons = (2 * h * c**2 / m**5 / np.expm1(h * c / (m * k * teff))) * m / (h * c)
        expected = np.trapezoid(photons * r_erfa, lam) / np.trapezoid(photons, lam)
        mean, rms = band_refraction(teff, s)
        # relative to 550 nm (the models' absolute refraction differs by 0.1%)
        ours = mean[0] - refraction(550.0, s)
        theirs = expected - _erfa_refraction(550.0, s)
        assert ours == pytest.approx(theirs, abs=0.01 * (r_erfa[0] - r_erfa[-1]))
        assert 0 < rms[0] < (r_erfa[0] - r_erfa[-1]) / np.sqrt(12) * 1.2


def test_hot_stars_are_lifted_more_and_adc_scales_the_shift():
    s = RefractionSettings(enabled=True, adc_residual=1.0, zenith_direction=90.0)
    dx, dy = star_displacement([3500.0, 20000.0], s)
    assert np.all(np.abs(dx) < 1e-15)
    assert dy[1] > dy[0]  # towards the zenith (+y here): the blue star further
    # no ADC at z = 30 deg: tens of mas between M dwarfs and hot stars in V
    assert 0.01 < dy[1] - dy[0] < 0.04
    half = star_displacement([3500.0, 20000.0], RefractionSettings(enabled=True, adc_residual=0.5))
    assert half[1] == pytest.approx(0.5 * dy, rel=1e-12)


def test_off_zenith_monochromatic_and_nan():
    zero = star_displacement([4000.0, 9000.0], RefractionSettings(enabled=False))
    assert np.all(zero[0] == 0) and np.all(zero[1] == 0)
    at_zenith = star_displacement([4000.0], RefractionSettings(enabled=True, zenith_angle=0.0))
    assert abs(at_zenith[1][0]) < 1e-15
    mono = RefractionSettings(enabled=True, band="monochromatic", adc_residual=1.0)
    assert np.all(np.abs(star_displacement([3000.0, 30000.0], mono)[1]) < 1e-12)
    s = RefractionSettings(enabled=True)
    a = star_displacement([np.nan], s)[1]
    b = star_displacement([s.default_teff], s)[1]
    assert a == pytest.approx(b)


def test_bad_settings_name_the_key():
    with pytest.raises(ConfigError, match="refraction.*zenith_angle"):
        from_mapping(RefractionSettings, {"zenith_angle": 80}, prefix="scene.optics.refraction")
    with pytest.raises(ConfigError, match="adc_residual"):
        from_mapping(RefractionSettings, {"adc_residual": 2}, prefix="scene.optics.refraction")
    with pytest.raises(ConfigError, match="pressure"):
        from_mapping(RefractionSettings, {"pressure": "-5 hPa"}, prefix="scene.optics.refraction")


@settings(max_examples=40, deadline=None)
@given(
    z=st.floats(0, 70),
    t=st.floats(-30, 40),
    p=st.floats(300, 1050),
    rh=st.floats(0, 1),
    teff=st.floats(2000, 60000),
)
def test_finite_and_bounded(z, t, p, rh, teff):
    s = RefractionSettings(
        enabled=True,
        zenith_angle=z,
        temperature=t,
        pressure=p,
        relative_humidity=rh,
        adc_residual=1.0,
    )
    dx, dy = star_displacement([teff], s)
    assert np.isfinite(dx).all() and np.isfinite(dy).all()
    # never more than the whole band's dispersion
    spread = refraction(470.0, s) - refraction(700.0, s)
    assert abs(dy[0]) <= spread + 1e-12


def test_frames_move_hot_and_cool_stars_apart():
    """Rendered noise-free: each star's image centroid moves by its DAR shift (+x here)."""
    from types import SimpleNamespace

    import astropy.units as u
    from render_helpers import epoch_table, make_optics

    from mavispm.simulate.render.frame import render_frame
    from mavispm.simulate.render.scene import scene_from_mapping

    scene = scene_from_mapping(
        {"noise": False, "nexp": 1, "detector": {"nx": 96, "ny": 64}, "render": {"halo": False}}
    )
    table = epoch_table([-0.15, 0.15], [0.0, 0.0], [16.0, 16.0])
    table["teff"] = [3500.0, 20000.0] * u.K
    refr = RefractionSettings(enabled=True, adc_residual=1.0, zenith_direction=0.0)

    def centroids(optics):
        frame = render_frame(table, 0 * u.yr, scene, optics, None)
        img = frame.noiseless - frame.attrs["sky"].value
        yy, xx = np.indices(img.shape)
        out = []
        for xp in frame.truth["x_pix"]:
            box = np.abs(xx - xp) < 12
            out.append(np.sum((img * xx)[box]) / np.sum(img[box]))
        return np.array(out), frame

    plain = make_optics("gaussian")
    off, _ = centroids(plain)
    plain.settings = SimpleNamespace(refraction=refr)
    on, frame = centroids(plain)
    expected = star_displacement([3500.0, 20000.0], refr)[0] * 1000 / 7.5  # pixels
    assert on - off == pytest.approx(expected, abs=2e-3)
    assert np.allclose(frame.truth["dar_x"].to_value(u.arcsec), expected * 7.5 / 1000)


def test_per_epoch_pointing_changes_the_colour_shift():
    s = RefractionSettings(enabled=True, epochs=((0.0, 10.0, 90.0), (10.0, 45.0, 90.0)))
    teff = [3500.0, 20000.0]
    d0 = star_displacement(teff, s, 0.0)[1]
    d10 = star_displacement(teff, s, 10.0)[1]
    ratio = (d10[1] - d10[0]) / (d0[1] - d0[0])
    assert ratio == pytest.approx(np.tan(np.radians(45)) / np.tan(np.radians(10)), rel=1e-9)
    other = star_displacement(teff, s, 5.0)[1]  # not listed: the default 30 deg
    assert np.allclose(other, star_displacement(teff, RefractionSettings(enabled=True))[1])
    with pytest.raises(ConfigError, match="epochs"):
        from_mapping(RefractionSettings, {"epochs": [[0, 80, 0]]}, prefix="scene.optics.refraction")
