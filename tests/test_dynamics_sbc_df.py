"""The equilibrium (distribution-function) velocities of the SBC forward model
(``tests/sbc_helpers.py``, ``velocities = "df"``).

Independent truths: the analytic Plummer DF and the Keplerian cusp's power-law DF for the
Abel inversion; the Jeans dispersions (the Jeans equation is the DF's second moment) and
the tracer density (its zeroth) for the DF of the SBC's models; the escape speed for the
samples; the cluster generator's own inversion (``simulate/cluster/eddington.py``).
"""

import os

import numpy as np
import pytest
import sbc_helpers as h
from scipy.special import beta as beta_fn
from scipy.special import gamma as gamma_fn

#: Models of the DF prior (rounded prior draws): an IMBH with radial and tangential
#: anisotropy, a heavy IMBH in a steep cusp, an IMBH with the extended dark component.
MODELS = {
    "radial": dict(
        log_mass=4.84, log_scale_radius=2.012, gamma=1.417, log_cusp_radius=2.16,
        bh_mass=1910.8, beta=0.245, distance=4.559, x0=-0.207, y0=-0.453, pm_x0=-0.058,
        pm_y0=0.033,
    ),
    "tangential": dict(
        log_mass=5.205, log_scale_radius=2.069, gamma=0.942, log_cusp_radius=2.322,
        bh_mass=2678.0, beta=-0.135, distance=4.596, x0=-0.409, y0=0.085, pm_x0=0.01,
        pm_y0=0.031,
    ),
    "heavy": dict(
        log_mass=5.334, log_scale_radius=2.047, gamma=1.891, log_cusp_radius=1.964,
        bh_mass=9710.1, beta=0.22, distance=4.592, x0=1.037, y0=-0.087, pm_x0=-0.027,
        pm_y0=-0.021,
    ),
    "dark": dict(
        log_mass=5.287, log_scale_radius=2.075, gamma=1.101, log_cusp_radius=1.707,
        bh_mass=444.7, dark_mass=6488.4, log_dark_radius=0.343, beta=-0.337, distance=4.58,
        x0=-0.475, y0=-0.08, pm_x0=0.017, pm_y0=0.027,
    ),
}  # fmt: skip

#: r / a where the moments are compared (the field's stars lie at ~1e-3-0.2)
RADII = np.array([1e-4, 1e-3, 1e-2, 0.1, 0.5, 2.0])


def _grid():
    x = np.exp(h.LN_X)
    return x[x >= 1e-6]


def test_inversion_recovers_the_plummer_df():
    """Self-consistent Plummer sphere (G = M = a = 1, density (1 + x^2)^-5/2 without its
    3 / 4 pi): f = 24 sqrt(2) / (7 pi^3) E^(7/2) times 4 pi / 3 (Dejonghe 1987), and
    Psi = (1 + x^2)^-1/2."""
    x = _grid()
    nu, mass = (1 + x * x) ** -2.5, x**3 / (1 + x * x) ** 1.5
    psi, e, g = h.cuddeford_g(x, nu, -5 * x * x / (1 + x * x), mass, 0.0)
    np.testing.assert_allclose(psi, (1 + x * x) ** -0.5, rtol=1e-5)
    sel = (e > 1e-3) & (e < 0.999)
    exact = 24 * np.sqrt(2) / (7 * np.pi**3) * e[sel] ** 3.5 * 4 * np.pi / 3
    np.testing.assert_allclose(g[sel], exact, rtol=1e-3)


@pytest.mark.parametrize(
    "gam, beta", [(1.5, 0.0), (1.75, 0.25), (1.0, -0.25), (1.2, -0.4), (2.0, 0.2)]
)
def test_inversion_recovers_the_keplerian_cusp(gam, beta):
    """nu = r^-gamma around a unit point mass (Psi = 1 / r): r^(2 beta) nu = Psi^(gamma - 2
    beta) = C_beta int (Psi - E)^(1/2 - beta) A E^p dE gives p = gamma - beta - 3/2 and
    A = 1 / (C_beta B(gamma - beta - 1/2, 3/2 - beta)) (Cuddeford 1991; for beta = 0
    f ~ E^(gamma - 3/2)). With gamma - 2 beta > 1 (d rho_b / d Psi -> 0 at Psi -> 0, as for
    any finite cluster; the inversion's second form assumes it)."""
    x = _grid()
    psi, e, g = h.cuddeford_g(
        x, x ** (2 * beta - gam), np.full_like(x, 2 * beta - gam), np.ones_like(x), beta
    )
    c_beta = 2 ** (1.5 - beta) * np.pi**1.5 * gamma_fn(1 - beta) / gamma_fn(1.5 - beta)
    amp = 1.0 / (c_beta * beta_fn(gam - beta - 0.5, 1.5 - beta))
    sel = (e > 1e-2) & (e < 1e4)
    np.testing.assert_allclose(g[sel], amp * e[sel] ** (gam - beta - 1.5), rtol=1e-3)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_df_moments_are_the_density_and_the_jeans_dispersions(name):
    """The DF's zeroth moment is the tracer density, its radial second moment the Jeans
    sigma_r^2 of ``sigma_r2_3d`` (the constant-beta Jeans equation), to 1 %."""
    p = MODELS[name]
    df = h.df_tables(p)
    assert df["min_g"] >= -h.DF_NEGATIVE_TOLERANCE
    psi = np.exp(np.interp(np.log(RADII), np.log(df["x"]), np.log(df["psi"])))
    nu_b, s2r, s2t = h.df_moments(df["energy"], df["g"], p["beta"], psi)
    nu = np.exp(np.interp(np.log(RADII), np.log(df["x"]), np.log(df["nu"])))
    np.testing.assert_allclose(nu_b / RADII ** (2 * p["beta"]), nu, rtol=0.01)
    jeans = h.sigma_r2_3d(p, RADII) / h._dispersion_unit(p)
    np.testing.assert_allclose(s2r, jeans, rtol=0.01)


@pytest.mark.parametrize("name", ["radial", "dark"])
def test_df_samples_have_the_jeans_dispersions_and_stay_bound(name):
    """Drawn 3-D velocities: <v_r^2> the Jeans sigma_r^2, each tangential <v_t^2> =
    (1 - beta) sigma_r^2 (40,000 draws per radius: 3 % is > 4 standard errors), means
    zero, and no speed above the local escape speed sqrt(2 Psi)."""
    p = MODELS[name]
    df = h.df_tables(p)
    rng = np.random.default_rng(5)
    n = 40_000
    for xr in (1e-3, 3e-2, 0.3):
        psi = float(np.exp(np.interp(np.log(xr), np.log(df["x"]), np.log(df["psi"]))))
        v_r, v_1, v_2 = h.df_velocities(df["energy"], df["g"], p["beta"], np.full(n, psi), rng)
        jeans = float(h.sigma_r2_3d(p, np.array([xr]))[0] / h._dispersion_unit(p))
        np.testing.assert_allclose(np.mean(v_r**2), jeans, rtol=0.03)
        for vt in (v_1, v_2):
            np.testing.assert_allclose(np.mean(vt**2), (1 - p["beta"]) * jeans, rtol=0.03)
        for v in (v_r, v_1, v_2):
            assert abs(np.mean(v)) < 5 * np.sqrt(jeans / n)
        speed = np.sqrt(v_r**2 + v_1**2 + v_2**2)
        assert speed.max() <= np.sqrt(2 * psi) * (1 + 1e-9)
        assert speed.max() > 0.8 * np.sqrt(2 * psi)  # the DF reaches towards the escape speed


def test_df_catalogue_respects_the_escape_speed_in_projection():
    """``draw_sample(..., "df")``: no star's sky-plane motion about the true centre exceeds
    the escape speed at its projected radius (a lower bound on its 3-D radius) by more
    than 5 of its errors; Gaussian 3-D velocities ("3d", the same model) do."""
    p = MODELS["heavy"]
    df = h.df_tables(p)
    a = 10.0 ** p["log_scale_radius"]

    def excess(velocities):
        stars = h.draw_sample(p, 20_000, np.random.default_rng(3), velocities, 15.0, df)
        R, v_R, v_T, e2_R, e2_T = h._about_centre(p, stars)
        psi = np.exp(np.interp(np.log(R / a), np.log(df["x"]), np.log(df["psi"])))
        v_esc = np.sqrt(2 * psi * h._dispersion_unit(p))
        return np.sum(np.hypot(v_R, v_T) > v_esc + 5 * np.sqrt(e2_R + e2_T))

    assert excess("df") == 0
    assert excess("3d") > 5


@pytest.mark.parametrize("name", ["radial", "tangential"])
def test_df_agrees_with_the_generators_inversion(name):
    """The cluster generator's ``eddington_df`` (first-form Abel integral, Gauss-Legendre
    nodes, spline derivative; its potential zero at 1000 Plummer radii) for the same tracer,
    mass and IMBH: g(E) up to a constant (units) within 2 % at E = 0.7 Psi(r), r / a from
    1e-4 to 10."""
    from mavispm.simulate.cluster.eddington import eddington_df
    from mavispm.simulate.cluster.profiles import G_PC, TracerProfile, build_mass_model

    p = MODELS[name]
    df = h.df_tables(p)
    pc = p["distance"] * h.PC_PER_ARCSEC_KPC
    a_pc = 10 ** p["log_scale_radius"] * pc
    tracer = TracerProfile(
        "plummer", a_pc, cusp_gamma=p["gamma"], cusp_radius=10 ** p["log_cusp_radius"] * pc
    )
    model = build_mass_model(tracer, 10 ** p["log_mass"], p["bh_mass"])
    gen = eddington_df(model, beta=p["beta"])
    offset = G_PC * (10 ** p["log_mass"] + p["bh_mass"]) / model.r[-1]
    xs = np.geomspace(1e-4, 10, 30)
    e = 0.7 * np.exp(np.interp(np.log(xs), np.log(df["x"]), np.log(df["psi"])))
    mine = np.exp(np.interp(np.log(e), np.log(df["energy"]), np.log(df["g"])))
    ratio = gen(e * G_PC / a_pc - offset) / mine
    np.testing.assert_allclose(ratio / np.median(ratio), 1.0, rtol=0.02)


def test_negative_df_is_flagged_and_redrawn():
    """A cusp ending well inside the IMBH's influence radius (flat tracer between r_c and
    the Plummer radius) has no DF of this family: flagged here, refused by the generator,
    and ``draw_truth`` redraws such draws from the (unrestricted) prior."""
    from mavispm.simulate.cluster.eddington import NoIsotropicDFError, eddington_df
    from mavispm.simulate.cluster.profiles import TracerProfile, build_mass_model

    p = dict(MODELS["radial"], log_cusp_radius=-0.6, beta=0.18, bh_mass=5000.0)
    assert h.df_tables(p, n_energy=800)["min_g"] < -0.1
    pc = p["distance"] * h.PC_PER_ARCSEC_KPC
    tracer = TracerProfile(
        "plummer",
        10 ** p["log_scale_radius"] * pc,
        cusp_gamma=p["gamma"],
        cusp_radius=10 ** p["log_cusp_radius"] * pc,
    )
    with pytest.raises(NoIsotropicDFError):
        eddington_df(build_mass_model(tracer, 10 ** p["log_mass"], p["bh_mass"]), beta=p["beta"])
    space, _ = h.sbc_space("imbh", gamma_range=(0.75, 2.0), beta_range=(-0.5, 0.25))
    redraws = [h.draw_truth(space, np.random.default_rng([s, 17]), "df")[2] for s in range(3)]
    assert sum(redraws) > 0
    space, _ = h.sbc_space("imbh", **h.SBC_DF_PRIORS)
    truth, df, n = h.draw_truth(space, np.random.default_rng([0, 17]), "df")
    assert df["min_g"] >= -h.DF_NEGATIVE_TOLERANCE
    with pytest.raises(ValueError, match="velocities"):
        h.draw_sample(truth, 10, np.random.default_rng(0), "dff")


def _df_sbc_fit(seed, law):
    return h.sbc_full_trial(seed, velocities="df", velocity_law=law, priors=h.SBC_DF_PRIORS)


@pytest.mark.slow
def test_df_sbc_gaussian_law_calibrated_line_of_sight_law_low():
    """SBC on DF velocities (``benchmarks/sbc_df.py``'s draws, seeds 3000-3029, 800 stars
    in 15", nested 100 / 0.5), both laws on the same data: the Gaussian law's M_bh pulls
    (median - truth) / half-width have mean within +-0.4 and its 95 % intervals hold the
    truth in >= 85 %; the line-of-sight law's pulls are lower by > 0.2 on average (its
    Gaussian 3-D velocities make the equilibrium's flatter motions near the IMBH too
    little mass). ``DYN_WORKERS`` processes (default 2); ~60 fits of ~5-10 CPU s."""
    from concurrent.futures import ProcessPoolExecutor

    seeds = list(range(3000, 3030))
    laws = ("gaussian", "line_of_sight")
    with ProcessPoolExecutor(max_workers=int(os.environ.get("DYN_WORKERS", "2"))) as ex:
        rows = list(ex.map(_df_sbc_fit, seeds * 2, [law for law in laws for _ in seeds]))
    pulls, cover = {}, {}
    for law in laws:
        rs = [r for r in rows if r["velocity_law"] == law]
        t = np.array([r["bh_true"] for r in rs])
        q = {k: np.array([r[k] for r in rs]) for k in ("q2.5", "q16", "q50", "q84", "q97.5")}
        pulls[law] = (q["q50"] - t) / (0.5 * (q["q84"] - q["q16"]))
        cover[law] = np.mean((q["q2.5"] <= t) & (t <= q["q97.5"]))
    assert abs(pulls["gaussian"].mean()) < 0.4
    assert cover["gaussian"] >= 0.85
    assert np.mean(pulls["line_of_sight"] - pulls["gaussian"]) < -0.2
