"""Helpers for the fast-star tests: generator catalogues with PM errors and no-IMBH fits.

The catalogues come from the cluster generator (its own Eddington DF in the
potential of cluster + IMBH), the errors are drawn here, and the no-IMBH mass
models come from the dynamics stage's likelihood (MAP, or a short emcee run in
the slow tests): nothing of the fast-star code is used to make the data.
"""

from __future__ import annotations

import functools

import astropy.units as u
import numpy as np

#: ~2,000 luminous stars inside 17" of the NGC 3201 preset, PM errors 20-100 uas/yr.
FIELD = {"radius": 17.0, "n_circle": 2000, "err_lo": 0.020, "err_hi": 0.100}

#: Cluster variants without an IMBH that mimic one: a 2000 Msun stellar-mass black-hole
#: subsystem (default radius 0.4 a; the ngc3201-nbody preset, whose Plummer-shaped groups
#: admit one), and Osipkov-Merritt radial anisotropy with the
#: smallest anisotropy radius the generator accepts for NGC 3201 (~300").
VARIANTS = {
    "plain": {},
    "bh_subsystem": {"preset": "ngc3201-nbody", "bh_subsystem_mass": 2000.0},
    "radial": {"anisotropy_radius": 300.0},
}


@functools.lru_cache(maxsize=8)
def generator_setup(bh_mass: float, variant: str = "plain"):
    """Settings and prebuilt model of the NGC 3201 generator cluster (cached)."""
    from mavispm.simulate.cluster.generator import (
        ClusterSettings,
        build_cluster_model,
        n_stars_for_circle,
    )

    radius = FIELD["radius"]
    s = ClusterSettings(
        imbh_mass=bh_mass,
        epochs=[0.0],
        field_size=2.0 * radius,
        margin=0.0,
        include_remnants=False,
        **VARIANTS[variant],
    )
    model = build_cluster_model(s)
    n = n_stars_for_circle(s, FIELD["n_circle"], radius, model)
    return s.replace(n_stars=n), model


def generator_catalogue(seed: int, bh_mass: float, variant: str = "plain", err_factor=1.0):
    """Luminous stars inside 17": truth table rows, noisy PMs and the model.

    Returns
    -------
    stars : PMStars
        With ``pm_x_true, pm_y_true``; per-axis errors uniform in [20, 100] uas/yr
        times ``err_factor`` (10 yr / baseline for another baseline).
    truth : dict
        ``r3d`` [pc], ``v3d`` [km/s] and ``psi`` [(km/s)^2] (the generator's
        relative potential at r3d, escape to its outer edge), ``psi_stars`` (the
        same without the IMBH: the stars' own potential) per star, and the
        positions ``x, y`` [arcsec].
    params : dict
        The generator's model parameters.
    """
    from mavispm.dynamics.fast_stars import PMStars
    from mavispm.simulate.cluster.generator import simulate_catalogue

    settings, model = generator_setup(float(bh_mass), variant)
    epochs, attrs = simulate_catalogue(settings, seed, model)
    t = next(iter(epochs.values()))
    x, y = t["x"].to_value(u.arcsec), t["y"].to_value(u.arcsec)
    R = np.hypot(x, y)
    keep = np.asarray(t["luminous"], bool) & (R < FIELD["radius"])
    rng = np.random.default_rng([seed, 7])
    n = int(keep.sum())
    err = err_factor * rng.uniform(FIELD["err_lo"], FIELD["err_hi"], (2, n))
    true = np.stack(
        [t["pm_x"].to_value(u.mas / u.yr)[keep], t["pm_y"].to_value(u.mas / u.yr)[keep]]
    )
    pm = true + err * rng.standard_normal((2, n))
    stars = PMStars(
        id=np.asarray(t["id"])[keep],
        R=R[keep],
        pm_x=pm[0],
        pm_y=pm[1],
        pm_x_err=err[0],
        pm_y_err=err[1],
        pm_xy_corr=np.zeros(n),
        pm_x_true=true[0],
        pm_y_true=true[1],
    )
    r3d = t["r3d"].to_value(u.pc)[keep]
    v3d = np.sqrt(sum(t[k].to_value(u.km / u.s)[keep] ** 2 for k in ("vx", "vy", "vz")))
    from mavispm.simulate.cluster.profiles import build_mass_model

    stellar = build_mass_model(model.mass.tracer, model.mass.stellar_mass, 0.0)
    truth = {
        "r3d": r3d,
        "v3d": v3d,
        "psi": model.mass.relative_potential(r3d),
        "psi_stars": stellar.relative_potential(r3d),
        "x": x[keep],
        "y": y[keep],
    }
    return stars, truth, dict(attrs["model_params"])


def fit_settings(anisotropy: str = "constant"):
    """NGC 3201 dynamics settings: King62 (c = 1.33) with a free inner cusp, core-radius
    prior; the centre and mean motion are held at the truth's (0) to keep the MAP fast.

    One constant beta by default: the MAP trials stand the MAP in for the posterior,
    which holds for constant beta. With the general profile (the stage's default) the
    no-IMBH MAP can sit at the prior's corners with a mass the posterior puts in its 1%
    tail (seed 210: beta_0 -0.49, beta_inf 0.95, log10 M 4.89 against the posterior's
    median 5.22; 3 false fast stars and a 2460 solMass "limit" from that MAP, none from
    the posterior's escape quantile), so that profile is tested through the stage's own
    posterior path (:func:`posterior_trial`)."""
    from mavispm.dynamics.settings import DynamicsSettings

    return DynamicsSettings(
        anisotropy=anisotropy,
        velocity_law="free_kurtosis",
        tracer="king62",
        king_concentration=1.33,
        cusp=True,
        log_scale_radius_range=(1.0, 3.0),
        log_scale_radius_prior=(np.log10(79.0), 0.05),
        centre_error=0.0,
        systemic_error=0.0,
        distance_error=0.0,
        progress=False,
    )


def star_sample(stars, x, y, settings):
    """The dynamics likelihood's :class:`StarSample` of PM stars at positions x, y
    [arcsec]: motions and errors along and across the radius."""
    from mavispm.dynamics.likelihood import StarSample
    from mavispm.measure.propermotions.motion_fit import radial_tangential

    var_x, var_y = stars.pm_x_err**2, stars.pm_y_err**2
    v_r, v_t, e_r, e_t, R, _ = radial_tangential(
        x, y, stars.pm_x, stars.pm_y, var_x, var_y, np.zeros_like(var_x)
    )
    return StarSample(
        np.maximum(R, settings.min_radius), v_r, v_t, e_r, e_t, FIELD["radius"], x=x, y=y
    )


def likelihoods(stars, x, y, distance, settings=None):
    """IMBH and no-IMBH (space, likelihood) pairs for PM stars at positions x, y [arcsec]."""
    from mavispm.dynamics.fit import make_likelihood, parameter_space

    s = settings or fit_settings()
    sample = star_sample(stars, x, y, s)
    out = []
    for with_bh in (True, False):
        sp = parameter_space(s, distance, with_bh)
        out.append((sp, make_likelihood(sample, sp, s, distance)))
    return out


def fast_flags(result, ids) -> np.ndarray:
    """Per star of ``ids`` (in order): whether the fast-star ``result`` calls it fast."""
    table = result.table
    return np.isin(ids, np.asarray(table["id"])[np.asarray(table["fast"], bool)])


def map_trial(
    seed: int,
    bh_mass: float,
    alpha: float = 0.00135,
    imbh_model: bool = True,
    variant="plain",
    baseline: float = 10.0,
):
    """Fast-star test of one generator catalogue with the MAP models of both fits.

    The MAP no-IMBH model stands in for the posterior (one model, so the escape
    quantile is that model's value): less conservative than the stage's posterior
    quantile, i.e. a stronger test of false detections and of the lower limit.
    ``imbh_model`` also fits the IMBH model (its escape curve and expected count);
    ``baseline`` [yr] scales the 10-yr PM errors by 10 / baseline.

    Returns
    -------
    dict
        ``result`` (FastStarResult), ``truth``, ``stars``, ``fast`` (bool per
        usable star, aligned with ``stars``), ``distance``.
    """
    from mavispm.dynamics.escape_velocity import mass_model_from_sample
    from mavispm.dynamics.fast_stars import FastStarSettings, fast_star_test, model_dispersion
    from mavispm.dynamics.sampling import find_map

    stars, truth, params = generator_catalogue(seed, bh_mass, variant, 10.0 / baseline)
    d = params["distance"]
    (sp1, l1), (sp0, l0) = likelihoods(stars, truth["x"], truth["y"], d)
    th0 = sp0.from_scaled(find_map(l0, sp0))
    imbh = {}
    if imbh_model:
        th1 = sp1.from_scaled(find_map(l1, sp1))
        stellar = th1.copy()
        stellar[sp1.index("bh_mass")] = 0.0
        imbh = {
            "imbh_models": [mass_model_from_sample(l1, th1)],
            "imbh_dispersion": model_dispersion(l1, th1),
            "stellar_models": [mass_model_from_sample(l1, stellar)],
        }
    res = fast_star_test(
        stars,
        d,
        [mass_model_from_sample(l0, th0)],
        FastStarSettings(alpha=alpha, n_monte_carlo=2000),
        dispersion=model_dispersion(l0, th0),
        baseline=baseline,
        field_radius=FIELD["radius"],
        seed=seed,
        **imbh,
    )
    fast = fast_flags(res, stars.id)
    return {"result": res, "truth": truth, "stars": stars, "fast": fast, "distance": d}


def posterior_trial(
    seed: int,
    bh_mass: float = 0.0,
    variant: str = "plain",
    alpha: float = 0.00135,
    anisotropy: str = "general",
    models: tuple = ("none",),
):
    """The stage's fast-star test of one generator catalogue: the nested posteriors of
    ``models`` (nlive 100, dlogz 0.5; the helper's settings with ``anisotropy``) and
    :func:`mavispm.dynamics.fast_stars.run_on_fits`, the escape velocity's quantile over
    the no-IMBH posterior and the lower limit against the deepest stellar potential of
    the IMBH model's posterior (when ``models`` holds ``imbh``), as the stage takes them.

    Returns
    -------
    dict
        As :func:`map_trial`, plus ``log_mass`` (the ``none`` posterior's 1 / 50 / 99 %
        quantiles of log10 M [solMass]).
    """
    import dataclasses

    from mavispm.dynamics.fast_stars import FastStarSettings, run_on_fits
    from mavispm.dynamics.fit import fit_model

    stars, truth, params = generator_catalogue(seed, bh_mass, variant)
    d = params["distance"]
    s = dataclasses.replace(
        fit_settings(anisotropy),
        posterior="nested",
        nlive=100,
        dlogz=0.5,
        kinematic_evidence=False,
        fast_stars=FastStarSettings(alpha=alpha, n_monte_carlo=2000),
    )
    sample = star_sample(stars, truth["x"], truth["y"], s)
    fits = [fit_model(sample, s, d, model, seed) for model in models]
    res = run_on_fits(None, s, fits, d, FIELD["radius"], seed, stars=sample)
    log_mass = fits[0].chain.samples[:, fits[0].space.index("log_mass")]
    return {
        "result": res,
        "truth": truth,
        "stars": stars,
        "fast": fast_flags(res, np.arange(stars.R.size)),  # the sample's ids: row numbers
        "distance": d,
        "log_mass": np.percentile(log_mass, [1.0, 50.0, 99.0]),
    }
