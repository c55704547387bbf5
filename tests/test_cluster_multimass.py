"""Multi-mass, segregated, anisotropic clusters (issue 12) against independent references.

The Jeans references (tests/cluster_helpers.py) integrate the Jeans equation of each
mass group in the total potential with scipy quad from the model's density
functions only: they never use the generator's DF or quantile tables.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from cluster_helpers import (
    JeansReference,
    MultiMassJeansReference,
    binned_dispersion_chi2,
    pm2_interpolators,
    sky_components,
)
from hypothesis import HealthCheck, example, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from mavispm.simulate.cluster import population as pop
from mavispm.simulate.cluster.eddington import NoIsotropicDFError
from mavispm.simulate.cluster.generator import (
    build_cluster_model,
    sample_stars,
    simulate_catalogue,
)
from mavispm.simulate.cluster.settings import ClusterKnobs, ClusterSettings

N_BINS = 15
#: Osipkov-Merritt radius used in the tests [arcsec] (6.7 pc at 4.6 kpc).
RA_ARCSEC = 300.0


@functools.lru_cache(maxsize=4)
def _sampled(imbh: float, ra: float | None, n_stars: int, seed: int = 5, beta: float = 0.0):
    settings = ClusterSettings(
        preset="ngc3201-nbody",
        imbh_mass=imbh,
        anisotropy_radius=ra,
        n_stars=n_stars,
        anisotropy_beta=beta,
    )
    model = build_cluster_model(settings)
    stars, _ = sample_stars(settings, seed, model)
    return settings, model, stars


_TOTALS: dict = {}


def _reference(model, group: int):
    comp = next(c for c in model.components if group in c.groups)
    ra = model.params["anisotropy_radius"]
    key = id(model)
    if key not in _TOTALS:  # M_tot(r) by quad, shared by the groups of one model
        _TOTALS[key] = (
            model,
            JeansReference(
                model.total_density, model.params["bh_mass"], comp.mass.r[0], comp.mass.r_max
            ),
        )
    return MultiMassJeansReference(
        comp.mass.density,
        _TOTALS[key][1],
        model.params["bh_mass"],
        comp.mass.r[0],
        comp.mass.r_max,
        np.inf if ra is None else ra,
        model.params["anisotropy_beta"],
    )


def _check_group(model, stars, group: int):
    sel = stars["group"] == group
    sub = {k: v[sel] for k, v in stars.items()}
    R, v_rad, v_tan = sky_components(sub)
    s_rad, s_tan = pm2_interpolators(_reference(model, group), R.min(), R.max())
    out = []
    for v, s2 in ((v_rad, s_rad), (v_tan, s_tan)):
        chi2, dof = binned_dispersion_chi2(R, v, s2, N_BINS, min_per_bin=300)
        out.append(chi2 / dof)
    return out


def test_group_pm_dispersions_match_multimass_jeans():
    """Lightest stars and heavy white dwarfs (IMBH + OM), 1e5 field objects in all."""
    _, model, stars = _sampled(1500.0, RA_ARCSEC, 70_000)
    assert stars["x"].size >= 100_000
    groups = model.params["groups"]
    kinds = [g["kind"] for g in groups]
    for g in (0, len(kinds) - 1 - kinds[::-1].index("white_dwarf")):
        chi_rad, chi_tan = _check_group(model, stars, g)
        assert chi_rad < 2.2 and chi_tan < 2.2, (groups[g]["kind"], chi_rad, chi_tan)


def test_constant_beta_group_pm_dispersions_match_jeans():
    """Tangential constant-beta DF (Cuddeford), IMBH: the giant / turn-off group."""
    _, model, stars = _sampled(1500.0, None, 40_000, 6, -0.3)
    for g in (3,):
        chi_rad, chi_tan = _check_group(model, stars, g)
        assert chi_rad < 2.2 and chi_tan < 2.2, (g, chi_rad, chi_tan)


@pytest.mark.parametrize("beta, extra", [(-0.3, {}), (0.3, {"core_collapse": True})])
def test_constant_beta_profile_from_3d_velocities(beta, extra):
    settings = ClusterSettings(
        preset="ngc3201-nbody", anisotropy_beta=beta, n_stars=30_000, **extra
    )
    stars, _ = sample_stars(settings, 3)
    pos = np.stack([stars["x"], stars["y"], stars["z"]])
    vel = np.stack([stars["vx"], stars["vy"], stars["vz"]])
    r = np.sqrt(np.sum(pos**2, axis=0))
    v_r = np.sum(pos * vel, axis=0) / r
    v_t2 = np.sum(vel**2, axis=0) - v_r**2
    for idx in np.array_split(np.argsort(r), 6):
        sr2, st2 = np.mean(v_r[idx] ** 2), np.mean(v_t2[idx]) / 2
        e_sr = np.std(v_r[idx] ** 2) / np.sqrt(idx.size)
        e_st = np.std(v_t2[idx] / 2) / np.sqrt(idx.size)
        err = (st2 / sr2) * np.hypot(e_sr / sr2, e_st / st2)
        assert abs(1 - st2 / sr2 - beta) < 4 * err


def test_radial_constant_beta_needs_a_cusp():
    """A cored model cannot be radially anisotropic at its centre (An & Evans 2006)."""
    with pytest.raises(NoIsotropicDFError, match="anisotropy_beta"):
        build_cluster_model(ClusterSettings(preset="ngc3201-nbody", anisotropy_beta=0.3))


@pytest.mark.slow
@pytest.mark.parametrize("imbh", [0.0, 1500.0])
@pytest.mark.parametrize("ra", [None, RA_ARCSEC])
def test_every_group_matches_multimass_jeans(imbh, ra):
    _, model, stars = _sampled(imbh, ra, 200_000, seed=9)
    for g in range(len(model.params["groups"])):
        if np.count_nonzero(stars["group"] == g) < N_BINS * 300:
            continue
        chi_rad, chi_tan = _check_group(model, stars, g)
        assert chi_rad < 2.0 and chi_tan < 2.0, (g, chi_rad, chi_tan)


def test_jeans_check_has_power_against_the_isotropic_model():
    """The OM sample is rejected by the isotropic reference of the same densities."""
    _, model, stars = _sampled(1500.0, RA_ARCSEC, 70_000)
    iso = build_cluster_model(ClusterSettings(preset="ngc3201-nbody", imbh_mass=1500.0, n_stars=10))
    sel = stars["group"] == 0
    sub = {k: v[sel] for k, v in stars.items()}
    R, v_rad, v_tan = sky_components(sub)
    s_rad, s_tan = pm2_interpolators(_reference(iso, 0), R.min(), R.max())
    chi_t, dof = binned_dispersion_chi2(R, v_tan, s_tan, N_BINS, min_per_bin=300)
    chi_r, _ = binned_dispersion_chi2(R, v_rad, s_rad, N_BINS, min_per_bin=300)
    assert max(chi_t, chi_r) / dof > 4.0


def test_heavy_groups_are_more_concentrated_and_colder():
    _, model, stars = _sampled(1500.0, RA_ARCSEC, 70_000)
    groups = model.params["groups"]
    field = stars["region"] == 0
    R = np.hypot(stars["x"], stars["y"])
    light = field & (stars["group"] == 0)
    heavy = field & (stars["group"] == 3)  # the turn-off / giant group
    assert groups[0]["mean_mass"] < 0.3 < 0.7 < groups[3]["mean_mass"]
    # model: scale radius falls with mass; sample: heavy stars sit closer to the centre
    radii = [g["scale_radius"] for g in groups if not g["fixed_range"]]
    means = [g["mean_mass"] for g in groups if not g["fixed_range"]]
    assert np.all(np.diff(np.array(radii)[np.argsort(means)]) <= 0)
    # heavy objects are over-represented in the central field against the whole cluster
    ratio_field = heavy.sum() / light.sum()
    ratio_all = groups[3]["number"] / groups[0]["number"]
    err = ratio_field * np.sqrt(1 / heavy.sum() + 1 / light.sum())
    assert ratio_field - ratio_all > 4 * err
    # and, inside the field, concentrated towards its centre more than light stars
    inner = [np.mean(R[sel] < 0.1) for sel in (light, heavy)]
    assert inner[1] > inner[0]
    # light stars move faster inside the field (the model's prediction, checked per group above)
    disp = [np.sqrt(np.mean(stars["vx"][s] ** 2 + stars["vy"][s] ** 2)) for s in (light, heavy)]
    errd = disp[0] / np.sqrt(2 * np.count_nonzero(light)) + disp[1] / np.sqrt(2 * heavy.sum())
    assert disp[0] - disp[1] > 4 * errd


def test_unsegregated_groups_share_one_component():
    model = build_cluster_model(ClusterSettings(n_stars=10))
    assert len(model.components) == 1 and model.params["segregation"] == 0


def test_osipkov_merritt_beta_profile_from_3d_velocities():
    _, model, stars = _sampled(1500.0, RA_ARCSEC, 70_000)
    ra = model.params["anisotropy_radius"]
    pos = np.stack([stars["x"], stars["y"], stars["z"]])
    vel = np.stack([stars["vx"], stars["vy"], stars["vz"]])
    r = np.sqrt(np.sum(pos**2, axis=0))
    v_r = np.sum(pos * vel, axis=0) / r
    v_t2 = np.sum(vel**2, axis=0) - v_r**2
    order = np.argsort(r)
    chi2, n = 0.0, 0
    for idx in np.array_split(order, 20):
        sr2, st2 = np.mean(v_r[idx] ** 2), np.mean(v_t2[idx]) / 2
        beta = 1 - st2 / sr2
        # delta-method error from the sample variances of v_r^2 and v_t^2 / 2
        e_sr = np.std(v_r[idx] ** 2) / np.sqrt(idx.size)
        e_st = np.std(v_t2[idx] / 2) / np.sqrt(idx.size)
        err = (st2 / sr2) * np.hypot(e_sr / sr2, e_st / st2)
        rm = np.median(r[idx])
        expect = np.mean(r[idx] ** 2 / (r[idx] ** 2 + ra**2))
        chi2 += ((beta - expect) / err) ** 2
        n += 1
        assert abs(beta - expect) < 5 * err, (rm, beta, expect, err)
    assert chi2 / n < 2.5
    assert np.max(r) > ra  # the test spans the isotropic and the radial regime


def test_catalogue_kinds_masses_and_imbh_row():
    settings = ClusterSettings(
        preset="ngc3201-nbody", imbh_mass=1500.0, bh_subsystem_mass=1000.0, n_stars=3000
    )
    tables, attrs = simulate_catalogue(settings, seed=4)
    t = tables["e0"]
    kind = np.asarray(t["kind"])
    mass = t["mass"].value
    lum = np.asarray(t["luminous"])
    np.testing.assert_array_equal(lum, kind == "star")
    assert np.all(t["mag"].value[~lum] == pop.DARK_MAGNITUDE)
    wd, ns, bh = (kind == k for k in ("white_dwarf", "neutron_star", "black_hole"))
    assert wd.sum() > 500 and ns.sum() >= 1 and bh.sum() >= 1
    assert np.all((mass[wd] >= 0.48) & (mass[wd] <= 1.2))
    assert np.all((mass[ns] >= 1.3) & (mass[ns] <= 1.4))
    assert np.all((mass[bh] >= 10) & (mass[bh] <= 20))
    assert np.all(mass[lum] <= pop.tip_mass())
    (imbh,) = np.flatnonzero(kind == "imbh")
    assert mass[imbh] == 1500.0 and t["x"][imbh].value == 0 and not lum[imbh]
    # the black-hole subsystem is far more concentrated than the stars
    R = np.hypot(t["x"].value, t["y"].value)
    assert np.median(R[bh]) < np.median(R[lum])
    params = attrs["model_params"]
    dark = sum(g["mass"] for g in params["groups"] if g["kind"] != "star")
    assert 0.3 < dark / params["stellar_mass"] < 0.5  # N-body-like remnant mass fraction


def test_imbh_and_no_imbh_nbody_catalogues_share_objects():
    base = ClusterSettings(preset="ngc3201-nbody", n_stars=1500, anisotropy_radius=RA_ARCSEC)
    t0, _ = simulate_catalogue(base, seed=8)
    t1, _ = simulate_catalogue(base.replace(imbh_mass=1500.0), seed=8)
    a, b = t0["e0"], t1["e0"]
    common, ia, ib = np.intersect1d(np.asarray(a["id"]), np.asarray(b["id"]), return_indices=True)
    assert common.size > 0.95 * len(a)
    np.testing.assert_array_equal(a["mass"][ia], b["mass"][ib])
    np.testing.assert_array_equal(a["mag"][ia], b["mag"][ib])
    np.testing.assert_array_equal(np.asarray(a["kind"])[ia], np.asarray(b["kind"])[ib])


def test_core_collapse_cusp_has_the_post_collapse_projected_slope():
    settings = ClusterSettings(
        preset="ngc3201-nbody", core_collapse=True, n_stars=60_000, include_remnants=False
    )
    stars, model = sample_stars(settings, seed=3)
    assert model.params["cusp_gamma"] == pytest.approx(1.8) and model.params["bh_mass"] == 0
    field = stars["region"] == 0
    R = np.hypot(stars["x"], stars["y"])[field]
    edges = np.geomspace(0.02, 0.3, 9)  # pc, circles inside the 30" field (0.33 pc half-size)
    counts, _ = np.histogram(R, edges)
    area = np.pi * np.diff(edges**2)
    mid = np.sqrt(edges[1:] * edges[:-1])
    slope, cov = np.polyfit(np.log(mid), np.log(counts / area), 1, w=np.sqrt(counts), cov=True)
    assert slope[0] == pytest.approx(-0.8, abs=max(0.1, 4 * np.sqrt(cov[0, 0])))


FAST = ClusterKnobs(n_energy=300, n_rows=40, n_levels=129, n_los=128, n_speed=128)


# ---------------------------------------------------------------- stress and bad input
#: Words a refusal must contain: the setting to change.
SETTING_NAMES = (
    "anisotropy_radius",
    "anisotropy_beta",
    "segregation",
    "cusp",
    "bh_subsystem",
    "IMBH",
)


@hsettings(
    max_examples=8,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    mass=st.floats(2e4, 1e6),
    ns=st.floats(0.0, 1.0),
    bh=st.floats(0.0, 1.0),
    ra=st.one_of(st.none(), st.floats(20.0, 3000.0), st.floats(-0.45, 0.45)),
    bhs=st.floats(0.0, 5000.0),
    imbh=st.sampled_from([0.0, 300.0, 3000.0, 30000.0]),
)
@example(mass=20000.0, ns=0.0, bh=0.0, ra=None, bhs=5e-324, imbh=0.0)
@example(mass=20000.0, ns=0.0, bh=2.225073858507e-311, ra=None, bhs=0.0, imbh=0.0)
def test_stress_models_are_finite_reproducible_or_clearly_refused(mass, ns, bh, ra, bhs, imbh):
    try:
        settings = ClusterSettings(
            preset="ngc3201-nbody",
            stellar_mass=mass,
            ns_retention=ns,
            bh_retention=bh,
            anisotropy_radius=ra if ra is None or ra > 1 else None,
            anisotropy_beta=ra if ra is not None and ra < 1 else 0.0,
            bh_subsystem_mass=bhs,
            imbh_mass=imbh,
            n_stars=300,
            knobs=FAST,
        )
        model = build_cluster_model(settings)
    except (NoIsotropicDFError, ValueError) as exc:
        msg = str(exc)
        assert "\n" not in msg and any(k in msg for k in SETTING_NAMES), msg
        return
    for comp in model.components:
        assert np.all(np.isfinite(comp.df.f)) and np.all(comp.df.f >= 0)
        assert comp.df.min_raw >= -1e-6
    a, _ = sample_stars(settings, 2, model)
    b, _ = sample_stars(settings, 2, model)
    for key in ("x", "y", "z", "vx", "vy", "vz", "mass"):
        assert np.all(np.isfinite(a[key]))
        np.testing.assert_array_equal(a[key], b[key])
    # every object is bound in the total potential
    psi = model.components[0].mass.relative_potential(a["r3d"])
    v2 = a["vx"] ** 2 + a["vy"] ** 2 + a["vz"] ** 2
    assert np.all(v2 < 2 * psi)


@pytest.mark.parametrize(
    "args, key",
    [
        (["--segregation", "-1"], "segregation"),
        (["--anisotropy-radius", "0"], "anisotropy_radius"),
        (["--bh-subsystem-mass", "-5"], "bh_subsystem_mass"),
        (["--bh-subsystem-mass", "1e5"], "bh_subsystem_mass"),
        (["--anisotropy-radius", "60"], "anisotropy_radius"),  # inside the core: no OM DF
        (["--anisotropy-beta", "0.5"], "anisotropy_beta"),
        (["--anisotropy-beta", "0.2", "--anisotropy-radius", "300"], "anisotropy_beta"),
    ],
)
def test_cli_bad_new_settings_one_line_and_no_output(tmp_path, capsys, args, key):
    from mavispm.workflows.cli import main

    out = tmp_path / "c.h5"
    base = ["simulate", "cluster", "--preset", "ngc3201-nbody", "--n-stars", "50", "-o", str(out)]
    rc = main(base + args)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and key in err and len(err.splitlines()) == 1, err
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "table, key",
    [
        ({"ns_retention": 2.0}, "ns_retention"),
        ({"bh_retention": -0.1}, "bh_retention"),
        ({"bh_subsystem_radius": -1.0}, "bh_subsystem_radius"),
        ({"external": "{dark_flux = -1.0}"}, "dark_flux"),
        ({"anisotropy_beta": 0.7}, "anisotropy_beta"),
        ({"alpha_low": 9.0}, "alpha_low"),
        ({"core_collapse": '"yes"'}, "core_collapse"),
        # a compact, massive BH subsystem without IMBH: cored light stars have no DF
        (
            {"preset": '"ngc3201-nbody"', "bh_subsystem_mass": 5000.0, "bh_subsystem_radius": 0.3},
            "bh_subsystem",
        ),
        ({"preset": '"ngc3201-nbody"', "tracer": '"king"', "segregation": 1.5}, "segregation"),
    ],
)
def test_toml_bad_new_settings_are_named(tmp_path, capsys, table, key):
    from mavispm.workflows.cli import main

    cfg = tmp_path / "s.toml"
    cfg.write_text("[cluster]\n" + "".join(f"{k} = {v}\n" for k, v in table.items()))
    out = tmp_path / "c.h5"
    rc = main(["simulate", "cluster", "--config", str(cfg), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and key in err and len(err.splitlines()) == 1, err
    assert not out.exists()


# ---------------------------------------------------------------- external input
def test_mavisim_tiny_fluxes_are_dark_and_imbh_recorded(tmp_path):
    from mavispm.core.catalogue import read_catalogue
    from mavispm.simulate.cluster.cli import run_stage

    rows = ["Star RA Dec X Y Flux PM_X PM_Y Mass"]
    for i, (flux, mass) in enumerate([(1.0e6, 0.8), (1.8e-4, 0.6), (2.0e-4, 1.35), (3e-4, 12.0)]):
        rows.append(
            f"{i + 1} 154.40 -46.41 {0.5 * i:.2f} {20.0 * (i == 3):.2f} {flux} 0.01 0.0 {mass}"
        )
    path = tmp_path / "mavisim_10yr.txt"
    path.write_text("\n".join(rows) + "\n")
    ext = {
        "path": str(path),
        "format": "mavisim",
        "pm_convention": "arcsec_per_baseline",
        "flux_zeropoint": 29.08,
    }
    out = run_stage({"external": ext, "imbh_mass": 1500.0}, tmp_path / "m.h5", 0)
    cat = read_catalogue(out)
    t = cat.epochs["e0"]
    np.testing.assert_array_equal(np.asarray(t["luminous"]), [True, False, False, False])
    np.testing.assert_array_equal(
        np.asarray(t["kind"]), ["star", "white_dwarf", "neutron_star", "black_hole"]
    )
    assert t["mag"].value[0] == pytest.approx(29.08 - 15.0)
    assert cat.attrs["imbh_mass"].value == 1500.0
    # the 10" default margin of MAVISIM lists keeps the object 20" from the centre (5" outside the field)
    assert len(t) == 4
    # one later-epoch list gives both epochs: x(10 yr) = X + PM_X
    e1 = cat.epochs["e1"]
    np.testing.assert_allclose((e1["x"] - t["x"]).to_value("arcsec"), 0.01)


def test_cli_nbody_preset_writes_kinds_and_model(tmp_path, capsys):
    import json

    from mavispm.core.catalogue import read_catalogue
    from mavispm.workflows.cli import main

    out = tmp_path / "c.h5"
    args = ["simulate", "cluster", "--preset", "ngc3201-nbody", "--imbh-mass", "1500"]
    args += ["--anisotropy-radius", "300", "--bh-subsystem-mass", "500", "--n-stars", "400"]
    assert main(args + ["-o", str(out)]) == 0
    cat = read_catalogue(out)
    kinds = set(np.asarray(cat.epochs["e0"]["kind"]).tolist())
    assert {"star", "white_dwarf", "imbh"} <= kinds
    params = cat.attrs["model_params"]
    params = json.loads(params) if isinstance(params, str) else params
    assert params["segregation"] == 0.4 and params["bh_subsystem_mass"] == 500.0
    assert params["anisotropy_radius"] == pytest.approx(300 * 4.6 / 206.264806, rel=1e-6)


@pytest.mark.parametrize(
    "beta, ra", [(0.0, np.inf), (-0.3, np.inf), (0.2, np.inf), (0.0, 3.0)], ids=str
)
def test_anisotropic_dfs_reproduce_the_density(beta, ra):
    """Velocity-space quadrature of the tabulated DF gives back rho(r) (1 %).

    Constant beta: ``rho = r^(-2 beta) C_beta int_0^Psi (Psi - E)^(1/2 - beta) g(E) dE``;
    Osipkov-Merritt: ``rho = 4 pi sqrt(2) int_0^Psi f(Q) sqrt(Psi - Q) dQ / (1 + r^2/r_a^2)``.
    """
    from scipy.integrate import quad
    from scipy.special import gamma as gamma_fn

    from mavispm.simulate.cluster.eddington import eddington_df
    from mavispm.simulate.cluster.profiles import TracerProfile, build_mass_model

    tracer = TracerProfile("plummer", 2.0, cusp_gamma=1.55, cusp_radius=0.5)
    model = build_mass_model(tracer, 1e5, 1000.0)
    df = eddington_df(model, beta=beta, anisotropy_radius=ra)
    c_beta = 2 ** (1.5 - beta) * np.pi**1.5 * gamma_fn(1 - beta) / gamma_fn(1.5 - beta)
    for r in (0.01, 0.3, 3.0):
        psi = float(model.relative_potential(r))
        integral = quad(
            lambda e, psi=psi: df(np.array([e]))[0] * (psi - e) ** (0.5 - beta),
            0,
            psi,
            limit=400,
        )[0]
        rho = c_beta * integral * r ** (-2 * beta)
        if np.isfinite(ra):
            rho /= 1 + (r / ra) ** 2
        assert rho == pytest.approx(float(model.density(r)), rel=0.01), r
