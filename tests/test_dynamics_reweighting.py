"""Importance reweighting of nested samples: analytic cases, the Pareto diagnostic, a fit."""

import dataclasses

import numpy as np
import pytest

from mavispm.dynamics.reweighting import K_MAX, pareto_k, reweight_samples


def test_pareto_shape_of_known_tails():
    """Ratios with a generalised-Pareto tail of shape 0.9 give k near 0.9 (> 0.7, unusable);
    log-normal ratios of width 0.3 give k < 0.5."""
    rng = np.random.default_rng(0)
    heavy = rng.pareto(1.0 / 0.9, 4000)  # Lomax: GPD tail of shape 0.9
    assert 0.7 < pareto_k(np.log(heavy)) < 1.1
    light = rng.normal(0.0, 0.3, 4000)
    assert pareto_k(light) < 0.5
    assert pareto_k(np.full(10, -np.inf)) == np.inf


def test_reweighting_gaussians_matches_the_analytic_ratio():
    """Proposal posterior N(0, 1) (L_q = exp(-x^2 / 2)), target L = exp(-(x - mu)^2 / (2 s^2)):
    E_q[L / L_q] = s and the target posterior is N(mu, s^2). mu = 0.3, s = 0.8: within
    3 errors and 0.05; mu = 4, s = 0.3 (no overlap): k > 0.7."""
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 1.0, (4000, 1))
    ll_q = -0.5 * x[:, 0] ** 2
    good = reweight_samples(x, ll_q, lambda v: -0.5 * ((v[0] - 0.3) / 0.8) ** 2, rng)
    assert good["pareto_k"] < K_MAX
    assert good["log_mean_ratio"] == pytest.approx(np.log(0.8), abs=3 * good["log_mean_ratio_err"])
    assert good["log_mean_ratio"] == pytest.approx(np.log(0.8), abs=0.05)
    assert np.mean(good["samples"]) == pytest.approx(0.3, abs=0.05)
    assert np.std(good["samples"]) == pytest.approx(0.8, abs=0.05)
    assert good["n_calls"] == 4000  # every distinct draw evaluated once
    bad = reweight_samples(x, ll_q, lambda v: -0.5 * ((v[0] - 4.0) / 0.3) ** 2, rng)
    assert bad["pareto_k"] > K_MAX


def test_reweighted_fit_agrees_with_the_direct_line_of_sight_fit():
    """300 stars with 3-D velocities (SBC forward model, 1500 solMass IMBH), model ``imbh``
    with 4 parameters: the Gaussian-law run reweighted to the line-of-sight law gives the
    direct line-of-sight run's ln Z within 3 errors and its M_bh median within 0.35 of
    the posterior's standard deviation; the Gaussian-law run alone differs more in ln Z."""
    from sbc_helpers import SBC_DISTANCE, draw_sample

    from mavispm.dynamics.fit import fit_model
    from mavispm.dynamics.settings import DynamicsSettings

    p = dict(
        log_mass=5.2, log_scale_radius=2.08, gamma=0.0, log_cusp_radius=0.0, bh_mass=1500.0,
        beta=0.1, distance=SBC_DISTANCE, x0=0.0, y0=0.0, pm_x0=0.0, pm_y0=0.0,
    )  # fmt: skip
    stars = draw_sample(p, 300, np.random.default_rng(4), "3d")
    s = DynamicsSettings(
        cusp=False, centre_error=0.0, systemic_error=0.0, distance_error=0.0,
        posterior="nested", nlive=60, dlogz=0.5, models=("imbh",), progress=False,
        log_scale_radius_prior=(2.08, 0.05), kinematic_evidence=False,
        velocity_law="line_of_sight",
    )  # fmt: skip
    direct = fit_model(stars, s, SBC_DISTANCE, "imbh", 5)
    rew = fit_model(stars, dataclasses.replace(s, reweight=True), SBC_DISTANCE, "imbh", 5)
    gauss = fit_model(
        stars, dataclasses.replace(s, velocity_law="gaussian"), SBC_DISTANCE, "imbh", 5
    )
    assert rew.evidence.method == "reweighted" and rew.evidence.pareto_k < K_MAX
    err = np.hypot(direct.evidence.log_z_err, rew.evidence.log_z_err)
    assert rew.evidence.log_z == pytest.approx(direct.evidence.log_z, abs=3 * err)
    i = direct.space.index("bh_mass")
    bh_d, bh_r = direct.chain.samples[:, i], rew.chain.samples[:, i]
    assert abs(np.median(bh_r) - np.median(bh_d)) < 0.35 * np.std(bh_d)
    assert abs(gauss.evidence.log_z - direct.evidence.log_z) > abs(
        rew.evidence.log_z - direct.evidence.log_z
    )
