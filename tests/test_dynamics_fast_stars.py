"""The fast-star test: escape velocities, selection, false-star budget, lower mass limit."""

import math

import astropy.units as u
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from mavispm.core.errors import InputError
from mavispm.dynamics.escape_velocity import (
    PointMass,
    ProfileComponent,
    SphericalMassModel,
    dimensionless_potential,
    escape_velocity,
    escape_velocity_quantile,
)
from mavispm.dynamics.fast_stars import (
    FastStarSettings,
    PMStars,
    binary_kicks,
    fast_star_test,
    lower_mass_limit,
    measure_tails,
    p_value,
    rice_sf,
    threshold,
    velocity_2d,
)
from mavispm.dynamics.tracers import Cusped, Dehnen, King62, Plummer

G = 4.300917270e-3  # pc (km/s)^2 / Msun, CODATA-derived (independent of the code's constant)
KMS = 4.740470463533348


# ----------------------------------------------------------------- escape velocity


@settings(max_examples=40, deadline=None)
@given(st.floats(-6, 5), st.floats(1e3, 1e7), st.floats(0.05, 20), st.floats(0, 1e4))
def test_plummer_plus_point_mass_escape_velocity_is_analytic(log_x, mass, a_pc, bh):
    r = a_pc * 10.0**log_x
    model = SphericalMassModel((ProfileComponent(Plummer(), mass, a_pc), PointMass(bh)))
    expected = np.sqrt(2 * G * (mass / np.sqrt(r * r + a_pc * a_pc) + bh / r))
    got = escape_velocity(model, r * u.pc)
    assert got.unit == u.km / u.s
    assert got.value == pytest.approx(expected, rel=1e-7)


@pytest.mark.parametrize("gamma", [0.0, 0.5, 1.0, 1.5, 1.9])
def test_dehnen_potential_is_analytic(gamma):
    x = np.geomspace(1e-8, 1e5, 200)
    exact = -(1.0 - (x / (1.0 + x)) ** (2.0 - gamma)) / (2.0 - gamma)
    got = dimensionless_potential(Dehnen(gamma), x)
    assert np.max(np.abs(got / exact - 1.0)) < 1e-6


def _king_density_independent(x, xt):
    """King (1962) density (unnormalised), written out again for the test."""
    z2 = (1.0 + x * x) / (1.0 + xt * xt)
    if z2 >= 1.0:
        return 0.0
    z = math.sqrt(z2)
    return (math.acos(z) / z - math.sqrt(1.0 - z2)) / z2


@pytest.mark.parametrize("c", [0.8, 1.33, 2.0])
def test_king_potential_against_independent_quadrature(c):
    xt = 10.0**c

    def mass(r):
        return integrate.quad(
            lambda s: 4 * np.pi * s * s * _king_density_independent(s, xt), 0, r, limit=200
        )[0]

    total = mass(xt)
    for x in (1e-3, 0.1, 0.7, 3.0, 0.5 * xt, 0.99 * xt, 2 * xt):
        inner = mass(min(x, xt)) / x
        outer = integrate.quad(
            lambda s: 4 * np.pi * s * _king_density_independent(s, xt), min(x, xt), xt, limit=200
        )[0]
        phi = -(inner + outer) / total
        assert dimensionless_potential(King62(c), np.array([x]))[0] == pytest.approx(phi, rel=5e-6)


def test_cusped_king_potential_against_quadrature():
    prof = Cusped(King62(1.33), 1.55, 0.2)
    xt = 10.0**1.33

    def rho(s):
        return _king_density_independent(s, xt) * (1 + (0.2 / s) ** 2) ** (1.55 / 2)

    total = integrate.quad(lambda s: 4 * np.pi * s * s * rho(s), 0, xt, limit=400, points=[0.2])[0]
    for x in (1e-3, 0.05, 0.5, 5.0):
        inner = integrate.quad(lambda s: 4 * np.pi * s * s * rho(s), 0, x, limit=400)[0] / x
        outer = integrate.quad(lambda s: 4 * np.pi * s * rho(s), x, xt, limit=400)[0]
        exact = -(inner + outer) / total
        assert dimensionless_potential(prof, np.array([x]))[0] == pytest.approx(exact, rel=2e-4)


def test_escape_velocity_quantile_takes_r_equal_R_and_the_high_quantile():
    models = [SphericalMassModel((ProfileComponent(Plummer(), m, 1.0),)) for m in (1e4, 2e4, 4e4)]
    R = np.array([0.0, 0.5, 2.0]) * u.pc
    q = escape_velocity_quantile(models, R, 1.0)
    expected = np.sqrt(2 * G * 4e4 / np.sqrt(R.value**2 + 1.0))
    assert q.to_value(u.km / u.s) == pytest.approx(expected, rel=1e-7)
    with pytest.raises(ValueError):
        escape_velocity_quantile(models, R, 0.0)


# ----------------------------------------------------------------- statistics


def test_rice_sf_against_monte_carlo_and_far_tail():
    rng = np.random.default_rng(1)
    nu, sig, t = 5.0, 1.0, 7.0
    draws = np.hypot(nu + sig * rng.standard_normal(400_000), sig * rng.standard_normal(400_000))
    assert rice_sf(t, nu, sig) == pytest.approx(np.mean(draws > t), rel=0.03)
    # far tail: ~ Gaussian one-sided tail of the excess (no underflow to 0)
    assert 1e-17 < rice_sf(38.0, 30.0, 1.0) < 1e-14


def test_threshold_inverts_the_p_value():
    sigma = np.array([0.01, 0.05, 0.2])
    v_esc = np.array([20.0, 20.0, 35.0])
    d, w = np.array([4.4, 4.6, 4.8]), np.array([0.25, 0.5, 0.25])
    t = threshold(sigma, v_esc, d, w, 1e-3)
    assert p_value(t, sigma, v_esc, d, w) == pytest.approx(1e-3, rel=1e-4)


def test_velocity_error_with_covariance_against_monte_carlo():
    rng = np.random.default_rng(2)
    ex, ey, rho = 0.05, 0.02, 0.6
    s = PMStars(
        np.array([1]), np.array([1.0]), np.array([0.6]), np.array([0.8]),
        np.array([ex]), np.array([ey]), np.array([rho]),
    )  # fmt: skip
    v, v_err = velocity_2d(s, 5.0, 0.2)
    cov = [[ex * ex, rho * ex * ey], [rho * ex * ey, ey * ey]]
    pm = rng.multivariate_normal([0.6, 0.8], cov, 200_000)
    d = 5.0 + 0.2 * rng.standard_normal(200_000)
    vv = KMS * d * np.hypot(pm[:, 0], pm[:, 1])
    assert v[0] == pytest.approx(KMS * 5.0, rel=1e-12)
    assert v_err[0] == pytest.approx(np.std(vv), rel=0.02)


def test_measured_tails_gaussian_and_student():
    rng = np.random.default_rng(3)
    g = measure_tails(rng.standard_normal(200_000) * 2.0, "truth")
    assert g.robust_sigma == pytest.approx(2.0, rel=0.01) and math.isinf(g.dof)
    t = measure_tails(rng.standard_t(3, 200_000), "truth")
    assert 2.0 < t.dof < 4.5
    assert measure_tails([1.0, 2.0], "truth").source == "none"


def test_binary_kicks_period_limits():
    """After a full period the photocentre is back (no kick); after half a period it is
    at the opposite side: kick = 4.74 x 2 alpha / T at most (face-on)."""
    rng = np.random.default_rng(4)
    T = 10.0
    full = FastStarSettings(binary_log_period=(np.log10(T * 365.25), 1e-9))
    assert np.max(binary_kicks(10_000, rng, T, full)) < 1e-6
    half = FastStarSettings(binary_log_period=(np.log10(2 * T * 365.25), 1e-9))
    kicks = binary_kicks(200_000, rng, T, half)
    q = np.linspace(0.1, 1.0, 10_001)
    a_au = (0.8 * (1 + q) * (2 * T) ** 2) ** (1 / 3)  # Kepler, AU / yr / Msun
    alpha = a_au * np.abs(q / (1 + q) - q**3.5 / (1 + q**3.5))
    bound = KMS * 2 * alpha.max() / T
    assert kicks.max() <= bound * (1 + 1e-6) and kicks.max() > 0.95 * bound
    # only binaries closer than the separation limit remain: chord <= 2 a
    narrow = FastStarSettings(binary_max_separation=0.01)
    assert np.max(binary_kicks(10_000, rng, T, narrow)) <= KMS * 2 * 0.01 / T


# ----------------------------------------------------------------- lower mass limit


def test_lower_limit_single_star_keplerian():
    """No stellar potential, tiny errors: M = R v^2 / (2 G) for r = R, v_3D = v_2D."""
    R_arcsec, d = 0.5, 4.6
    pm = np.array([[1.2, 0.5]])
    cov = np.array([np.eye(2) * 1e-12])
    lim, per = lower_mass_limit(np.array([R_arcsec]), pm, cov, np.zeros(1), d, 0.0, 0.95, 500)
    r_pc = R_arcsec * d * 1e3 * np.pi / 648000
    v = KMS * d * np.hypot(1.2, 0.5)
    assert lim == pytest.approx(r_pc * v * v / (2 * G), rel=1e-5)
    assert per[0] == pytest.approx(lim, rel=1e-9)
    # the stellar escape velocity lowers it; a star below v_esc gives no limit
    lim2, _ = lower_mass_limit(np.array([R_arcsec]), pm, cov, np.array([0.5 * v]), d, 0, 0.95, 500)
    assert lim2 == pytest.approx(0.75 * lim, rel=1e-5)
    lim3, _ = lower_mass_limit(np.array([R_arcsec]), pm, cov, np.array([2 * v]), d, 0, 0.95, 500)
    assert lim3 == 0.0


def test_lower_limit_combines_by_the_maximum():
    R = np.array([0.3, 0.3])
    pm = np.array([[1.0, 0.0], [2.0, 0.0]])
    cov = np.array([np.eye(2) * 1e-12] * 2)
    lim, per = lower_mass_limit(R, pm, cov, np.zeros(2), 4.6, 0.0, 0.95, 300)
    assert lim == pytest.approx(per.max(), rel=1e-5) and per[1] == pytest.approx(
        4 * per[0], rel=1e-5
    )


# ----------------------------------------------------------------- the test on toy data


class _Flat:
    """A mass model with a constant escape speed (for bad-input tests)."""

    def __init__(self, v):
        self.v = v

    def escape_speed_at(self, R):
        return np.full(np.shape(R), self.v)


def _toy_stars(n, seed=0, sigma_kms=5.0, err=0.02, d=4.6):
    rng = np.random.default_rng(seed)
    pm = rng.standard_normal((2, n)) * sigma_kms / (KMS * d) + err * rng.standard_normal((2, n))
    return PMStars(
        np.arange(n), rng.uniform(0, 10, n), pm[0], pm[1],
        np.full(n, err), np.full(n, err), np.zeros(n),
    )  # fmt: skip


def test_toy_cluster_without_and_with_a_fast_star():
    stars = _toy_stars(500)
    res = fast_star_test(stars, 4.6, [_Flat(25.0)], dispersion=lambda R: np.full(len(R), 0.23))
    assert res.possible and res.attrs["fast_n_significant"] == 0
    assert res.attrs["bh_mass_lower_limit"].to_value(u.Msun) == 0.0
    assert 0 <= res.attrs["fast_expected_false_errors"] < 1e-3
    # one star at 40 km/s, 0.5" from the centre
    pm_x = stars.pm_x.copy()
    pm_x[0], pm_y = 40.0 / (KMS * 4.6), stars.pm_y.copy()
    pm_y[0] = 0.0
    R = stars.R.copy()
    R[0] = 0.5
    fast = PMStars(stars.id, R, pm_x, pm_y, stars.pm_x_err, stars.pm_y_err, stars.pm_xy_corr)
    res = fast_star_test(fast, 4.6, [_Flat(25.0)], dispersion=lambda R: np.full(len(R), 0.23))
    assert res.attrs["fast_n_significant"] == 1 and res.table["id"][0] == 0
    assert res.table["significance"][0] > 10
    r_pc = 0.5 * 4.6 * 1e3 * np.pi / 648000
    kepler = r_pc * (40.0**2 - 25.0**2) / (2 * G)
    lim = res.attrs["bh_mass_lower_limit"].to_value(u.Msun)
    assert 0.9 * kepler < lim < kepler * 1.01
    assert res.attrs["fast_p_count_ge_no_imbh"] < 1e-3


def test_fast_star_plot(tmp_path):
    from mavispm.dynamics.plots import fast_star_plot

    stars = _toy_stars(200)
    res = fast_star_test(stars, 4.6, [_Flat(25.0)], imbh_models=[_Flat(30.0)])
    path = fast_star_plot(res, tmp_path / "fs.png")
    assert path.stat().st_size > 10_000


def test_field_stars_add_expected_false_fast_stars():
    stars = _toy_stars(300)
    s = FastStarSettings(field_density=0.1, field_pm_mean=(3.0, 0.0), field_pm_sigma=1.0)
    res = fast_star_test(stars, 4.6, [_Flat(25.0)], s, field_radius=10.0)
    # field stars at 3 mas/yr = 65 km/s relative: nearly all of the 31 in the area are "fast"
    assert res.attrs["fast_expected_false_field"] == pytest.approx(0.1 * np.pi * 100, rel=0.05)


def test_bad_input_no_errors_nan_single_star_no_distance():
    stars = _toy_stars(50)
    zero_err = PMStars(
        stars.id, stars.R, stars.pm_x, stars.pm_y,
        np.zeros(50), np.zeros(50), np.zeros(50),
    )  # fmt: skip
    res = fast_star_test(zero_err, 4.6, [_Flat(25.0)])
    assert not res.possible and "no test possible" in res.note
    assert res.attrs["fast_n_significant"] == 0 and len(res.table) == 0
    nan = PMStars(
        stars.id, stars.R, np.full(50, np.nan), stars.pm_y,
        stars.pm_x_err, stars.pm_y_err, stars.pm_xy_corr,
    )  # fmt: skip
    res = fast_star_test(nan, 4.6, [_Flat(25.0)])
    assert not res.possible and res.attrs["fast_n_dropped"] == 50
    single = stars.select(np.arange(50) == 0)
    assert not fast_star_test(single, 4.6, [_Flat(25.0)]).possible
    with pytest.raises(InputError, match="distance"):
        fast_star_test(stars, float("nan"), [_Flat(25.0)])
    with pytest.raises(InputError, match="no-IMBH"):
        fast_star_test(stars, 4.6, [])
    with pytest.raises(ValueError, match="alpha"):
        FastStarSettings(alpha=0.7)


# ----------------------------------------------------------------- in the dynamics stage


@pytest.fixture(scope="module")
def pm_file(tmp_path_factory):
    from dynamics_helpers import write_mock_propermotions

    path = tmp_path_factory.mktemp("fast") / "pm.h5"
    # compact Plummer cluster with a 20,000 Msun IMBH. The mock's velocities are
    # Gaussian (not a bound DF), so only the product's structure is checked here;
    # the physics is tested on the cluster generator's catalogues.
    return write_mock_propermotions(path, seed=3, n_field=500, mass=5e4, a_arcsec=25.0, bh_mass=2e4)


def test_cli_fast_stars_flag_writes_table_and_plot(pm_file, tmp_path, capsys):
    from mavispm.core.products import read_product
    from mavispm.workflows.cli import main

    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[dynamics]\nwalkers = 10\nmax_steps = 30\ncheck_every = 30\nn_bootstrap = 2\n"
        'progress = false\nfield_radius = "17 arcsec"\nmodels = ["none", "imbh"]\n'
        "cusp = false\ncentre_error = 0\nsystemic_error = 0\ndistance_error = 0\n"
        "kinematic_evidence = false\n"
        "[dynamics.fast_stars]\nn_models = 10\nn_monte_carlo = 500\n"
    )
    out = tmp_path / "f.h5"
    args = ["dynamics", str(pm_file), "-o", str(out), "--config", str(cfg), "--no-evidence"]
    assert main([*args, "--fast-stars"]) == 0
    prod = read_product(out, "dynamics")
    a, t = prod.attrs, prod.tables["fast_stars"]
    assert a["fast_test_possible"] and a["fast_n_stars"] == 500 and a["fast_n_models"] == 10
    assert set(t.colnames) >= {"id", "R", "v_2d", "v_2d_err", "v_esc", "significance", "fast"}
    assert t["v_2d"].unit == u.km / u.s and t["R"].unit == u.arcsec
    assert a["fast_n_significant"] == int(np.sum(t["fast"])) >= 1
    assert np.all(t["v_2d"][t["fast"]] > t["v_esc"][t["fast"]])
    assert a["bh_mass_lower_limit"].to_value(u.Msun) > 0
    # rerun on the product without refitting, stricter significance, with the plot
    fs = tmp_path / "fs.toml"
    fs.write_text("[dynamics.fast_stars]\nalpha = 1e-12\nn_models = 10\n")
    out2 = tmp_path / "g.h5"
    rerun = ["fast-stars", str(out), "-o", str(out2), "--config", str(fs), "--plots", str(tmp_path)]
    assert main(rerun) == 0
    b = read_product(out2, "dynamics")
    assert b.attrs["fast_alpha"] == 1e-12 and b.attrs["config"]["fast_stars"]["alpha"] == 1e-12
    assert b.attrs["fast_n_significant"] <= a["fast_n_significant"]
    assert set(b.tables) == set(prod.tables)
    assert (tmp_path / "fast_stars.png").stat().st_size > 10_000
    capsys.readouterr()
    assert main(["fast-stars", str(tmp_path / "none.h5"), "-o", str(out2)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_bad_fast_star_settings_are_one_line_errors(tmp_path, capsys):
    from mavispm.core.errors import ConfigError
    from mavispm.dynamics.cli import validate_settings

    with pytest.raises(ConfigError, match="dynamics.fast_stars.alpah"):
        validate_settings({"fast_stars": {"alpah": 0.01}})
    with pytest.raises(ConfigError, match="alpha out of range"):
        validate_settings({"fast_stars": {"alpha": 2.0}})
    s = validate_settings({"fast_stars": {"baseline": "5 yr", "field_density": "0.01 arcsec-2"}})
    assert s.fast_stars.baseline == 5.0 and s.fast_stars.field_density == 0.01


def test_propermotions_without_errors_is_one_line_error(tmp_path):
    from astropy.table import QTable

    from mavispm.core.products import write_product
    from mavispm.dynamics.fast_stars import read_pm_stars

    t = QTable()
    t["id"] = np.arange(3)
    t["x"] = t["y"] = t["R"] = np.ones(3) * u.arcsec
    t["pm_x"] = t["pm_y"] = np.zeros(3) * u.mas / u.yr
    path = write_product(tmp_path / "pm.h5", "propermotions", tables={"stars": t})
    with pytest.raises(InputError, match="pm_x_err"):
        read_pm_stars(path)


def test_escape_speed_agrees_with_the_dynamics_mass_models():
    """The fast-star path and dynamics.mass_models (separate quadratures) agree."""
    from mavispm.dynamics.escape_velocity import escape_speed_at_projected
    from mavispm.dynamics.mass_models import mass_model

    params = {"log_mass": 5.2, "log_scale_radius": 1.9, "dark_mass": 3000.0}
    params["log_dark_radius"] = 0.5
    theirs = mass_model(params, tracer="king62", concentration=1.33, distance=4.6)
    mine = SphericalMassModel(
        (
            ProfileComponent(King62(1.33), 10**5.2, 10**1.9 * 4.6 * 1e3 * np.pi / 648000),
            ProfileComponent(Plummer(), 3000.0, 10**0.5 * 4.6 * 1e3 * np.pi / 648000),
        )
    )
    R = np.array([0.01, 0.3, 3.0, 30.0])
    a = escape_speed_at_projected(theirs, R, 4.6)
    b = escape_speed_at_projected(
        type(
            "M",
            (),
            {"escape_speed_at": lambda self, R: mine.escape_speed(R * 4.6 * 1e3 * np.pi / 648000)},
        )(),
        R,
        4.6,
    )
    assert a == pytest.approx(b, rel=1e-5)
    # a test run accepts those models directly
    res = fast_star_test(_toy_stars(100), 4.6, [theirs])
    assert res.possible and res.attrs["v_esc_center_no_imbh"].to_value(u.km / u.s) > 0


def test_fast_stars_report_recipe(tmp_path):
    from mavispm.core.products import write_product
    from mavispm.workflows.report import RECIPES

    stars = _toy_stars(200)
    pm_x = stars.pm_x.copy()
    pm_x[0] = 40.0 / (KMS * 4.6)
    fast = PMStars(stars.id, stars.R, pm_x, stars.pm_y, stars.pm_x_err, stars.pm_y_err,
                   stars.pm_xy_corr)  # fmt: skip
    nodes = []
    for i, (data, mass) in enumerate(((stars, 0), (fast, 1500))):
        res = fast_star_test(data, 4.6, [_Flat(25.0)])
        write_product(
            tmp_path / f"d{i}.h5",
            "dynamics",
            tables={"fast_stars": res.table},
            attrs={**res.attrs, "ln_bayes_factor": 3.0 * i},
        )
        nodes.append(
            {
                "id": f"dynamics/{i}",
                "stage": "dynamics",
                "products": {"main": f"d{i}.h5"},
                "labels": {"study": "s", "point": f"mass={mass}"},
                "sweep": {"mass": mass, "baseline": [0, 10]},
            }
        )
    out = tmp_path / "report"
    out.mkdir()
    text = RECIPES["fast_stars"]({"nodes": nodes}, tmp_path, out)
    assert "Significant fast stars" in text and "| s mass=1500 | 200 | 1 |" in text
    assert (out / "fast_stars_sweep.png").stat().st_size > 10_000
    assert (out / "fast_stars.csv").read_text().count("\n") == 3
    assert RECIPES["fast_stars"]({"nodes": []}, tmp_path, out).startswith("No dynamics")


def test_stars_about_the_fitted_centre_and_systemic_motion():
    from mavispm.dynamics.fast_stars import about_fitted_centre, stars_from_sample
    from mavispm.dynamics.likelihood import StarSample

    x, y = np.array([1.0, 3.0, 0.0]), np.array([0.0, 0.0, 2.0])
    sample = StarSample(np.hypot(x, y), np.array([0.1, 0.2, 0.3]), np.zeros(3),
                        np.full(3, 0.01), np.full(3, 0.02), 5.0, x=x, y=y)  # fmt: skip
    stars = stars_from_sample(sample)
    assert stars.pm_x_err[0] == 0.01 and stars.pm_y_err[0] == 0.02
    rng = np.random.default_rng(5)
    names = ["log_mass", "x0", "y0", "pm_x0", "pm_y0"]
    samples = np.column_stack(
        [np.full(4000, 5.0), 1.0 + 0.1 * rng.standard_normal(4000), np.zeros(4000),
         0.05 + 0.01 * rng.standard_normal(4000), np.zeros(4000)]
    )  # fmt: skip
    moved = about_fitted_centre(stars, samples, names)
    sd = np.std(samples[:, 1])
    x0 = np.median(samples[:, 1])
    expected_R = np.maximum(np.hypot(x - x0, y) - 2 * sd, 0)
    assert moved.R == pytest.approx(expected_R, abs=1e-12)
    assert moved.pm_x == pytest.approx(stars.pm_x - np.median(samples[:, 3]))
    assert moved.pm_x_err == pytest.approx(np.hypot(0.01, np.std(samples[:, 3])))
    # nothing fitted: unchanged
    same = about_fitted_centre(stars, samples[:, :1], names[:1])
    assert np.array_equal(same.R, stars.R) and np.array_equal(same.pm_x, stars.pm_x)
