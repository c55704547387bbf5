"""The verdict when the best model puts the dark centre in the extended component.

On the ``ngc3201-nbody`` matrix at 5000 solMass (segregated, seed 206; docs/dynamics.md,
"The matrix at 500 and 5000 solMass") the ``dark`` model beats both IMBH models by
ln B 3.0 with its scale radius at the lower edge of its prior, while a dark centre is
favoured over ``none`` by ln B 230: the verdict word is ``no_imbh``, and its sentence must
not read as "nothing in the centre". Hand-made fits (posteriors placed against the prior's
edge) are the reference.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mavispm.dynamics.evidence import EvidenceResult
from mavispm.dynamics.fit import DARK_EDGE_DEX, Comparison, ModelFit, _verdict, compare
from mavispm.dynamics.parameters import Parameter, ParameterSpace


def _fit(name, log_z, extra):
    """A converged fit of ``name`` with evidence ``log_z``; ``extra``: {parameter: (lo, hi,
    posterior value)} besides the cluster mass."""
    params = [Parameter("log_mass", lo=4.0, hi=6.0)]
    params += [Parameter(k, lo=lo, hi=hi) for k, (lo, hi, _) in extra.items()]
    n = 500
    rng = np.random.default_rng(1)
    cols = [np.full(n, 5.0)] + [v + 0.01 * rng.standard_normal(n) for _, _, v in extra.values()]
    return ModelFit(
        name=name,
        space=ParameterSpace(params),
        likelihood=None,
        chain=SimpleNamespace(samples=np.column_stack(cols), converged=True),
        summary={},
        evidence=EvidenceResult(log_z=log_z, log_z_err=0.5, n_calls=10, max_log_like=log_z),
        criteria={"aic": -log_z, "bic": -log_z, "max_log_like": log_z},
    )


def _fits(log_b_dark):
    edge = (-0.5, 1.5)
    return [
        _fit("none", -20646.2, {}),
        _fit("imbh", -20418.9, {"bh_mass": (0.0, 1e4, 4900.0)}),
        _fit(
            "dark",
            -20415.9,
            {"dark_mass": (0.0, 2e4, 5500.0), "log_dark_radius": (*edge, log_b_dark)},
        ),
        _fit(
            "imbh_dark",
            -20419.3,
            {
                "bh_mass": (0.0, 1e4, 5000.0),
                "dark_mass": (0.0, 2e4, 9000.0),
                "log_dark_radius": (*edge, 1.3),
            },
        ),
    ]


def test_a_compact_dark_component_at_its_prior_edge_is_said_so():
    c = compare(_fits(-0.43), bh_mass_max=1e4)
    assert c.verdict == "no_imbh" and c.best_model == "dark"
    assert c.ln_b_dark_centre > 200 and c.dark_radius_at_prior_edge
    assert "dark central mass is favoured over none (ln B = 230.30)" in c.verdict_text
    assert "as compact as its prior allows" in c.verdict_text


def test_a_resolved_dark_component_is_not_called_compact():
    c = compare(_fits(-0.5 + DARK_EDGE_DEX + 0.3), bh_mass_max=1e4)
    assert c.verdict == "no_imbh" and not c.dark_radius_at_prior_edge
    assert "dark central mass is favoured over none" in c.verdict_text
    assert "as compact as its prior allows" not in c.verdict_text


def test_no_dark_sentence_when_none_is_best_or_an_imbh_is_favoured():
    word, text = _verdict(
        Comparison(ln_bayes_factor=-6.0, best_model="none", best_model_without_imbh="none"),
        [],
        1.0,
    )
    assert word == "no_imbh" and "dark central mass" not in text
    c = Comparison(
        ln_bayes_factor=4.0,
        best_model="imbh",
        best_model_without_imbh="dark",
        ln_b_dark_centre=50.0,
        dark_radius_at_prior_edge=True,
    )
    word, text = _verdict(c, [], 1.0)
    assert word == "imbh" and "dark central mass" not in text
