"""The scale-radius prior from an observed surface-density profile (issue 13, item 4)."""

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable

from mavispm.core.errors import ConfigError, InputError
from mavispm.dynamics.surface_density import fit_surface_density, read_surface_density

RADII = np.geomspace(5.0, 900.0, 25)  # arcsec, as wide-field photometry gives


def plummer_profile(radius, a, s0=100.0, bg=0.5):
    """Closed-form Plummer (1911) surface density plus a background."""
    return s0 * (1.0 + (radius / a) ** 2) ** -2 + bg


def king62_profile(radius, rc, c, s0=100.0, bg=0.5):
    """King (1962) closed form, written out here (independent of the tracer module)."""
    rt = rc * 10.0**c
    inside = radius < rt
    core = 1.0 / np.sqrt(1.0 + (radius / rc) ** 2) - 1.0 / np.sqrt(1.0 + (rt / rc) ** 2)
    norm = (1.0 - 1.0 / np.sqrt(1.0 + (rt / rc) ** 2)) ** 2
    return s0 * np.where(inside, core**2, 0.0) / norm + bg


def test_plummer_scale_radius_and_its_error_are_calibrated():
    """5% noise on a Plummer profile (a = 121"): over 200 draws the fitted log10 a is
    unbiased, the fit's standard error holds the truth in ~68% of them, and the quoted
    (chi^2-inflated, conservative) error in at least as many."""
    rng = np.random.default_rng(0)
    truth = np.log10(121.0)
    raw, quoted = [], []
    for _ in range(200):
        s = plummer_profile(RADII, 121.0)
        e = 0.05 * s
        fit = fit_surface_density(RADII, s + e * rng.standard_normal(s.size), e)
        assert fit.dof == RADII.size - 3
        dev = fit.log_scale_radius - truth
        inflation = max(1.0, np.sqrt(fit.chi2 / fit.dof))
        raw.append(dev / (fit.log_scale_radius_err / inflation))
        quoted.append(dev / fit.log_scale_radius_err)
    raw, quoted = np.array(raw), np.array(quoted)
    assert abs(np.mean(raw)) < 0.2
    assert 0.6 < np.mean(np.abs(raw) < 1.0) < 0.76
    assert np.mean(np.abs(raw) < 1.0) <= np.mean(np.abs(quoted) < 1.0) < 0.9


def test_king62_core_radius_and_concentration():
    """King62 (r_c = 78", c = 1.33, NGC 3201's Harris values): both recovered within
    their quoted 2-sigma errors, errors of a few per cent in r_c."""
    rng = np.random.default_rng(1)
    s = king62_profile(RADII, 78.0, 1.33)
    e = 0.03 * s + 0.02
    fit = fit_surface_density(RADII, s + e * rng.standard_normal(s.size), e, tracer="king62")
    assert abs(fit.log_scale_radius - np.log10(78.0)) < 2 * fit.log_scale_radius_err
    assert abs(fit.concentration - 1.33) < 2 * fit.concentration_err
    assert fit.log_scale_radius_err < 0.05


def test_wrong_law_inflates_the_prior_width():
    """A King62 cluster fitted with the Plummer law: chi^2/dof >> 1 and the prior is
    sqrt(chi^2/dof) wider than a Plummer fit of a Plummer profile with the same errors,
    so the misfit is not hidden in a tight prior."""
    s = king62_profile(RADII, 78.0, 1.33)
    e = 0.02 * s + 0.01
    assert fit_surface_density(RADII, s, e, tracer="king62").chi2 < 1e-6
    loose = fit_surface_density(RADII, s, e, tracer="plummer")
    assert loose.chi2 / loose.dof > 10
    p = plummer_profile(RADII, 10.0**loose.log_scale_radius, loose.central_density, 0.5)
    exact = fit_surface_density(RADII, p, 0.02 * p + 0.01)
    assert exact.chi2 < 1e-6
    ratio = loose.log_scale_radius_err / exact.log_scale_radius_err
    assert ratio == pytest.approx(np.sqrt(loose.chi2 / loose.dof), rel=0.3)


def test_bad_profiles(tmp_path):
    with pytest.raises(InputError, match="needs >= 4"):
        fit_surface_density([1.0, 2.0, 3.0], [3.0, 2.0, 1.0], [0.1, 0.1, 0.1])
    with pytest.raises(InputError, match="> 0"):
        fit_surface_density(RADII, plummer_profile(RADII, 100.0), np.zeros(RADII.size))
    path = tmp_path / "p.ecsv"
    QTable({"radius": RADII * u.arcmin, "density": np.ones(25)}).write(path)
    with pytest.raises(InputError, match="density_err"):
        read_surface_density(path)
    QTable({"radius": RADII * u.kg, "density": np.ones(25), "density_err": np.ones(25)}).write(
        path, overwrite=True
    )
    with pytest.raises(InputError, match="not an angle"):
        read_surface_density(path)
    (tmp_path / "bad.ecsv").write_text("not a table")
    with pytest.raises(InputError, match="cannot read"):
        read_surface_density(tmp_path / "bad.ecsv")


def test_profile_in_arcmin_is_read_in_arcsec(tmp_path):
    path = tmp_path / "p.ecsv"
    s = plummer_profile(RADII, 121.0)
    QTable({"radius": RADII / 60.0 * u.arcmin, "density": s, "density_err": 0.05 * s}).write(path)
    r, d, e = read_surface_density(path)
    np.testing.assert_allclose(r, RADII)
    assert fit_surface_density(r, d, e).log_scale_radius == pytest.approx(np.log10(121.0), abs=1e-4)


def test_stage_takes_its_scale_radius_prior_from_the_profile(tmp_path):
    """``run_stage(..., surface_density=...)``: the fitted prior is used (the posterior of
    log_scale_radius follows it) and recorded; a second source is a config error."""
    from dynamics_helpers import write_mock_propermotions

    from mavispm.core.products import read_product
    from mavispm.dynamics.cli import run_stage

    pm = write_mock_propermotions(tmp_path / "pm.h5", seed=7, n_field=500)
    prof = tmp_path / "prof.ecsv"
    s = plummer_profile(RADII, 80.0)
    QTable({"radius": RADII * u.arcsec, "density": s, "density_err": 0.01 * s}).write(prof)
    cfg = {
        "walkers": 10,
        "max_steps": 60,
        "check_every": 30,
        "evidence": False,
        "posterior": "emcee",
        "velocity_law": "free_kurtosis",  # one law: no evidences to weigh laws by
        "n_bootstrap": 5,
        "progress": False,
        "field_radius": "15 arcsec",
        "cusp": False,
        "centre_error": 0.0,
        "systemic_error": 0.0,
        "distance_error": 0.0,
        "models": ["none"],
    }
    out = run_stage(pm, cfg, tmp_path / "fit.h5", seed=1, surface_density=prof)
    fit = read_product(out, "dynamics")
    a = fit.attrs
    assert a["surface_density_log_scale_radius"] == pytest.approx(np.log10(80.0), abs=1e-3)
    assert a["surface_density_log_scale_radius_err"] < 0.01
    post = np.asarray(fit.tables["posterior_none"]["log_scale_radius"])
    assert abs(np.median(post) - np.log10(80.0)) < 0.03
    with pytest.raises(ConfigError, match="not both"):
        run_stage(
            pm,
            {**cfg, "log_scale_radius_prior": [1.9, 0.1]},
            tmp_path / "f2.h5",
            seed=1,
            surface_density=prof,
        )
