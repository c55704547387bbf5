"""Parameter recovery: independent Plummer mocks and the cluster generator's catalogues."""

import functools
import json
import os
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from dynamics_helpers import (
    generator_fit_settings,
    generator_recovery_trial,
    generator_stars,
    mock_likelihoods,
)

from mavispm.dynamics.fit import make_likelihood, parameter_space
from mavispm.dynamics.sampling import find_map


def _map_fit(seed, bh_mass):
    _, (sp1, l1), (sp0, l0) = mock_likelihoods(seed, bh_mass)
    v1 = sp1.from_scaled(find_map(l1, sp1))
    v0 = sp0.from_scaled(find_map(l0, sp0))
    return v1[sp1.index("bh_mass")], l1(v1) - l0(v0)


def test_map_recovers_injected_imbh():
    """Optimiser check (fast): the IMBH is found near 1500 Msun and improves ln L."""
    bh, dlnl = _map_fit(seed=2, bh_mass=1500.0)
    assert 500.0 < bh < 4500.0
    assert dlnl > 3.0


def test_map_without_imbh_finds_little_mass():
    """Optimiser check (fast): no IMBH injected -> small best-fit M_bh and ln L gain."""
    bh, dlnl = _map_fit(seed=3, bh_mass=0.0)
    assert bh < 1500.0
    assert -1e-6 <= dlnl < 3.0


def test_map_on_generator_catalogue_finds_imbh():
    """Quick recovery check on a cluster-generator catalogue (King62 + cusp, 1500 Msun IMBH).

    ~2,000 stars inside 17", PM errors 20-100 microarcsec/yr, Dehnen tracer with
    free gamma: the best-fit M_bh is within 30% of the truth, the inner slope
    near the generator's 1.55 cusp, and the IMBH improves ln L by far more than 3.
    """
    stars, truth = generator_stars(seed=2, bh_mass=1500.0)
    assert 1800 < stars.R.size < 2200
    s = generator_fit_settings()
    dist = truth["distance"]
    sp1 = parameter_space(s, dist, "imbh", positions=False)
    sp0 = parameter_space(s, dist, "none", positions=False)
    l1, l0 = make_likelihood(stars, sp1, s, dist), make_likelihood(stars, sp0, s, dist)
    v1 = sp1.from_scaled(find_map(l1, sp1))
    v0 = sp0.from_scaled(find_map(l0, sp0))
    assert abs(v1[sp1.index("bh_mass")] / truth["bh_mass"] - 1.0) < 0.3
    assert abs(v1[sp1.index("gamma")] - truth["cusp_gamma"]) < 0.3
    assert l1(v1) - l0(v0) > 10.0


@pytest.mark.slow
def test_generator_recovery_coverage_and_bayes_factor():
    """10 generator seeds each (nested posterior and ln B, nlive 100): with a 1500 Msun
    IMBH the 68% interval holds the truth in >= 60% and ln B > 3 in every catalogue;
    without one the median 95% upper limit is below 1500 Msun and ln B < 1 in >= 9 of 10
    (issue 13's criterion for nulls). Seed 109's null carries an IMBH-like central
    excess: M_BH 1100-1700 (68%) with either anisotropy model and either velocity law,
    ln B 0.7-2.0 between sampler seeds (docs/dynamics.md, "Recovery on the cluster
    generator's catalogues, current models")."""
    seeds = list(range(100, 110))
    # "dehnen", "cusped_king", "cusped_king_rc"
    model = os.environ.get("DYN_GENERATOR_MODEL", "cusped_king_rc")
    jobs = [(s, bh) for s in seeds for bh in (1500.0, 0.0)]
    out = os.environ.get("DYN_RECOVERY_JSON")
    results = []
    with ProcessPoolExecutor(max_workers=int(os.environ.get("DYN_WORKERS", "2"))) as ex:
        trial = functools.partial(generator_recovery_trial, model=model)
        for res in ex.map(trial, *zip(*jobs)):
            results.append(res)
            if out:  # one JSON line per finished trial
                with open(out, "a") as fh:
                    fh.write(json.dumps(res, default=float) + "\n")
    imbh = [r for r in results if r["bh_true"] > 0]
    none = [r for r in results if r["bh_true"] == 0]
    for r in results:
        print(
            f"{r['seed']} {r['bh_true']:6.0f}: ln B {r['ln_b']:7.2f} +- {r['ln_b_err']:.2f}, "
            f"M_BH {r['q50']:5.0f} ({r['q16']:.0f}-{r['q84']:.0f}), 95% upper {r['q95']:.0f}, "
            f"{r['cpu_s']:.0f} CPU s"
        )
    coverage = np.mean([r["q16"] <= 1500.0 <= r["q84"] for r in imbh])
    assert coverage >= 0.6
    assert all(r["ln_b"] > 3.0 for r in imbh)
    assert np.median([r["q95"] for r in none]) < 1500.0
    assert sum(r["ln_b"] < 1.0 for r in none) >= 9
