"""Benchmark of the dynamics stage: likelihood cost and accuracy, sampler cost.

Run ``python benchmarks/bench_dynamics.py [--quick]`` from the repository root
(with ``PYTHONPATH=.dev``). Prints

1. Jeans projection accuracy and time against the radial grid / quadrature knobs
   (error: max relative error of the projected dispersion against the analytic
   Plummer result and against a very fine reference for the point-mass term);
2. one likelihood evaluation against the number of stars; the line-of-sight mixture's
   cost and error against its nodes (and the Gaussian law's cost);
3. emcee to convergence (walkers, steps, tau, wall time) and posterior width;
4. dynesty evidence per model (calls, wall time, ln Z error);
5. with ``--node-evidence``: each model's ln Z with 16 against 64 line-of-sight nodes on
   two radially anisotropic validation-matrix clusters;
6. with ``--comparison``: one model's evidence with each velocity law (Gaussian,
   line-of-sight direct, reweighted) and the full four-model comparison against the number of
   stars and with the cheap knobs (no cusp, centre/systemic fixed, no kinematic
   evidence).

Times are CPU (process) seconds, robust against other jobs on a shared
machine; wall times are printed alongside. Compare ratios measured in one run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from dynamics_helpers import RECOVERY_MOCK, mock_likelihoods  # noqa: E402

from mavispm.dynamics.evidence import run_dynesty  # noqa: E402
from mavispm.dynamics.jeans import JeansProjector  # noqa: E402
from mavispm.dynamics.likelihood import DiscreteLikelihood, StarSample  # noqa: E402
from mavispm.dynamics.sampling import run_emcee  # noqa: E402
from mavispm.dynamics.tracers import Plummer  # noqa: E402


def _time(fn, repeat):
    """CPU seconds per call (process time: robust on a shared machine)."""
    fn()
    t0 = time.process_time()
    for _ in range(repeat):
        fn()
    return (time.process_time() - t0) / repeat


def bench_projection(quick):
    print("\n# Jeans projection: quadrature knobs vs accuracy (Plummer, R = 1e-4..1e3 a)")
    X = np.logspace(-4, 3, 40)
    ref = JeansProjector(X, n_panels=64, n_gl=8).moments(Plummer(), 0.3)
    analytic = 3 * np.pi / (64 * np.sqrt(1 + X**2))
    print(f"{'panels':>6} {'nodes':>5} {'time/ms':>8} {'err_cl(b=0)':>12} {'err_bh(b=.3)':>12}")
    for n_panels, n_gl in [(8, 4), (12, 6), (16, 6), (24, 6), (32, 8)]:
        proj = JeansProjector(X, n_panels=n_panels, n_gl=n_gl)
        t = _time(lambda p=proj: p.moments(Plummer(), 0.3), 5 if quick else 30)
        e0 = np.max(np.abs(proj.moments(Plummer(), 0.0).radial_cluster / analytic - 1))
        e1 = np.max(np.abs(proj.moments(Plummer(), 0.3).radial_bh / ref.radial_bh - 1))
        print(f"{n_panels:6d} {n_gl:5d} {1e3 * t:8.3f} {e0:12.2e} {e1:12.2e}")


def bench_likelihood(quick):
    print("\n# likelihood: cost vs stars and radial grid size (Plummer, no cusp, IMBH model)")
    stars, (sp1, _), _ = mock_likelihoods(1, 1500.0)
    truth = {"log_mass": 4.7, "log_scale_radius": np.log10(25.0), "bh_mass": 1500.0}
    # isotropic in whichever anisotropy model the settings take (constant or general),
    # Gaussian in shape (kappa 0) with the free-kurtosis law
    truth.update(beta=0.0, beta_0=0.0, beta_inf=0.0, log_anisotropy_radius=1.0, kappa=0.0)
    truth.update(distance=4.6)
    theta = np.array([truth[n] for n in sp1.names])
    rng = np.random.default_rng(0)
    ref_like = None
    print(f"{'stars':>6} {'grid':>5} {'time/ms':>8} {'dlnL vs grid 256':>17}")
    for n in [500, 2000, 3500] + ([] if quick else [7000]):
        pick = rng.integers(0, stars.R.size, n)
        s = StarSample(
            stars.R[pick], stars.v_r[pick], stars.v_t[pick], stars.e_r[pick], stars.e_t[pick], 17.0
        )
        ref_like = DiscreteLikelihood(s, sp1.names, distance=4.6, grid_size=256)(theta)
        for grid in (32, 64, 128):
            like = DiscreteLikelihood(s, sp1.names, distance=4.6, grid_size=grid)
            t = _time(lambda lk=like: lk(theta), 20 if quick else 200)
            print(f"{n:6d} {grid:5d} {1e3 * t:8.3f} {like(theta) - ref_like:17.2e}")


def bench_line_of_sight(quick):
    """Line-of-sight mixture: cost and error against its nodes, and the Gaussian law's cost.

    Stars with 3-D Gaussian velocities from the SBC forward model (full model with an
    IMBH and a dark component); error: the kinematic ln L minus the independent dense sum
    over 4000 depths per star (``tests/sbc_helpers.py``)."""
    import dataclasses

    from sbc_helpers import (
        SBC_DISTANCE,
        draw_prior,
        draw_sample,
        independent_line_of_sight_ln_likelihood,
        sbc_space,
    )

    from mavispm.dynamics.fit import make_likelihood

    print("\n# line-of-sight mixture: nodes vs cost and |dlnL| (full model, 3-D velocities)")
    space, s = sbc_space("imbh_dark")
    rng = np.random.default_rng([1, 7])
    p = draw_prior(space, rng)
    theta = np.array([p[n] for n in space.names])
    print(f"{'stars':>6} {'law':>14} {'nodes':>5} {'time/ms':>8} {'|dlnL| vs dense':>16}")
    for n in [300, 3500]:
        stars = draw_sample(p, n, rng, "3d")
        ref = independent_line_of_sight_ln_likelihood(p, stars)
        for law, nodes in [("gaussian", 0), *[("line_of_sight", k) for k in (8, 12, 16, 24)]]:
            knobs = dict(velocity_law=law, line_of_sight_nodes=max(nodes, 2))
            like = make_likelihood(
                stars, space, dataclasses.replace(s, **knobs), SBC_DISTANCE, star_counts=False
            )
            t = _time(lambda lk=like: lk(theta), 20 if quick else 100)
            err = abs(like(theta) - ref)
            print(f"{n:6d} {law:>14} {nodes or '-':>5} {1e3 * t:8.3f} {err:16.2e}")


def bench_tracers(quick):
    print("\n# likelihood per tracer family, 3,500 stars, grid 64 (new parameters every call)")
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.settings import DynamicsSettings
    from mavispm.dynamics.star_sums import star_sums, star_sums_numpy

    s = _stars(3500)
    rng = np.random.default_rng(0)
    king = {"tracer": "king62", "king_concentration": 1.33, "log_scale_radius_range": (1.0, 3.0)}
    fixed = {"centre_error": 0.0, "systemic_error": 0.0, "distance_error": 0.0}
    cases = {
        "plummer, no cusp, nuisances fixed": ({"cusp": False, **fixed}, "imbh"),
        "plummer + cusp, nuisances fixed": (fixed, "imbh"),
        "dehnen, free gamma": ({"tracer": "dehnen", **fixed}, "imbh"),
        "cusped King62": ({**king, **fixed}, "imbh"),
        "plummer + cusp + nuisances": ({}, "imbh"),
        "... + dark component (imbh_dark)": ({}, "imbh_dark"),
        "... + Osipkov-Merritt (imbh_dark)": ({"anisotropy": "osipkov-merritt"}, "imbh_dark"),
        "... star counts off": ({"star_counts": False}, "imbh_dark"),
    }
    n_calls = 50 if quick else 300
    print(f"{'model':>36} {'npar':>4} {'ms/call':>8}")
    for name, (kw, model) in cases.items():
        settings = DynamicsSettings(**{"velocity_law": "free_kurtosis", **kw})
        space = parameter_space(settings, 4.6, model)
        like = make_likelihood(s, space, settings, 4.6)
        thetas = space.from_scaled(rng.uniform(-0.5, 0.5, (n_calls, len(space))))
        thetas[:, space.index("log_mass")] = 5.0
        like(thetas[0])  # build the cached tables
        t = _time(lambda lk=like, th=thetas: [lk(v) for v in th], 1) / n_calls
        print(f"{name:>36} {len(space):4d} {1e3 * t:8.3f}")
    # the star loop alone: fused numba kernel vs the numpy reference
    grid = np.linspace(-6, 2, 64)
    ln_s2 = np.stack([-grid, -grid - 0.1])
    args = (np.log(s.R) - 3.0, grid[0], grid[1] - grid[0], ln_s2, -grid)
    args += (np.stack([s.v_r, s.v_t]) ** 2, np.stack([s.e_r, s.e_t]) ** 2)
    star_sums(*args)
    t_nb = _time(lambda: star_sums(*args), 200)
    t_np = _time(lambda: star_sums_numpy(*args), 200)
    print(f"star sums (3,500 stars): numba {1e3 * t_nb:.3f} ms, numpy {1e3 * t_np:.3f} ms")
    # the model on its grid: compiled (the likelihood's path) vs the numpy reference
    settings = DynamicsSettings(velocity_law="free_kurtosis")
    space = parameter_space(settings, 4.6, "imbh_dark")
    like = make_likelihood(s, space, settings, 4.6)
    thetas = space.from_scaled(rng.uniform(-0.5, 0.5, (n_calls, len(space))))
    t_c = _time(lambda: [like.log_model_on_grid(v) for v in thetas], 1) / n_calls
    t_n = _time(lambda: [like.model_on_grid(v) for v in thetas], 1) / n_calls
    print(
        f"grid model (imbh_dark, cusp): compiled {1e3 * t_c:.3f} ms, numpy moments {1e3 * t_n:.3f} ms"
    )


def bench_line_of_sight_evidence(seed=206, case="radial_anisotropy", imbh_mass=500.0,
                                 models=("none", "imbh", "dark"), n_draws=600):  # fmt: skip
    """Do the line-of-sight nodes move the evidences? Nested runs with the default 16 nodes
    (line-of-sight law, the default general anisotropy, ``validation_settings`` and the
    matrix's observer priors) on one validation-matrix cluster, then each model's ln Z
    corrected to 64 nodes by importance weights over ``n_draws`` posterior draws,
    ``ln E_post[L_64 / L_16]`` (docs/dynamics.md, "Nor the evidences on realistic radially
    anisotropic clusters")."""
    import dataclasses

    from dynamics_helpers import observer_trial_inputs, validation_settings
    from scipy.special import logsumexp

    from mavispm.dynamics.fit import fit_model, make_likelihood

    base = validation_settings(workers=1, velocity_law="line_of_sight", kinematic_evidence=False)
    stars, dist, s, _ = observer_trial_inputs(seed, case, imbh_mass, base)
    print(
        f"\n# line-of-sight nodes and the evidences: {case}, seed {seed}, {imbh_mass:g} solMass, "
        f"{stars.R.size} stars, anisotropy {s.anisotropy}"
    )
    print(f"{'model':>10} {'ln Z (16)':>12} {'err':>5} {'dlnL 64-16: median (range)':>30} "
          f"{'dlnZ':>7} {'beta_inf':>8} {'CPU s':>6}")  # fmt: skip
    for model in models:
        c0 = time.process_time()
        fit = fit_model(stars, s, dist, model, seed)
        rng = np.random.default_rng(0)
        samples = fit.chain.samples
        draws = samples[rng.choice(len(samples), min(n_draws, len(samples)), replace=False)]
        ln_l = {}
        for nodes in (16, 64):
            knobs = dataclasses.replace(s, line_of_sight_nodes=nodes)
            like = make_likelihood(stars, fit.space, knobs, dist)
            ln_l[nodes] = np.array([like(theta) for theta in draws])
        d = ln_l[64] - ln_l[16]
        shift = logsumexp(d) - np.log(d.size)
        beta_inf = np.median(samples[:, fit.space.index("beta_inf")])
        print(
            f"{model:>10} {fit.evidence.log_z:12.2f} {fit.evidence.log_z_err:5.2f} "
            f"{np.median(d):+10.3f} ({d.min():+.3f} to {d.max():+.3f}) {shift:+7.3f} "
            f"{beta_inf:8.2f} {time.process_time() - c0:6.0f}"
        )


def _stars(n, seed=1):
    """``n`` mock stars (Plummer + 1500 Msun IMBH) with positions, inside 17"."""
    from dynamics_helpers import mock_pm_stars

    d = mock_pm_stars(seed, **{**RECOVERY_MOCK, "n_field": n})
    return StarSample(
        d["R"], d["pm_r"], d["pm_t"], d["pm_r_err"], d["pm_t_err"], 17.0, x=d["x"], y=d["y"]
    )


def bench_comparison(quick, n_stars=(1000, 3500), **knobs):
    """The four-model comparison (emcee + full and kinematics-only dynesty) per star number."""
    from mavispm.dynamics.fit import compare, fit_model
    from mavispm.dynamics.settings import DynamicsSettings

    base = {
        "progress": False,
        "posterior": "emcee",  # this benchmark times emcee + dynesty (the default is nested)
        "velocity_law": "free_kurtosis",  # one law (the default weighs two: twice the cost)
        "walkers": 32,
        "max_steps": 3000,
        "tau_factor": 20.0,
        "check_every": 250,
        "nlive": 100,
        "dlogz": 0.5,
    }
    settings = DynamicsSettings(**{**base, **knobs})
    print(f"\n# four-model comparison, knobs {knobs or 'default'} (wall and CPU seconds)")
    for n in n_stars:
        stars = _stars(n)
        t0, c0 = time.perf_counter(), time.process_time()
        fits = [fit_model(stars, settings, 4.6, m, seed=1) for m in settings.models]
        comp = compare(fits, settings.bh_mass_max)
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        parts = ", ".join(
            f"{f.name}: " + "/".join(f"{v:.0f}" for v in f.wall_s.values()) for f in fits
        )
        print(
            f"N={n}: {dt:.0f} s wall, {cpu:.0f} s CPU; ln B = {comp.ln_bayes_factor:.2f}, "
            f"kinematic {comp.ln_bayes_factor_kinematic:.2f}, verdict {comp.verdict}; "
            f"per model emcee/evidence/kinematic s: {parts}"
        )


def bench_reweighting_overlap(n_seeds=12):
    """Does the Gaussian law's nested posterior cover the line-of-sight law's? For SBC draws
    of ``imbh`` (800 stars, 3-D Gaussian velocities, ``tests/sbc_helpers.py``, seeds
    3000...): the Pareto shape of the importance ratios (reliable below 0.7), their
    effective sample size over 4,000 draws and ln E[L_los / L_gauss]."""
    import dataclasses

    from sbc_helpers import SBC_DISTANCE, draw_prior, draw_sample, sbc_space

    from mavispm.dynamics.fit import make_likelihood
    from mavispm.dynamics.reweighting import reweight_samples

    print("\n# reweighting the Gaussian law's nested run to the line-of-sight law (SBC draws)")
    print(f"{'seed':>5} {'M_bh':>7} {'pareto_k':>8} {'ESS':>7} {'ln E[ratio]':>11}")
    for seed in range(3000, 3000 + n_seeds):
        rng = np.random.default_rng([seed, 17])
        space, s = sbc_space("imbh", "line_of_sight")
        truth = draw_prior(space, rng)
        stars = draw_sample(truth, 800, rng, "3d")
        target = make_likelihood(stars, space, s, SBC_DISTANCE)
        gauss = dataclasses.replace(s, velocity_law="gaussian")
        proposal = make_likelihood(stars, space, gauss, SBC_DISTANCE)
        run = run_dynesty(proposal, space, seed, nlive=s.nlive, dlogz=s.dlogz)
        draws = run.samples[np.random.default_rng([seed, 71]).choice(len(run.samples), 4000)]
        rw = reweight_samples(draws, np.array([proposal(v) for v in draws]), target, rng)
        print(
            f"{seed:5d} {truth['bh_mass']:7.0f} {rw['pareto_k']:8.2f} {rw['ess']:7.1f} "
            f"{rw['log_mean_ratio']:11.2f}"
        )


def _target_stars():
    """The 3,500 stars of issue 13's speed target: the luminous stars of an
    ``ngc3201-nbody`` catalogue (segregated, 1500 solMass IMBH, seed 200) inside 15",
    resampled with replacement to 3,500; and the true distance [kpc]."""
    from dynamics_helpers import realistic_stars

    stars, dist = realistic_stars(200, "segregated", 1500.0)
    idx = np.random.default_rng(0).choice(stars.R.size, 3500, replace=True)
    s = StarSample(
        stars.R[idx], stars.v_r[idx], stars.v_t[idx], stars.e_r[idx], stars.e_t[idx],
        stars.field_radius, x=stars.x[idx], y=stars.y[idx],
    )  # fmt: skip
    return s, dist


def bench_target_comparison(**knobs):
    """Issue 13's speed target: the four-model comparison (8 nested runs per velocity law
    with the kinematics-only evidences; 16 with the default's two laws weighed) of the
    3,500 target stars in two worker processes
    (``validation_settings(workers=2)``), wall and CPU seconds of this process and its
    workers."""
    import resource

    from dynamics_helpers import validation_settings

    from mavispm.dynamics.fit import compare, fit_models

    settings = validation_settings(workers=2, **knobs)
    s, dist = _target_stars()
    print(f"\n# four-model comparison, 3,500 target stars, workers 2, knobs {knobs or 'default'}")

    def cpu():
        own = resource.getrusage(resource.RUSAGE_SELF)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime

    c0, t0 = cpu(), time.perf_counter()
    fits = fit_models(s, settings, dist, 200)
    comp = compare(fits, settings.bh_mass_max)
    wall, used = time.perf_counter() - t0, cpu() - c0
    calls = sum(  # with the laws weighed, every law's runs (the kept law's alone undercount)
        g.evidence.n_calls + (g.evidence_kinematic.n_calls if g.evidence_kinematic else 0)
        for f in fits
        for g in (f.law_fits or (f,))
    )
    print(
        f"wall {wall:.1f} s ({wall / 60:.2f} min), CPU {used:.1f} s, {calls} likelihood calls "
        f"({1e3 * used / calls:.2f} CPU ms per call); ln B {comp.ln_bayes_factor:.2f}, "
        f"kinematics-only {comp.ln_bayes_factor_kinematic:.2f}, verdict {comp.verdict}"
    )


def bench_velocity_laws():
    """One model's nested evidence at 3,500 stars with the Gaussian law, the line-of-sight
    law run directly, the Gaussian run reweighted to it and the free-kurtosis law (same
    stars, settings, seed)."""
    import dataclasses

    from dynamics_helpers import validation_settings

    from mavispm.dynamics.fit import fit_model

    print("\n# velocity laws: one imbh evidence, 3,500 stars (CPU and wall seconds)")
    s, dist = _target_stars()
    base = dataclasses.replace(validation_settings(workers=1), kinematic_evidence=False)
    for name, knobs in (
        ("gaussian", {"velocity_law": "gaussian"}),
        ("reweighted", {"velocity_law": "line_of_sight", "reweight": True}),
        ("line_of_sight", {"velocity_law": "line_of_sight"}),
        ("free_kurtosis", {"velocity_law": "free_kurtosis"}),
    ):
        c0, t0 = time.process_time(), time.perf_counter()
        f = fit_model(s, dataclasses.replace(base, **knobs), dist, "imbh", 200)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
        bh = np.percentile(f.chain.samples[:, f.space.index("bh_mass")], [16, 50, 84])
        ev = f.evidence
        print(
            f"{name:14s} CPU {cpu:7.1f} s, wall {wall:7.1f} s, calls {ev.n_calls}, "
            f"ln Z {ev.log_z:.2f} +- {ev.log_z_err:.2f} ({ev.method}, k {ev.pareto_k:.2f}), "
            f"M_bh {bh[1]:.0f} ({bh[0]:.0f}-{bh[2]:.0f})"
        )


def bench_samplers(quick):
    print("\n# samplers on the recovery mock (2000 stars, M_bh = 1500 Msun)")
    _, (sp1, l1), (sp0, l0) = mock_likelihoods(1, 1500.0)
    configs = [(24, 20.0, 2500)] if quick else [(24, 20.0, 4000), (32, 50.0, 20000)]
    for walkers, tau_factor, max_steps in configs:
        t0, c0 = time.perf_counter(), time.process_time()
        r = run_emcee(
            l1,
            sp1,
            1,
            walkers=walkers,
            max_steps=max_steps,
            tau_factor=tau_factor,
            check_every=250,
            progress=False,
        )
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        bh = r.samples[:, sp1.index("bh_mass")]
        q = np.percentile(bh, [16, 50, 84])
        print(
            f"emcee walkers={walkers} tau_factor={tau_factor:g}: {cpu:7.1f} s CPU "
            f"({dt:.0f} s wall), steps={r.steps}, "
            f"tau_max={np.max(r.tau):.0f}, converged={r.converged}, acc={r.acceptance:.2f}, "
            f"M_bh={q[1]:.0f} +{q[2] - q[1]:.0f} -{q[1] - q[0]:.0f}"
        )
    for nlive in [100] if quick else [100, 250]:
        for name, sp, like in (("imbh", sp1, l1), ("no_imbh", sp0, l0)):
            t0, c0 = time.perf_counter(), time.process_time()
            e = run_dynesty(like, sp, 1, nlive=nlive, dlogz=0.5 if nlive < 200 else 0.1)
            dt, cpu = time.perf_counter() - t0, time.process_time() - c0
            print(
                f"dynesty {name:8s} nlive={nlive}: {cpu:7.1f} s CPU ({dt:.0f} s wall), calls={e.n_calls}, "
                f"lnZ={e.log_z:.2f} +- {e.log_z_err:.2f}, {1e3 * cpu / e.n_calls:.2f} ms CPU/call"
            )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and cases")
    parser.add_argument("--no-samplers", action="store_true", help="skip emcee/dynesty")
    parser.add_argument(
        "--comparison", action="store_true", help="time the four-model comparison (slow)"
    )
    parser.add_argument(
        "--target",
        action="store_true",
        help="time issue 13's speed target, the four-model comparison at 3,500 stars (slow)",
    )
    parser.add_argument(
        "--node-evidence",
        action="store_true",
        help="ln Z with 16 against 64 line-of-sight nodes on radially anisotropic clusters (slow)",
    )
    parser.add_argument(
        "--reweighting",
        action="store_true",
        help="overlap of the Gaussian and line-of-sight posteriors on SBC draws (slow)",
    )
    args = parser.parse_args(argv)
    print(f"mock: {RECOVERY_MOCK}")
    bench_projection(args.quick)
    bench_likelihood(args.quick)
    bench_line_of_sight(args.quick)
    bench_tracers(args.quick)
    if not args.no_samplers:
        bench_samplers(args.quick)
    if args.reweighting:
        bench_reweighting_overlap()
    if args.node_evidence:
        bench_line_of_sight_evidence(200, imbh_mass=1500.0, models=("none", "imbh"))
        bench_line_of_sight_evidence(206, imbh_mass=500.0)
    if args.target:
        bench_target_comparison()
    if args.comparison:
        bench_velocity_laws()
        bench_comparison(args.quick)
        fast = {"cusp": False, "centre_error": 0.0, "systemic_error": 0.0}
        bench_comparison(args.quick, n_stars=(3500,), kinematic_evidence=False, **fast)


if __name__ == "__main__":
    main()
