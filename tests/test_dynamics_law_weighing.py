"""Weighing the velocity laws by their evidences (``velocity_law = "weighed"``, the
default, over ``compare_velocity_laws``).

The combination is checked against its definition (equal prior odds per law: the mean of
the laws' evidences) on hand-made evidences; the settings refuse what cannot be weighed;
the slow test takes an equilibrium (DF) null cluster, written independently of the
package (``sbc_helpers``), on which the projected laws alone claim an IMBH.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.errors import ConfigError
from mavispm.dynamics.cli import validate_settings
from mavispm.dynamics.evidence import EvidenceResult
from mavispm.dynamics.fit import ModelFit, weigh_velocity_laws

sys.path.insert(0, str(Path(__file__).parent))


def _fit(name, log_z, err=0.2, kin=None, wall=1.0):
    ev = EvidenceResult(log_z=log_z, log_z_err=err, n_calls=10, max_log_like=log_z + 5)
    kev = None if kin is None else EvidenceResult(kin, err, 10, kin + 5)
    return ModelFit(
        name=name,
        space=None,
        likelihood=None,
        chain=None,
        summary={"log_z": log_z},
        evidence=ev,
        evidence_kinematic=kev,
        criteria={"aic": -log_z, "bic": -log_z, "max_log_like": log_z + 5},
        wall_s={"evidence": wall},
    )


def test_each_model_gets_the_laws_mean_evidence_and_its_best_laws_posterior():
    per_law = {
        "free_kurtosis": [_fit("none", -100.0, 0.3, kin=-50.0), _fit("imbh", -90.0, 0.4, -40.0)],
        "line_of_sight": [_fit("none", -95.0, 0.2, kin=-52.0), _fit("imbh", -91.0, 0.1, -45.0)],
    }
    none, imbh = weigh_velocity_laws(per_law)
    # equal prior odds per law: Z = (Z_1 + Z_2) / 2
    assert none.evidence.log_z == pytest.approx(np.log((np.exp(-100.0) + np.exp(-95.0)) / 2))
    assert imbh.evidence.log_z == pytest.approx(np.log((np.exp(-90.0) + np.exp(-91.0)) / 2))
    assert imbh.evidence_kinematic.log_z == pytest.approx(
        np.log((np.exp(-40.0) + np.exp(-45.0)) / 2)
    )
    # the posterior (here the summary) of the law with the higher evidence
    assert none.summary["log_z"] == -95.0 and none.criteria["velocity_law"] == "line_of_sight"
    assert imbh.summary["log_z"] == -90.0 and imbh.criteria["velocity_law"] == "free_kurtosis"
    assert none.criteria["log_z_free_kurtosis"] == -100.0
    assert none.criteria["log_z_line_of_sight"] == -95.0
    # error: the laws' errors by their shares (one law dominating: its own)
    w = 1.0 / (1.0 + np.exp(-5.0))
    assert none.evidence.log_z_err == pytest.approx(np.hypot(w * 0.2, (1 - w) * 0.3))
    assert none.wall_s["evidence"] == 2.0
    # one law: the mean is that law's evidence
    (only,) = weigh_velocity_laws({"gaussian": [_fit("none", -7.0)]})
    assert only.evidence.log_z == -7.0


def test_equal_evidences_cost_ln_2_and_cancel_in_the_bayes_factor():
    per_law = {law: [_fit("none", -10.0), _fit("imbh", -8.0)] for law in ("a", "b")}
    none, imbh = weigh_velocity_laws(per_law)
    assert none.evidence.log_z == pytest.approx(-10.0)
    assert imbh.evidence.log_z - none.evidence.log_z == pytest.approx(2.0)


def _bh_fit(name, log_z, bh_mass, n=4000):
    """A fitted IMBH model whose M_BH posterior is a point at ``bh_mass``."""
    from types import SimpleNamespace

    from mavispm.dynamics.parameters import Parameter, ParameterSpace

    fit = _fit(name, log_z)
    space = ParameterSpace(
        [Parameter("log_mass", lo=4.0, hi=6.0), Parameter("bh_mass", lo=0.0, hi=1e4)]
    )
    samples = np.column_stack([np.full(n, 5.0), np.full(n, float(bh_mass))])
    return ModelFit(**{**fit.__dict__, "space": space, "chain": SimpleNamespace(samples=samples)})


def test_the_bh_mass_marginal_is_the_mixture_over_models_and_laws():
    """With the laws weighed, M_BH is marginalised over every (model, law) pair with
    weights Z_m,L (equal prior odds): not only the kept law's posterior."""
    from mavispm.dynamics.fit import marginal_bh_samples

    ln3 = np.log(3.0)
    per_law = {
        "free_kurtosis": [_fit("none", -100.0), _bh_fit("imbh", -90.0, 1000.0)],
        "line_of_sight": [_fit("none", -95.0), _bh_fit("imbh", -90.0 + ln3, 2000.0)],
    }
    none, imbh = weigh_velocity_laws(per_law)
    assert imbh.criteria["velocity_law"] == "line_of_sight"
    assert np.all(imbh.chain.samples[:, 1] == 2000.0)  # the kept law's posterior
    bh = marginal_bh_samples([none, imbh], seed=1)
    assert bh.size == 4000
    assert np.mean(bh == 2000.0) == pytest.approx(0.75, abs=1e-3)
    assert np.mean(bh == 1000.0) == pytest.approx(0.25, abs=1e-3)
    # with a second IMBH model (one law, its evidence e^2 times the first's total)
    other = _bh_fit("imbh_dark", -90.0 + np.log(4.0) + 2.0, 3000.0)
    bh = marginal_bh_samples([none, imbh, other], seed=1)
    z = np.array([1.0, 3.0, 4.0 * np.exp(2.0)])  # in units of exp(-90)
    for mass, share in zip((1000.0, 2000.0, 3000.0), z / z.sum()):
        assert np.mean(bh == mass) == pytest.approx(share, abs=2e-3)


@settings(max_examples=60, deadline=None)
@given(
    base=st.floats(-1e6, 0.0),
    spread=st.lists(st.floats(-2e3, 2e3), min_size=4, max_size=4),
)
def test_weighed_evidence_and_mixture_stay_finite_and_bounded(base, spread):
    """Evidences far below exp's range (ln Z ~ -1e6) and laws thousands of units apart:
    each model's ln Z lies between its best law's minus ln 2 and its best law's, and the
    M_BH mixture is finite, drawn only from the components that carry weight."""
    from mavispm.dynamics.fit import marginal_bh_samples

    lz = base + np.array(spread)
    per_law = {
        "free_kurtosis": [_fit("none", lz[0]), _bh_fit("imbh", lz[1], 1000.0, n=200)],
        "line_of_sight": [_fit("none", lz[2]), _bh_fit("imbh", lz[3], 2000.0, n=200)],
    }
    fits = weigh_velocity_laws(per_law)
    for fit, pair in zip(fits, ((lz[0], lz[2]), (lz[1], lz[3]))):
        assert max(pair) - np.log(2) - 1e-9 <= fit.evidence.log_z <= max(pair) + 1e-9
        assert np.isfinite(fit.evidence.log_z_err)
    bh = marginal_bh_samples(fits, seed=0)
    assert bh.size > 0 and np.all(np.isfinite(bh))
    share_los = 1.0 / (1.0 + np.exp(np.clip(lz[1] - lz[3], -700, 700)))
    assert np.mean(bh == 2000.0) == pytest.approx(share_los, abs=0.01)


def test_weighing_refuses_fits_without_evidence():
    a = _fit("none", -1.0)
    b = ModelFit("none", None, None, None, {}, evidence=None)
    with pytest.raises(ValueError, match="evidence"):
        weigh_velocity_laws({"gaussian": [a], "free_kurtosis": [b]})


def test_fitting_one_model_refuses_weighed_laws():
    """fit_model fits one law: the default settings (laws weighed) are refused, not
    silently fitted with one of them; so is a parameter space for them."""
    from mavispm.dynamics.fit import fit_model, parameter_space

    for s in (validate_settings({}), validate_settings({"velocity_law": "weighed"})):
        with pytest.raises(ValueError, match="fit_models"):
            fit_model(None, s, 4.6, "none", 0)
        with pytest.raises(ValueError, match="one law"):
            parameter_space(s, 4.6, "imbh")


@pytest.mark.parametrize(
    "cfg, key, words",
    [
        ({"compare_velocity_laws": ["free_kurtosis", "lorentzian"]}, "compare", "lorentzian"),
        ({"compare_velocity_laws": ["gaussian", "gaussian"]}, "compare", "two different"),
        ({"compare_velocity_laws": []}, "compare", "set velocity_law to one law"),
        (
            {
                "compare_velocity_laws": ["gaussian", "line_of_sight"],
                "evidence": False,
                "posterior": "emcee",
            },
            "weighed",
            "evidence = true",
        ),
        # the default weighs too: without evidences the message says what to set
        ({"evidence": False, "posterior": "emcee"}, "weighed", "set velocity_law to one law"),
        # a list of laws with one law asked for: which one was meant is unknown
        (
            {"velocity_law": "gaussian", "compare_velocity_laws": ["gaussian", "line_of_sight"]},
            "compare",
            "drop one of the two",
        ),
        ({"velocity_law": "lorentzian"}, "velocity_law", "weighed"),
    ],
)
def test_settings_refuse_law_lists_that_cannot_be_weighed(cfg, key, words):
    with pytest.raises(ConfigError, match=key) as err:
        validate_settings(cfg)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_the_laws_are_weighed_by_default_and_one_law_is_fitted_alone():
    """Default: free_kurtosis and line_of_sight weighed; a law asked for is fitted alone
    (the quickstart's ``velocity_law = "gaussian"``), the default list then unused; an
    emcee fit without evidences names its one law."""
    default = validate_settings({})
    assert default.velocity_law == "weighed"
    assert default.laws == ("free_kurtosis", "line_of_sight")
    s = validate_settings({"compare_velocity_laws": ["gaussian", "line_of_sight"]})
    assert s.laws == ("gaussian", "line_of_sight")
    one = validate_settings({"velocity_law": "gaussian"})
    assert one.laws == ("gaussian",)
    no_ev = {"evidence": False, "posterior": "emcee", "velocity_law": "free_kurtosis"}
    assert validate_settings(no_ev).laws == ("free_kurtosis",)


@pytest.mark.slow
def test_weighed_laws_do_not_claim_an_imbh_in_a_df_null_that_fools_the_projected_laws():
    """DF null draw 4020 of ``benchmarks/sbc_df.py`` (4" field inside a shallow cusp,
    gamma 0.77, no IMBH; 800 stars, DF velocities): with ``free_kurtosis`` alone ln B =
    +5.1 (``imbh``: the depth mixture's heavy tails read as an IMBH, kappa +1.9); the
    line-of-sight law's evidence is higher by ~17-22 for both models, so weighing the two
    laws gives ``no_imbh`` (ln B ~ -10) and keeps the line-of-sight law."""
    import sbc_helpers as h

    from mavispm.dynamics.fit import compare, fit_models
    from mavispm.dynamics.settings import DynamicsSettings

    rng = np.random.default_rng([4020, 17])
    truth_space, _ = h.sbc_space("imbh", "line_of_sight", **h.SBC_DF_PRIORS)
    truth, df, _ = h.draw_truth(truth_space, rng, "df", bh_mass=0.0)
    stars = h.draw_sample(truth, 800, rng, "df", 4.0, df)
    kw = {**h.SBC_FULL_SETTINGS, **h.SBC_DF_PRIORS}
    common = dict(models=("none", "imbh"), evidence=True, kinematic_evidence=False)
    alone = DynamicsSettings(**kw, **common, velocity_law="free_kurtosis")
    c_alone = compare(fit_models(stars, alone, h.SBC_DISTANCE, 4020), alone.bh_mass_max)
    both = DynamicsSettings(**kw, **common)  # the default: the two laws weighed
    fits = fit_models(stars, both, h.SBC_DISTANCE, 4020)
    c_both = compare(fits, both.bh_mass_max)
    print(
        f"ln B free_kurtosis {c_alone.ln_bayes_factor:+.2f}, weighed {c_both.ln_bayes_factor:+.2f}"
    )
    assert c_alone.verdict == "imbh"
    assert c_both.verdict == "no_imbh" and c_both.ln_bayes_factor < -3
    assert all(f.criteria["velocity_law"] == "line_of_sight" for f in fits)
