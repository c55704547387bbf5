"""Mass models for other stages (escape speeds): M(<r) and Phi(r) against closed forms and quad."""

import astropy.units as u
import numpy as np
import pytest
from scipy import integrate

from mavispm.dynamics.jeans import G_PC_KMS2_MSUN
from mavispm.dynamics.mass_models import MassModel, mass_model
from mavispm.dynamics.tracers import Cusped, Dehnen, King62, Plummer


def test_plummer_cluster_point_mass_and_dark_component_closed_form():
    """Three analytic pieces: -GM/sqrt(r^2+a^2) - G Mbh / r - G Md / sqrt(r^2+b^2)."""
    mm = MassModel(1e5 * u.Msun, 2.0 * u.pc, Plummer(), 1500 * u.Msun, 3000 * u.Msun, 0.3 * u.pc)
    r = np.array([0.01, 0.3, 1.0, 10.0]) * u.pc
    rv = r.value
    phi = -G_PC_KMS2_MSUN * (1e5 / np.hypot(rv, 2.0) + 1500 / rv + 3000 / np.hypot(rv, 0.3))
    np.testing.assert_allclose(mm.potential(r).to_value(u.km**2 / u.s**2), phi, rtol=1e-12)
    m = 1e5 * rv**3 / (rv**2 + 4.0) ** 1.5 + 1500 + 3000 * rv**3 / (rv**2 + 0.09) ** 1.5
    np.testing.assert_allclose(mm.enclosed_mass(r).to_value(u.Msun), m, rtol=1e-12)


@pytest.mark.parametrize("profile", [Dehnen(1.0), King62(1.33), Cusped(Plummer(), 1.55, 0.3)])
def test_numerical_potential_matches_quad_of_density(profile):
    """Phi(r) = -G [M(r)/r + int_r^inf 4 pi r' rho dr'] by scipy quad of the density."""
    mm = MassModel(1e5 * u.Msun, 1.0 * u.pc, profile)
    rmax = getattr(profile, "tidal_radius", np.inf)
    for r in (0.05, 0.7, 3.0):
        outer = integrate.quad(
            lambda s: 4 * np.pi * s * profile.density(s), r, rmax, limit=400, points=None
        )[0]
        ref = -G_PC_KMS2_MSUN * 1e5 * (float(profile.enclosed(r)) / r + outer)
        got = mm.potential(r * u.pc).to_value(u.km**2 / u.s**2)
        assert got == pytest.approx(ref, rel=2e-4)


def test_mass_model_from_fit_parameters():
    """Arcsec parameters become parsecs at the distance; Hernquist (Dehnen 1) closed form."""
    p = {"log_mass": 5.0, "log_scale_radius": 1.0, "gamma": 1.0, "distance": 5.0}
    mm = mass_model(p, tracer="dehnen")
    a = 10.0 * 5.0 * 1e3 * np.pi / 648000.0
    assert mm.scale_radius.to_value(u.pc) == pytest.approx(a)
    r = 0.4
    phi = -G_PC_KMS2_MSUN * 1e5 / (r + a)  # Hernquist potential
    assert mm.potential(r * u.pc).to_value(u.km**2 / u.s**2) == pytest.approx(phi, rel=1e-4)
    assert mm.escape_speed(r * u.pc).to_value(u.km / u.s) == pytest.approx(np.sqrt(-2 * phi), 1e-4)
    with pytest.raises(ValueError, match="distance"):
        mass_model({"log_mass": 5.0, "log_scale_radius": 1.0})
