"""The dynamics stage end to end, settings, bad input, evidence and sampler pieces."""

import astropy.units as u
import h5py
import numpy as np
import pytest
from astropy.table import QTable
from dynamics_helpers import write_mock_propermotions

from mavispm.core.errors import ConfigError, InputError
from mavispm.core.products import read_product, write_product
from mavispm.dynamics.cli import load_stars, run_stage, validate_settings
from mavispm.dynamics.evidence import run_dynesty, savage_dickey
from mavispm.dynamics.parameters import Parameter, ParameterSpace
from mavispm.dynamics.sampling import run_emcee
from mavispm.workflows.cli import main

TINY = {
    "walkers": 10,
    "max_steps": 60,
    "check_every": 30,
    "evidence": False,
    "posterior": "emcee",  # the emcee path (the default posterior is nested)
    "velocity_law": "free_kurtosis",  # one law: no evidences to weigh laws by
    "n_bootstrap": 5,
    "progress": False,
    "bin_size": 200,
    "field_radius": "17 arcsec",
    # fewer nuisances keep the four MAP searches of this plumbing test short
    "cusp": False,
    "anisotropy": "constant",  # one beta, not the default general profile's three
    "centre_error": 0.0,
    "systemic_error": 0.0,
    "distance_error": 0.0,
}


@pytest.fixture(scope="module")
def pm_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("dyn") / "pm.h5"
    return write_mock_propermotions(path, seed=7, n_field=800)


def test_run_stage_writes_product_and_plots(pm_file, tmp_path):
    out = run_stage(pm_file, TINY, tmp_path / "fit.h5", seed=1, plots_dir=tmp_path / "plots")
    prod = read_product(out, "dynamics")
    a = prod.attrs
    assert a["n_stars"] == 800 and a["distance"].to_value(u.kpc) == pytest.approx(4.6)
    assert np.isfinite(a["delta_ln_likelihood"])
    assert np.isfinite(a["delta_aic"]) and np.isnan(a["ln_bayes_factor"])
    assert a["bh_mass_upper95"].unit == u.Msun
    models = ("none", "imbh", "dark", "imbh_dark")
    assert set(prod.tables) >= {"profile", "summary"} | {f"posterior_{m}" for m in models}
    assert "bh_mass" in prod.tables["posterior_imbh"].colnames
    assert "bh_mass" not in prod.tables["posterior_none"].colnames
    assert "dark_mass" in prod.tables["posterior_imbh_dark"].colnames
    for m in models:  # every model's convergence and MAP are kept
        assert f"converged_{m}" in a and f"max_log_like_{m}" in a
    # 60 steps cannot converge: the headline numbers are withheld and the verdict says so
    assert a["verdict"] == "not_converged" and not a["converged"]
    assert np.isnan(a["bh_mass_median"].value)
    assert len(prod.tables["profile"]) == 4
    for name in ("dispersion_profile.png", "corner_imbh.png", "corner_none.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 10_000
    # resume: the emcee backend continues the stored chains
    more = {**TINY, "max_steps": 90}
    out2 = run_stage(pm_file, more, tmp_path / "fit.h5", seed=1)
    assert read_product(out2, "dynamics").attrs["steps_imbh"] == 90
    with h5py.File(tmp_path / "fit.h5.emcee-imbh.h5") as f:
        assert f["imbh"]["chain"].shape[0] == 90


def test_cli_command(pm_file, tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[dynamics]\nwalkers = 10\nmax_steps = 30\ncheck_every = 30\nn_bootstrap = 2\n"
        'cusp = false\ncentre_error = 0\nsystemic_error = 0\ndistance_error = 0\nmodels = ["none", "imbh"]\n'
    )
    rc = main(
        [
            "dynamics",
            str(pm_file),
            "-o",
            str(tmp_path / "f.h5"),
            "--config",
            str(cfg),
            "--no-evidence",
            "--fast",
        ]
    )
    captured = capsys.readouterr()
    assert rc == 0 and "bh_mass_upper95" in captured.out
    # progress bars only on a terminal (stderr is captured here, not a terminal)
    assert "it/s" not in captured.err and "%|" not in captured.err
    # --no-evidence leaves emcee as the posterior, and says so; 30 steps cannot converge,
    # and the user is told in one line what to do (the JSON line only said not_converged)
    assert '"verdict": "not_converged"' in captured.out
    told = [line for line in captured.err.splitlines() if "did not converge" in line]
    assert len(told) == 1 and 'set posterior = "nested"' in told[0], captured.err
    assert "--no-evidence: posterior from emcee" in captured.err
    # the nested posterior needs the nested sampling that --no-evidence skips
    bad = ["dynamics", str(pm_file), "-o", str(tmp_path / "h.h5"), "--no-evidence"]
    assert main([*bad, "--posterior", "nested"]) == 2
    assert not (tmp_path / "h.h5").exists()
    rc = main(["dynamics", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "g.h5")])
    assert rc == 2


def test_settings_validation():
    s = validate_settings({"bh_mass_max": "5000 solMass", "distance": "4.6 kpc"})
    assert s.bh_mass_max == 5000 and s.distance == 4.6
    with pytest.raises(ConfigError, match="walker"):
        validate_settings({"walker": 3})
    with pytest.raises(ConfigError, match="beta_range"):
        validate_settings({"beta_range": [0.5, 0.1]})
    with pytest.raises(ConfigError, match="tracer"):
        validate_settings({"tracer": "hernquist"})
    with pytest.raises(ConfigError):
        validate_settings({"fit_gamma": True})
    with pytest.raises(ConfigError, match="cusp_link"):  # removed: no cusp tied to M_bh
        validate_settings({"cusp_link": "influence"})
    with pytest.raises(ConfigError, match="king62"):
        validate_settings({"tracer": "king"})
    with pytest.raises(ConfigError, match="models"):
        validate_settings({"models": ["none", "bogus"]})
    with pytest.raises(ConfigError, match="anisotropy"):
        validate_settings({"anisotropy": "radial"})
    with pytest.raises(ConfigError, match="completeness"):
        validate_settings({"completeness_radius": [0, 10], "completeness": [0.5, 1.2]})


def _pm_table(n=20, drop=()):
    rng = np.random.default_rng(0)
    t = QTable()
    t["id"] = np.arange(n)
    x, y = rng.uniform(-10, 10, (2, n))
    t["x"], t["y"], t["R"] = x * u.arcsec, y * u.arcsec, np.hypot(x, y) * u.arcsec
    for c in ("pm_r", "pm_t"):
        t[c] = rng.normal(0, 0.3, n) * u.mas / u.yr
    for c in ("pm_r_err", "pm_t_err"):
        t[c] = np.full(n, 0.05) * u.mas / u.yr
    for c in drop:
        del t[c]
    return t


def test_bad_propermotions_inputs(tmp_path):
    no_err = write_product(
        tmp_path / "a.h5",
        "propermotions",
        tables={"stars": _pm_table(drop=("pm_r_err",))},
        attrs={"distance": 4.6 * u.kpc},
    )
    with pytest.raises(InputError, match="pm_r_err"):
        run_stage(no_err, TINY, tmp_path / "o.h5", seed=0)
    no_dist = write_product(tmp_path / "b.h5", "propermotions", tables={"stars": _pm_table()})
    with pytest.raises(InputError, match="distance"):
        run_stage(no_dist, TINY, tmp_path / "o.h5", seed=0)
    t = _pm_table()
    t["pm_t_err"][3] = -0.1 * u.mas / u.yr
    neg = write_product(
        tmp_path / "c.h5", "propermotions", tables={"stars": t}, attrs={"distance": 4.6 * u.kpc}
    )
    with pytest.raises(InputError, match="negative"):
        run_stage(neg, TINY, tmp_path / "o.h5", seed=0)
    assert not (tmp_path / "o.h5").exists()


def test_dynesty_evidence_of_gaussian_likelihood():
    """ln Z of a 2-D unit Gaussian in a [-5, 5]^2 uniform prior is -ln(100) (+ tiny)."""
    sp = ParameterSpace([Parameter("a", lo=-5, hi=5), Parameter("b", lo=-5, hi=5)])
    res = run_dynesty(lambda v: -0.5 * np.sum(v**2) - np.log(2 * np.pi), sp, seed=3, nlive=150)
    assert res.log_z == pytest.approx(-np.log(100.0), abs=4 * res.log_z_err + 0.05)
    assert res.samples.shape[1] == 2 and abs(np.std(res.samples[:, 0]) - 1) < 0.2


# calls with 12 steps over calls with dynesty's ndim + 20: 12 / 32 with 12 parameters; with
# 3 the first iterations draw from the prior (no walk): 0.79 measured, not 12 / 23
@pytest.mark.parametrize("ndim, nlive, ratio_range", [(12, 100, (0.25, 0.55)), (3, 50, (0, 0.9))])
def test_dynesty_walks_sets_the_random_walk_and_keeps_the_evidence(ndim, nlive, ratio_range):
    """``walks`` (DynamicsKnobs): with 12 parameters and with 3 (the random walk below 10
    parameters too, where dynesty's own choice would be uniform draws in ellipsoids) the
    calls scale with it, and ln Z of a unit Gaussian in a [-5, 5]^ndim prior stays its
    analytic ``-ndim ln 10`` with 12 steps or dynesty's own ndim + 20."""
    sp = ParameterSpace([Parameter(f"p{i}", lo=-5, hi=5) for i in range(ndim)])

    def like(v):
        return -0.5 * np.sum(v**2) - 0.5 * ndim * np.log(2 * np.pi)

    runs = {w: run_dynesty(like, sp, seed=5, nlive=nlive, dlogz=0.5, walks=w) for w in (0, 12)}
    for res in runs.values():
        assert res.log_z == pytest.approx(-ndim * np.log(10.0), abs=4 * res.log_z_err + 0.1)
    assert ratio_range[0] < runs[12].n_calls / runs[0].n_calls < ratio_range[1]


def test_emcee_recovers_gaussian_and_reports_tau():
    sp = ParameterSpace([Parameter("a", lo=-10, hi=10), Parameter("b", lo=-10, hi=10)])
    res = run_emcee(
        lambda v: -0.5 * ((v[0] - 1) ** 2 + (v[1] / 2) ** 2),
        sp,
        seed=1,
        walkers=16,
        max_steps=3000,
        tau_factor=50,
        check_every=500,
        progress=False,
    )
    assert res.converged and res.steps >= 50 * np.max(res.tau)
    assert np.mean(res.samples[:, 0]) == pytest.approx(1.0, abs=0.15)
    assert np.std(res.samples[:, 1]) == pytest.approx(2.0, rel=0.15)


def test_savage_dickey_valid_only_with_support_at_zero():
    rng = np.random.default_rng(0)
    # posterior = prior (uninformative data): ln B = 0
    lnb, note = savage_dickey(rng.uniform(0, 1e4, 20000), 1e4)
    assert lnb == pytest.approx(0.0, abs=0.15) and note.startswith("valid")
    lnb, note = savage_dickey(rng.normal(3000, 300, 20000), 1e4)
    assert np.isnan(lnb) and "not valid" in note


def test_pm_error_scale_and_floor(pm_file):
    """Errors become sqrt((scale e)^2 + floor^2); the same stars are kept."""
    base, _ = load_stars(pm_file, validate_settings({}))
    s = validate_settings({"pm_error_scale": 2.0, "pm_error_floor": "0.05 mas/yr"})
    stars, _ = load_stars(pm_file, s)
    np.testing.assert_allclose(stars.e_r, np.sqrt((2 * base.e_r) ** 2 + 0.05**2))
    np.testing.assert_allclose(stars.e_t, np.sqrt((2 * base.e_t) ** 2 + 0.05**2))
    np.testing.assert_array_equal(stars.v_r, base.v_r)
    with pytest.raises(ConfigError, match="pm_error"):
        validate_settings({"pm_error_scale": 0.0})


def test_from_catalogue_fits_true_motions_of_luminous_stars(tmp_path, capsys):
    """--from-catalogue: luminous stars inside the field, true motions, the given error."""
    from dynamics_helpers import write_mock_catalogue

    from mavispm.dynamics.cli import load_catalogue_stars
    from mavispm.dynamics.settings import DynamicsSettings

    cat = write_mock_catalogue(tmp_path / "cat.h5", seed=3, n_field=300)
    stars, dist = load_catalogue_stars(cat, DynamicsSettings(field_radius=15.0), pm_error=0.002)
    assert dist == pytest.approx(4.6) and np.all(stars.R <= 15.0)
    assert np.all(stars.e_r == 0.002) and np.all(np.abs(stars.v_r) < 50)  # dark stars dropped
    d = __import__("dynamics_helpers").mock_pm_stars(3, n_field=300, distance=4.6)
    assert stars.R.size == int(np.sum(d["R"] <= 15.0))
    with pytest.raises(InputError, match="epoch"):
        load_catalogue_stars(cat, DynamicsSettings(), epoch="e7")
    with pytest.raises(InputError, match="pm-error"):
        load_catalogue_stars(cat, DynamicsSettings(), pm_error=0.0)
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[dynamics]\nwalkers = 10\nmax_steps = 30\ncheck_every = 30\nn_bootstrap = 2\n"
        'cusp = false\ncentre_error = 0\nsystemic_error = 0\ndistance_error = 0\nmodels = ["none", "imbh"]\n'
    )
    out = tmp_path / "f.h5"
    args = ["dynamics", "--from-catalogue", str(cat), "--pm-error", "0.002", "-o", str(out)]
    assert main([*args, "--config", str(cfg), "--no-evidence"]) == 0
    a = read_product(out, "dynamics", load_arrays=False).attrs
    assert a["catalogue"] == str(cat) and a["pm_error"].to_value(u.mas / u.yr) == 0.002
    assert main(["dynamics", "-o", str(tmp_path / "x.h5")]) == 2  # neither input
    assert main(["dynamics", str(cat), "--epoch", "e0", "-o", str(tmp_path / "y.h5")]) == 2


def test_nested_posterior_reports_results_with_kinematic_evidence(pm_file, tmp_path):
    """posterior = "nested" (no emcee): converged by construction, so the headline numbers,
    the kinematics-only ln B and a verdict are reported; the 1500 Msun IMBH of the mock is
    found (independent Plummer mock, 800 stars)."""
    cfg = {
        **TINY,
        "posterior": "nested",
        "evidence": True,
        "nlive": 30,
        "dlogz": 1.0,
        "models": ["none", "imbh"],
    }
    out = run_stage(pm_file, cfg, tmp_path / "n.h5", seed=2)
    prod = read_product(out, "dynamics")
    a = prod.attrs
    assert a["converged"] and a["verdict"] in ("imbh", "undecided", "no_imbh")
    for key in ("ln_bayes_factor", "ln_bayes_factor_kinematic"):
        assert np.isfinite(a[key]), key
    assert a["best_model_without_imbh"] == "none" and a["best_model_with_imbh"] == "imbh"
    assert 0 < a["bh_mass_lo68"].value < a["bh_mass_median"].value < a["bh_mass_hi68"].value
    assert len(prod.tables["bh_mass_marginal"]) > 50
    # no emcee chain: no steps, tau or acceptance to report (they read 0 / NaN before)
    assert not any(k.startswith(("steps_", "tau_max_", "acceptance_")) for k in a)
    assert a["posterior_samples_imbh"] == len(prod.tables["posterior_imbh"]) > 50
    with pytest.raises(ConfigError, match="nested"):
        validate_settings({"posterior": "nested", "evidence": False})
    # the default posterior is the nested one: evidence = false alone says what to set
    with pytest.raises(ConfigError, match="posterior = 'emcee'"):
        validate_settings({"evidence": False})
    one = {"evidence": False, "posterior": "emcee", "velocity_law": "free_kurtosis"}
    assert validate_settings(one).evidence is False


def test_fit_models_in_worker_processes_equals_serial():
    """Two worker processes (each law's fit of each model and its kinematics-only evidence
    as separate jobs of one pool) give the same evidences, posterior samples and
    kinematics-only evidences, law by law, as one process: the split of the work changes
    nothing but its schedule."""
    from dynamics_helpers import mock_pm_stars

    from mavispm.dynamics.fit import fit_models
    from mavispm.dynamics.likelihood import StarSample
    from mavispm.dynamics.settings import DynamicsSettings

    d = mock_pm_stars(5, n_field=300)
    stars = StarSample(d["R"], d["pm_r"], d["pm_t"], d["pm_r_err"], d["pm_t_err"], 17.0)
    s = DynamicsSettings(
        cusp=False,
        distance_error=0.0,
        posterior="nested",
        nlive=25,
        dlogz=2.0,
        models=("none", "imbh"),
        anisotropy="constant",  # a schedule test: the fewest parameters
        progress=False,
    )
    serial = fit_models(stars, s, 4.6, 3)
    import dataclasses

    parallel = fit_models(stars, dataclasses.replace(s, workers=2), 4.6, 3)
    for a, b in zip(serial, parallel):
        assert a.name == b.name
        assert a.evidence.log_z == b.evidence.log_z
        assert a.evidence_kinematic.log_z == b.evidence_kinematic.log_z
        assert a.evidence_kinematic is not a.evidence
        np.testing.assert_array_equal(a.chain.samples, b.chain.samples)
        assert set(b.wall_s) == {"evidence", "evidence_kinematic"}
        # the default weighs two laws: every (law, model, part) a job of the one pool
        assert [f.likelihood.velocity_law for f in b.law_fits] == list(s.laws)
        assert len(s.laws) == 2
        for la, lb in zip(a.law_fits, b.law_fits, strict=True):
            assert la.evidence.log_z == lb.evidence.log_z
            assert la.evidence_kinematic.log_z == lb.evidence_kinematic.log_z
            np.testing.assert_array_equal(la.chain.samples, lb.chain.samples)


def test_verdict_words_follow_kass_raftery_and_quote_the_error():
    """The verdict sentence grades ln B on the Kass & Raftery (1995) scale (2 ln B of 2, 6
    and 10 bound positive, strong and very strong) and quotes its error."""
    from mavispm.dynamics.fit import Comparison, _verdict, evidence_strength

    assert evidence_strength(0.5) == "not worth more than a bare mention"
    assert [evidence_strength(x) for x in (1.1, -2.9, 3.0, 4.99, -5.0, 40.0)] == [
        "positive",
        "positive",
        "strong",
        "strong",
        "very strong",
        "very strong",
    ]
    c = Comparison(ln_bayes_factor=1.10, ln_bayes_factor_err=0.96, best_model="imbh")
    word, text = _verdict(c, [], 1.0)
    assert word == "imbh" and "positive evidence" in text and "1.10 +- 0.96" in text
    word, text = _verdict(Comparison(ln_bayes_factor=-6.0, best_model="none"), [], 1.0)
    assert word == "no_imbh" and "very strong" in text and "+-" not in text
    word, _ = _verdict(Comparison(ln_bayes_factor=0.4, ln_bayes_factor_err=0.2), [], 1.0)
    assert word == "undecided"


def test_only_the_products_reject_bits_drop_stars(tmp_path):
    """A star clipped from the alignment's reference set (flag 1) is kept, one flagged by
    the measure stage (8) is dropped, as the product's ``flag_reject_mask`` says; a product
    without the attribute drops every flagged star; the propermotions stage writes it."""
    from mavispm.measure.propermotions.pipeline import PMFlag

    path = write_mock_propermotions(tmp_path / "pm.h5", seed=3, n_field=200)
    prod = read_product(path, "propermotions")
    t = prod.tables["stars"]
    t["flag"][:10] = PMFlag.CLIPPED
    t["flag"][10:15] = PMFlag.INPUT_FLAGGED | PMFlag.CLIPPED
    attrs = {k: v for k, v in prod.attrs.items() if k in ("distance", "epochs")}
    s = validate_settings({"field_radius": "17 arcsec"})
    with_mask = write_product(
        tmp_path / "a.h5",
        "propermotions",
        tables={"stars": t},
        attrs={**attrs, "flag_reject_mask": int(PMFlag.REJECT)},
    )
    assert load_stars(with_mask, s)[0].R.size == 195
    without = write_product(tmp_path / "b.h5", "propermotions", tables={"stars": t}, attrs=attrs)
    assert load_stars(without, s)[0].R.size == 185
    everything = validate_settings({"field_radius": "17 arcsec", "use_flagged": True})
    assert load_stars(with_mask, everything)[0].R.size == 200
    assert PMFlag.REJECT & PMFlag.CLIPPED == 0 and PMFlag.REJECT & PMFlag.POOR_FIT


def test_free_kurtosis_law_puts_kappa_in_the_products(pm_file, tmp_path):
    """velocity_law = "free_kurtosis", kappa_profile = "radial": the summary and posterior
    tables carry kappa_inner / kappa_outer of every model, and the attrs the law and the
    anchor radii (the 10th / 90th percentiles of the fitted stars' radii)."""
    cfg = {**TINY, "models": ["none", "imbh"], "max_steps": 30}
    cfg.update(velocity_law="free_kurtosis", kappa_profile="radial", kappa_range=[-1.0, 2.0])
    out = run_stage(pm_file, cfg, tmp_path / "k.h5", seed=3)
    prod = read_product(out, "dynamics")
    a, summ = prod.attrs, prod.tables["summary"]
    assert a["velocity_law"] == "free_kurtosis"
    for model in ("none", "imbh"):
        rows = summ[summ["model"] == model]
        names = list(rows["parameter"])
        assert "kappa_inner" in names and "kappa_outer" in names
        k = rows[names.index("kappa_outer")]
        assert -1.0 <= k["lo68"] <= k["median"] <= k["hi68"] <= 2.0
        assert "kappa_inner" in prod.tables[f"posterior_{model}"].colnames
    stars, _ = load_stars(pm_file, validate_settings({"field_radius": "17 arcsec"}))
    np.testing.assert_allclose(
        a["kappa_anchor_radii"].to_value(u.arcsec),
        np.percentile(np.maximum(stars.R, 0.01), [10, 90]),
        rtol=1e-12,
    )


def test_line_of_sight_kurtosis_law_puts_kappa_in_the_products(pm_file, tmp_path):
    """velocity_law = "line_of_sight_kurtosis": one kappa in the summary and posterior
    tables of every model, inside kappa_range; the attrs name the law."""
    cfg = {**TINY, "models": ["none", "imbh"], "max_steps": 30}
    cfg.update(velocity_law="line_of_sight_kurtosis", kappa_range=[-1.0, 2.0])
    out = run_stage(pm_file, cfg, tmp_path / "k.h5", seed=3)
    prod = read_product(out, "dynamics")
    a, summ = prod.attrs, prod.tables["summary"]
    assert a["velocity_law"] == "line_of_sight_kurtosis"
    for model in ("none", "imbh"):
        rows = summ[summ["model"] == model]
        names = list(rows["parameter"])
        assert "kappa" in names and "kappa_inner" not in names
        k = rows[names.index("kappa")]
        assert -1.0 <= k["lo68"] <= k["median"] <= k["hi68"] <= 2.0
        assert "kappa" in prod.tables[f"posterior_{model}"].colnames


def test_weighed_velocity_laws_name_each_models_law_in_the_products(pm_file, tmp_path):
    """velocity_law = "weighed": the attrs name the weighed laws, the law kept per model (the
    one with the higher ln Z) and each law's ln Z; the model's ln Z is the laws' mean."""
    cfg = {**TINY, "models": ["none", "imbh"], "max_steps": 30}
    cfg.update(evidence=True, nlive=30, dlogz=5.0, kinematic_evidence=False)
    cfg.update(velocity_law="weighed", compare_velocity_laws=["gaussian", "free_kurtosis"])
    out = run_stage(pm_file, cfg, tmp_path / "w.h5", seed=3)
    a = read_product(out, "dynamics").attrs
    assert a["velocity_law"] == "weighed"
    assert a["compare_velocity_laws"] == "gaussian,free_kurtosis"
    for model in ("none", "imbh"):
        lz = [a[f"log_z_{law}_{model}"] for law in ("gaussian", "free_kurtosis")]
        assert a[f"velocity_law_{model}"] == ("gaussian", "free_kurtosis")[int(np.argmax(lz))]
        assert a[f"log_z_{model}"] == pytest.approx(np.logaddexp(*lz) - np.log(2))
    # the fast-star test's stored fits rebuild each model with the law its posterior was
    # drawn with (the product's settings say only "weighed")
    from mavispm.dynamics.fast_stars_cli import stored_fits

    prod = read_product(out, "dynamics")
    settings = validate_settings(prod.attrs["config"])
    stars, distance = load_stars(pm_file, settings)
    for fit in stored_fits(prod, settings, stars, distance):
        assert fit.likelihood.velocity_law == a[f"velocity_law_{fit.name}"]
