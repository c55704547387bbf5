"""Effective temperatures of catalogue stars (for the colour-dependent refraction)."""

from __future__ import annotations

import astropy.units as u
import numpy as np

from mavispm.simulate.cluster import population as pop
from mavispm.simulate.cluster.effective_temperature import MASS_TEFF_TABLE, effective_temperature
from mavispm.simulate.cluster.generator import simulate_catalogue
from mavispm.simulate.cluster.settings import ClusterSettings
from mavispm.simulate.optics.refraction import RefractionSettings, star_displacement


def test_table_follows_the_mass_luminosity_relation():
    # the same masses as the mass-luminosity table, so each star's colour matches its M_V
    assert np.array_equal(MASS_TEFF_TABLE[:, 0], pop.MASS_LUMINOSITY_TABLE[:, 0])
    t = MASS_TEFF_TABLE[:, 1]
    turnoff = np.argmax(t)
    assert MASS_TEFF_TABLE[turnoff, 0] == 0.78  # hottest at the turn-off (M_V 3.9)
    # an old metal-poor turn-off is 6,200-6,700 K; M dwarfs and the RGB tip are cool
    assert 6200 <= t[turnoff] <= 6700 and t[0] < 3500 and 3900 <= t[-1] <= 4400
    assert np.all(np.diff(t[: turnoff + 1]) > 0) and np.all(np.diff(t[turnoff:]) < 0)
    assert np.isnan(effective_temperature([1.0, 0.0]))[0]


def test_catalogue_has_teff_and_refraction_tells_dwarfs_from_giants():
    settings = ClusterSettings(preset="ngc3201-nbody", n_stars=400, epochs=(0.0,))
    epochs, _ = simulate_catalogue(settings, seed=3)
    e0 = epochs["e0"]
    teff = e0["teff"].to_value(u.K)
    lum = np.asarray(e0["luminous"], bool)
    assert np.all(np.isfinite(teff[lum])) and np.all(np.isnan(teff[~lum]))
    refr = RefractionSettings(enabled=True, adc_residual=1.0)
    shift = star_displacement(teff[lum], refr)[1]
    assert np.ptp(shift) > 1e-3  # > 1 mas between the coolest and hottest stars at 30 deg
