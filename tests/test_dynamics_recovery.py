"""Parameter recovery on independent mock catalogues (see dynamics_helpers)."""

import json
import os
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from dynamics_helpers import mock_likelihoods, recovery_trial

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


@pytest.mark.slow
def test_recovery_coverage_and_bayes_factor():
    """>= 10 seeds each: 68% coverage >= 60% and ln B > 3 with IMBH; limit < 1500, ln B < 1 without."""
    seeds = list(range(100, 110))
    jobs = [(s, 1500.0) for s in seeds] + [(s, 0.0) for s in seeds]
    with ProcessPoolExecutor(max_workers=int(os.environ.get("DYN_WORKERS", "2"))) as ex:
        results = list(ex.map(recovery_trial, *zip(*jobs)))
    out = os.environ.get("DYN_RECOVERY_JSON")
    if out:
        with open(out, "w") as fh:
            json.dump(results, fh, indent=1, default=float)
    imbh = [r for r in results if r["bh_true"] > 0]
    none = [r for r in results if r["bh_true"] == 0]
    coverage = np.mean([r["q16"] <= 1500.0 <= r["q84"] for r in imbh])
    assert coverage >= 0.6
    assert np.median([r["ln_b"] for r in imbh]) > 3.0
    assert np.median([r["q95"] for r in none]) < 1500.0
    assert np.median([r["ln_b"] for r in none]) < 1.0
