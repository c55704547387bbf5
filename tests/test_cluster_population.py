"""Mass function, magnitudes, remnants, projection and epochs."""

import astropy.units as u
import numpy as np
import pytest

from mavispm.simulate.cluster import population as pop
from mavispm.simulate.cluster.generator import (
    build_cluster_model,
    n_stars_for_circle,
    simulate_catalogue,
)
from mavispm.simulate.cluster.projection import (
    pm_to_velocity,
    propagate,
    sky_to_field,
    velocity_to_pm,
)
from mavispm.simulate.cluster.settings import ClusterSettings


def test_broken_power_law_sample_matches_analytic_fractions():
    mf = pop.MassFunction(mass_min=0.1, mass_break=0.5, mass_max=10.0)
    masses = mf.sample(np.random.default_rng(0).random(400_000))
    assert masses.min() >= 0.1 and masses.max() <= 10.0
    for lo, hi in [(0.1, 0.2), (0.2, 0.5), (0.5, 1.0), (1.0, 10.0)]:
        expected = mf.number_fraction(lo, hi)
        observed = np.mean((masses >= lo) & (masses < hi))
        assert observed == pytest.approx(expected, abs=4 * np.sqrt(expected / 400_000) + 1e-4)
    # slopes: dN/dlnm ~ m^(1 - alpha) on each side of the break
    lo_ratio = mf.number_fraction(0.1, 0.2) / mf.number_fraction(0.2, 0.4)
    assert lo_ratio == pytest.approx(2 ** (mf.alpha_low - 1), rel=1e-9)


def test_luminosity_function_spans_v14_to_27_at_ngc3201():
    settings = ClusterSettings()
    tables, attrs = simulate_catalogue(settings, seed=5)
    t = tables["e0"]
    lum = np.asarray(t["luminous"], bool)
    mag = t["mag"].to_value(u.mag)[lum]
    assert mag.max() == pytest.approx(27.0, abs=0.3)
    assert np.percentile(mag, 0.5) < 17.5 and mag.min() < 16
    dark = ~lum
    assert dark.sum() > 0 and np.all(t["mag"][dark].value == pop.DARK_MAGNITUDE)
    assert np.all(t["mass"][dark].value >= pop.remnant_mass(pop.tip_mass()))  # WDs and heavier


def test_distance_modulus():
    assert pop.distance_modulus(0.01) == pytest.approx(0.0)
    assert pop.distance_modulus(4.6) == pytest.approx(13.314, abs=1e-3)
    with pytest.raises(ValueError):
        pop.distance_modulus(0.0)


def test_pm_conversion_and_field_rotation():
    assert velocity_to_pm(4.740470463, 1.0) == pytest.approx(1.0, rel=1e-8)
    assert pm_to_velocity(velocity_to_pm(7.3, 4.6), 4.6) == pytest.approx(7.3)
    rng = np.random.default_rng(1)
    x, y, px, py = rng.normal(size=(4, 100))
    xf, yf, pxf, pyf = sky_to_field(x, y, px, py, offset=(0.5, -0.2), rotation=30.0)
    np.testing.assert_allclose(np.hypot(pxf, pyf), np.hypot(px, py))
    np.testing.assert_allclose(np.hypot(xf, yf), np.hypot(x - 0.5, y + 0.2))
    # position angle changes by -30 deg
    d = np.angle((xf + 1j * yf) / ((x - 0.5) + 1j * (y + 0.2)), deg=True)
    np.testing.assert_allclose(d, -30.0, atol=1e-9)
    x10, _ = propagate(np.zeros(1), np.zeros(1), np.array([2.0]), np.zeros(1), 10.0, 0.0)
    assert x10[0] == pytest.approx(0.02)  # 2 mas/yr * 10 yr = 20 mas


def test_imbh_and_no_imbh_share_stars_and_differ_only_dynamically():
    base = ClusterSettings(n_stars=2000, field_size=34.0)
    with_bh = base.replace(imbh_mass=1500.0)
    t0, a0 = simulate_catalogue(base, seed=11)
    t1, a1 = simulate_catalogue(with_bh, seed=11)
    e0, e1 = t0["e0"], t1["e0"]
    n = 2000  # the luminous field group comes first in both, same IDs
    np.testing.assert_array_equal(e0["id"][:n], e1["id"][:n])
    np.testing.assert_array_equal(e0["mag"][:n], e1["mag"][:n])
    np.testing.assert_array_equal(e0["mass"][:n], e1["mass"][:n])
    assert a1["imbh_mass"] == 1500 * u.solMass and a0["imbh_mass"] == 0 * u.solMass
    r0 = np.hypot(e0["x"], e0["y"])[:n].to_value(u.arcsec)
    r1 = np.hypot(e1["x"], e1["y"])[:n].to_value(u.arcsec)
    inner0 = np.std(e0["vx"][:n][r0 < 3].value)
    inner1 = np.std(e1["vx"][:n][r1 < 3].value)
    assert inner1 > 1.2 * inner0  # the IMBH heats the centre


def test_epochs_propagate_with_pm_and_keep_ids():
    settings = ClusterSettings(n_stars=300, epochs=[0.0, 5.0, 10.0], pm_sys_x=1.5)
    tables, _ = simulate_catalogue(settings, seed=2)
    assert list(tables) == ["e0", "e1", "e2"]
    e0, e2 = tables["e0"], tables["e2"]
    assert e2.meta["epoch"] == 10 * u.yr
    np.testing.assert_array_equal(e0["id"], e2["id"])
    dx = (e2["x"] - e0["x"]).to_value(u.mas)
    np.testing.assert_allclose(dx, 10 * e0["pm_x"].to_value(u.mas / u.yr), rtol=1e-9, atol=1e-9)
    model = build_cluster_model(settings)
    v_from_pm = pm_to_velocity(e0["pm_x"].value - 1.5, model.params["distance"])
    np.testing.assert_allclose(v_from_pm, e0["vx"].value, rtol=1e-9, atol=1e-9)


def test_offset_field_gets_about_the_requested_count():
    settings = ClusterSettings(n_stars=1500, offset_x=20.0, offset_y=-5.0, rotation=25.0)
    tables, _ = simulate_catalogue(settings, seed=4)
    t = tables["e0"]
    inside = (np.abs(t["x"].value) <= 15) & (np.abs(t["y"].value) <= 15) & t["luminous"]
    assert abs(inside.sum() - 1500) < 5 * np.sqrt(1500)
    assert np.all(np.abs(t["x"].value) <= 16 + 1e-9) and np.all(np.abs(t["y"].value) <= 16 + 1e-9)


def test_n_stars_for_circle_gives_the_requested_inner_count():
    base = ClusterSettings(field_size=34.0, imbh_mass=1500.0)
    n = n_stars_for_circle(base, 2000, 17.0)
    assert n > 2000
    tables, _ = simulate_catalogue(base.replace(n_stars=n), seed=8)
    t = tables["e0"]
    inner = (np.hypot(t["x"], t["y"]).to_value(u.arcsec) < 17.0) & t["luminous"]
    assert abs(inner.sum() - 2000) < 4 * np.sqrt(2000)


def test_mass_groups_match_quadrature_of_the_mass_function():
    """Group numbers and mean masses against scipy quad of the IMF and the IFMRs."""
    from scipy.integrate import quad

    mf = pop.MassFunction(alpha_low=0.5)
    groups = pop.mass_groups(mf, True, ns_retention=0.1, bh_retention=0.5)

    def dn(m):  # unnormalised broken power law
        return (
            m**-mf.alpha_low
            if m < mf.mass_break
            else (mf.mass_break ** (mf.alpha_high - mf.alpha_low) * m**-mf.alpha_high)
        )

    total = quad(dn, mf.mass_min, mf.mass_break)[0] + quad(dn, mf.mass_break, mf.mass_max)[0]
    final = {
        "star": lambda m: m,
        "white_dwarf": lambda m: min(0.109 * m + 0.394, 1.2),
        "neutron_star": lambda m: 1.3 + 0.1 * (m - 8.0) / 17.0,
        "black_hole": lambda m: min(5.0 + (m - 25.0) / 3.0, 30.0),
    }
    keep = {"neutron_star": 0.1, "black_hole": 0.5}
    kinds = [g.kind for g in groups]
    assert kinds == ["star"] * 4 + ["white_dwarf"] * 2 + ["neutron_star", "black_hole"]
    for g in groups:
        pts = [mf.mass_break] if g.lo < mf.mass_break < g.hi else None
        n = quad(dn, g.lo, g.hi, points=pts)[0] / total * keep.get(g.kind, 1.0)
        fin = final[g.kind]
        m = quad(lambda x, fin=fin: dn(x) * fin(x), g.lo, g.hi, points=pts, limit=200)[0]
        m = m / total * keep.get(g.kind, 1.0)
        assert g.number == pytest.approx(n, rel=1e-6)
        assert g.mean_mass == pytest.approx(m / n, rel=2e-4)
