"""Test helpers for the dynamics stage: an independent mock PM catalogue generator.

The cluster generator of the ``cluster`` branch was not available while these
tests were written, so recovery tests draw their own mock data here, by a
method independent of the code under test:

* positions: exact inverse-CDF sampling of a Plummer sphere, random orientation;
* velocities: isotropic Gaussians with the *closed-form* Plummer dispersion
  ``sigma^2 = G M / (6 sqrt(r^2 + a^2))`` plus the point-mass term
  ``G M_bh / a * (1 - u)^3 (u + 3) / (3 u) * (1 + x^2)^(5/2)``, ``u = x / sqrt(1 + x^2)``
  (derived by hand; no Jeans projector, quadrature or interpolation involved);
* proper motions with per-star Gaussian errors uniform in [err_lo, err_hi].
"""

from __future__ import annotations

import functools

import numpy as np

G = 4.300917270e-3  # pc (km/s)^2 / Msun
KMS = 4.740470463533348  # km/s per mas/yr per kpc
PC_PER_ARCSEC_KPC = 1e3 * np.pi / 648000.0


def plummer_sigma2_3d(r_pc, mass, a_pc, bh_mass):
    """Isotropic 1-D dispersion squared [km^2/s^2] of a Plummer sphere + point mass."""
    x = r_pc / a_pc
    s = np.sqrt(1.0 + x * x)
    u = x / s
    one_minus_u = 1.0 / (s * (s + x))  # cancellation-free 1 - u
    bh_term = one_minus_u**3 * (u + 3.0) / (3.0 * u) * s**5
    return G * mass / (6.0 * a_pc * s) + G * bh_mass / a_pc * bh_term


def mock_pm_stars(
    seed,
    n_field=2000,
    mass=1.0e5,
    a_arcsec=80.0,
    bh_mass=1500.0,
    distance=4.6,
    field_radius=17.0,
    err_lo=0.020,
    err_hi=0.100,
):
    """Draw ``n_field`` stars inside ``field_radius`` with noisy proper motions.

    Returns
    -------
    dict
        ``x, y, R`` [arcsec], ``pm_x, pm_y, pm_x_err, pm_y_err, pm_r, pm_t,
        pm_r_err, pm_t_err, pm_x_true, pm_y_true`` [mas/yr].
    """
    rng = np.random.default_rng(seed)
    a_pc = a_arcsec * distance * PC_PER_ARCSEC_KPC
    xs, ys, zs = [], [], []
    need = n_field
    while need > 0:
        m = max(4 * need * int(1 + (a_arcsec / field_radius) ** 2), 1000)
        q = rng.uniform(1e-12, 1.0, m)
        r = a_pc / np.sqrt(q ** (-2.0 / 3.0) - 1.0)
        cth = rng.uniform(-1, 1, m)
        phi = rng.uniform(0, 2 * np.pi, m)
        sth = np.sqrt(1 - cth**2)
        x, y, z = r * sth * np.cos(phi), r * sth * np.sin(phi), r * cth
        keep = np.hypot(x, y) / (distance * PC_PER_ARCSEC_KPC) < field_radius
        xs.append(x[keep])
        ys.append(y[keep])
        zs.append(z[keep])
        need -= int(keep.sum())
    x = np.concatenate(xs)[:n_field]
    y = np.concatenate(ys)[:n_field]
    z = np.concatenate(zs)[:n_field]
    r = np.sqrt(x * x + y * y + z * z)
    sig = np.sqrt(plummer_sigma2_3d(r, mass, a_pc, bh_mass))
    conv = KMS * distance
    pm_true = rng.standard_normal((2, n_field)) * sig / conv
    err = rng.uniform(err_lo, err_hi, (2, n_field))
    pm = pm_true + err * rng.standard_normal((2, n_field))
    xa = x / (distance * PC_PER_ARCSEC_KPC)
    ya = y / (distance * PC_PER_ARCSEC_KPC)
    R = np.hypot(xa, ya)
    cx, sy = xa / R, ya / R
    pm_r = pm[0] * cx + pm[1] * sy
    pm_t = -pm[0] * sy + pm[1] * cx
    # independent x/y errors: r/t errors are the rotated ones (exactly, for equal x/y errors)
    e_r = np.sqrt((err[0] * cx) ** 2 + (err[1] * sy) ** 2)
    e_t = np.sqrt((err[0] * sy) ** 2 + (err[1] * cx) ** 2)
    return {
        "x": xa,
        "y": ya,
        "R": R,
        "pm_x": pm[0],
        "pm_y": pm[1],
        "pm_x_err": err[0],
        "pm_y_err": err[1],
        "pm_r": pm_r,
        "pm_t": pm_t,
        "pm_r_err": e_r,
        "pm_t_err": e_t,
        "pm_x_true": pm_true[0],
        "pm_y_true": pm_true[1],
    }


def write_mock_propermotions(path, seed, distance=4.6, **kwargs):
    """Write a mock ``propermotions`` product from :func:`mock_pm_stars`."""
    import astropy.units as u
    from astropy.table import QTable

    from mavispm.core.products import write_product

    d = mock_pm_stars(seed, distance=distance, **kwargs)
    n = d["R"].size
    t = QTable()
    t["id"] = np.arange(n, dtype=np.int64)
    for k in ("x", "y", "R"):
        t[k] = d[k] * u.arcsec
    for k in (
        "pm_x",
        "pm_y",
        "pm_x_err",
        "pm_y_err",
        "pm_r",
        "pm_t",
        "pm_r_err",
        "pm_t_err",
        "pm_x_true",
        "pm_y_true",
    ):
        t[k] = d[k] * u.mas / u.yr
    t["pm_xy_corr"] = np.zeros(n)
    t["n_epochs"] = np.full(n, 2, dtype=np.int64)
    t["flag"] = np.zeros(n, dtype=np.int64)
    t["mag"] = np.full(n, 20.0) * u.mag
    return write_product(
        path,
        "propermotions",
        tables={"stars": t},
        attrs={
            "distance": distance * u.kpc,
            "epochs": np.array([0.0, 10.0]),
            "reference_epoch": 0.0 * u.yr,
            "imbh_mass_true": kwargs.get("bh_mass", 1500.0) * u.Msun,
        },
        seed=seed,
    )


#: Mock cluster used by the recovery tests: 5e4 Msun Plummer sphere, a = 25 arcsec
#: (0.56 pc at 4.6 kpc, central 1-D dispersion 8 km/s), 2,000 stars inside 17 arcsec.
RECOVERY_MOCK = {"mass": 5.0e4, "a_arcsec": 25.0, "distance": 4.6, "n_field": 2000}


def recovery_spaces(bh_mass_max=1.0e4):
    """Parameter spaces (IMBH, no-IMBH) with the default priors of the stage."""
    from mavispm.dynamics.fit import parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    # the mocks are cored Plummer spheres: the (free) cusp is switched off to keep
    # these optimiser tests short; the cusp is exercised on the generator catalogues
    s = DynamicsSettings(bh_mass_max=bh_mass_max, cusp=False, velocity_law="free_kurtosis")
    return (
        s,
        parameter_space(s, RECOVERY_MOCK["distance"], "imbh", positions=False),
        parameter_space(s, RECOVERY_MOCK["distance"], "none", positions=False),
    )


def mock_likelihoods(seed, bh_mass):
    """Star sample and the IMBH / no-IMBH likelihoods for one mock data set."""
    from mavispm.dynamics.fit import make_likelihood
    from mavispm.dynamics.likelihood import StarSample

    d = mock_pm_stars(seed, bh_mass=bh_mass, **RECOVERY_MOCK)
    stars = StarSample(d["R"], d["pm_r"], d["pm_t"], d["pm_r_err"], d["pm_t_err"], 17.0)
    s, sp1, sp0 = recovery_spaces()
    dist = RECOVERY_MOCK["distance"]
    return (
        stars,
        (sp1, make_likelihood(stars, sp1, s, dist)),
        (sp0, make_likelihood(stars, sp0, s, dist)),
    )


def recovery_trial(seed, bh_mass, nlive=100, dlogz=0.5):
    """Evidence of both models and the IMBH-model M_bh posterior for one mock.

    Returns
    -------
    dict
        ``ln_b``, ``ln_b_err``, M_bh quantiles ``q16``, ``q50``, ``q84``, ``q95``.
    """
    from mavispm.dynamics.evidence import bayes_factor, run_dynesty

    _, (sp1, l1), (sp0, l0) = mock_likelihoods(seed, bh_mass)
    e1 = run_dynesty(l1, sp1, seed, nlive=nlive, dlogz=dlogz)
    e0 = run_dynesty(l0, sp0, seed, nlive=nlive, dlogz=dlogz)
    return _trial_row(seed, bh_mass, bayes_factor(e1, e0), e1.samples[:, sp1.index("bh_mass")])


def _trial_row(seed, bh_mass, ln_b_and_err, bh_samples) -> dict:
    """One recovery-trial row: ln B with its error and the M_bh posterior quantiles."""
    q = np.percentile(bh_samples, [16, 50, 84, 95])
    return {
        "seed": seed,
        "bh_true": bh_mass,
        "ln_b": ln_b_and_err[0],
        "ln_b_err": ln_b_and_err[1],
        **{f"q{p}": v for p, v in zip((16, 50, 84, 95), q)},
    }


def write_noisy_propermotions(path, ids, x, y, true, mag, distance, seed, err_lo, err_hi):
    """A two-epoch ``propermotions`` product of stars at ``x, y`` [arcsec] whose true
    motions ``true`` (shape (2, N) [mas/yr]) get per-star Gaussian errors uniform in
    [err_lo, err_hi] mas/yr; ``mag`` [mag] and ``distance`` [kpc] as given."""
    import astropy.units as u
    from astropy.table import QTable

    from mavispm.core.products import write_product

    rng = np.random.default_rng(seed)
    n = len(x)
    err = rng.uniform(err_lo, err_hi, (2, n))
    pm = true + err * rng.standard_normal((2, n))
    R = np.hypot(x, y)
    cx = np.where(R > 0, x / np.maximum(R, 1e-300), 1.0)
    sy = np.where(R > 0, y / np.maximum(R, 1e-300), 0.0)
    mas = u.mas / u.yr
    out = QTable()
    out["id"] = ids
    out["x"], out["y"], out["R"] = x * u.arcsec, y * u.arcsec, R * u.arcsec
    out["pm_x"], out["pm_y"] = pm[0] * mas, pm[1] * mas
    out["pm_x_err"], out["pm_y_err"] = err[0] * mas, err[1] * mas
    out["pm_xy_corr"] = np.zeros(n)
    out["pm_r"] = (pm[0] * cx + pm[1] * sy) * mas
    out["pm_t"] = (-pm[0] * sy + pm[1] * cx) * mas
    out["pm_r_err"] = np.sqrt((err[0] * cx) ** 2 + (err[1] * sy) ** 2) * mas
    out["pm_t_err"] = np.sqrt((err[0] * sy) ** 2 + (err[1] * cx) ** 2) * mas
    out["n_epochs"] = np.full(n, 2, dtype=np.int64)
    out["flag"] = np.zeros(n, dtype=np.int64)
    out["mag"] = mag
    out["pm_x_true"], out["pm_y_true"] = true[0] * mas, true[1] * mas
    return write_product(
        path,
        "propermotions",
        tables={"stars": out},
        attrs={
            "distance": distance,
            "epochs": np.array([0.0, 10.0]),
            "reference_epoch": 0.0 * u.yr,
        },
        seed=seed,
    )


#: Cluster-generator recovery setup: NGC 3201 preset, ~2,000 luminous stars inside
#: 17 arcsec (a 34" square field holds the whole circle), PM errors 20-100 microarcsec/yr.
GENERATOR_FIELD = {"radius": 17.0, "n_circle": 2000, "err_lo": 0.020, "err_hi": 0.100}


@functools.lru_cache(maxsize=4)
def _generator_setup(bh_mass):
    from mavispm.simulate.cluster.generator import (
        ClusterSettings,
        build_cluster_model,
        n_stars_for_circle,
    )

    radius = GENERATOR_FIELD["radius"]
    s = ClusterSettings(
        imbh_mass=bh_mass,
        epochs=[0.0],
        field_size=2.0 * radius,
        margin=0.0,
        include_remnants=False,
    )
    model = build_cluster_model(s)
    n = n_stars_for_circle(s, GENERATOR_FIELD["n_circle"], radius, model)
    return s.replace(n_stars=n), model


def generator_stars(seed, bh_mass):
    """Stars inside 17" of a cluster-generator catalogue with Gaussian PM errors.

    Returns
    -------
    stars : StarSample
        Radial/tangential PMs about the centre with per-star errors uniform in
        [20, 100] microarcsec/yr (independent x/y errors, rotated exactly).
    params : dict
        The generator's true ``model_params``.
    """
    import astropy.units as u

    from mavispm.dynamics.likelihood import StarSample
    from mavispm.simulate.cluster.generator import simulate_catalogue

    settings, model = _generator_setup(float(bh_mass))
    epochs, attrs = simulate_catalogue(settings, seed, model)
    t = next(iter(epochs.values()))
    x, y = t["x"].to_value(u.arcsec), t["y"].to_value(u.arcsec)
    R = np.hypot(x, y)
    keep = np.asarray(t["luminous"], bool) & (R < GENERATOR_FIELD["radius"])
    rng = np.random.default_rng([seed, 7])
    n = int(keep.sum())
    err = rng.uniform(GENERATOR_FIELD["err_lo"], GENERATOR_FIELD["err_hi"], (2, n))
    pm = np.stack([t["pm_x"].to_value(u.mas / u.yr)[keep], t["pm_y"].to_value(u.mas / u.yr)[keep]])
    pm = pm + err * rng.standard_normal((2, n))
    R = np.maximum(R[keep], 1e-9)
    cx, sy = x[keep] / R, y[keep] / R
    stars = StarSample(
        R,
        pm[0] * cx + pm[1] * sy,
        -pm[0] * sy + pm[1] * cx,
        np.sqrt((err[0] * cx) ** 2 + (err[1] * sy) ** 2),
        np.sqrt((err[0] * sy) ** 2 + (err[1] * cx) ** 2),
        GENERATOR_FIELD["radius"],
    )
    return stars, dict(attrs["model_params"])


def generator_fit_settings(model="dehnen"):
    """Fit settings for generator catalogues.

    The generator's King62 (W0 = 6.3, core 79") cluster is flat inside 17" without an
    IMBH and has a gamma = 1.55 cusp inside the influence radius (39") with one;
    Plummer or fixed-slope profiles cannot follow both.

    Parameters
    ----------
    model : {"dehnen", "cusped_king"}
        Dehnen tracer with free inner slope, or a King62 profile (c = 1.33) with a
        fitted cusp slope and radius (``cusped_king``; the cusp is free in every
        model, never tied to the BH). A suffix ``_rc`` adds a Gaussian
        prior on the King62 core radius (the generator's 79" +- 12%), as a photometric
        surface-density profile would give.
    """
    from mavispm.dynamics.settings import DynamicsSettings

    # the generator's King62 core radius (79", NGC 3201's photometric value) as known
    # from the surface-brightness profile, 12% (0.05 dex) uncertainty
    prior = (np.log10(79.0), 0.05) if model.endswith("_rc") else None
    model = model.removesuffix("_rc")
    if model == "cusped_king":
        return DynamicsSettings(
            tracer="king62",
            king_concentration=1.33,
            cusp=True,
            log_scale_radius_range=(1.0, 3.0),
            log_scale_radius_prior=prior,
            progress=False,
            velocity_law="free_kurtosis",
        )
    return DynamicsSettings(
        tracer="dehnen", cusp=True, progress=False, velocity_law="free_kurtosis"
    )


def generator_recovery_trial(seed, bh_mass, nlive=100, dlogz=0.5, model="dehnen"):
    """Nested-sampling posterior of M_bh and ln B on one generator catalogue.

    The ``imbh`` and ``none`` models' dynesty runs give ln B, and the ``imbh`` run's
    posterior (the stage's default posterior, the one the simulation-based calibration
    covers) the 68% interval and the 95% upper limit. (Until 2026-12-05 the interval
    came from emcee chains of 16 walkers that did not reach 20 autocorrelation times in
    their 2,000 steps with the current models: tau 78-229.)

    Returns
    -------
    dict
        ``seed, bh_true, n_stars, ln_b, ln_b_err, q16, q50, q84, q95, cpu_s, model``.
    """
    import time

    from mavispm.dynamics.evidence import bayes_factor, run_dynesty
    from mavispm.dynamics.fit import make_likelihood, nested_chain, parameter_space

    t0 = time.process_time()
    stars, params = generator_stars(seed, bh_mass)
    s = generator_fit_settings(model)
    dist = params["distance"]
    sp1 = parameter_space(s, dist, "imbh", positions=False)
    sp0 = parameter_space(s, dist, "none", positions=False)
    l1, l0 = make_likelihood(stars, sp1, s, dist), make_likelihood(stars, sp0, s, dist)
    e1 = run_dynesty(l1, sp1, seed, nlive=nlive, dlogz=dlogz)
    e0 = run_dynesty(l0, sp0, seed, nlive=nlive, dlogz=dlogz)
    chain = nested_chain(e1, sp1)
    return {
        **_trial_row(seed, bh_mass, bayes_factor(e1, e0), chain.samples[:, sp1.index("bh_mass")]),
        "n_stars": int(stars.R.size),
        "cpu_s": time.process_time() - t0,
        "model": model,
    }


def write_mock_catalogue(path, seed, distance=4.6, n_dark=50, **kwargs):
    """Write a mock truth ``catalogue`` (one epoch) from :func:`mock_pm_stars`.

    The true motions are ``pm_x_true, pm_y_true``; ``n_dark`` extra non-luminous
    stars with absurd motions (100 mas/yr) must be ignored by truth-level fits.
    """
    import astropy.units as u
    from astropy.table import QTable

    from mavispm.core.catalogue import write_catalogue

    d = mock_pm_stars(seed, distance=distance, **kwargs)
    n = d["R"].size
    t = QTable()
    t["id"] = np.arange(n + n_dark, dtype=np.int64)
    t["x"] = np.concatenate([d["x"], np.zeros(n_dark) + 1.0]) * u.arcsec
    t["y"] = np.concatenate([d["y"], np.zeros(n_dark)]) * u.arcsec
    t["pm_x"] = np.concatenate([d["pm_x_true"], np.full(n_dark, 100.0)]) * u.mas / u.yr
    t["pm_y"] = np.concatenate([d["pm_y_true"], np.full(n_dark, 100.0)]) * u.mas / u.yr
    t["mag"] = np.full(n + n_dark, 20.0) * u.mag
    t["luminous"] = np.concatenate([np.ones(n, bool), np.zeros(n_dark, bool)])
    t.meta["epoch"] = 0.0 * u.yr
    return write_catalogue(path, {"e0": t}, attrs={"distance": distance * u.kpc}, seed=seed)


#: Simulation-based calibration: priors the mocks are drawn from and the fit uses.
SBC_PRIOR = {"log_mass": (4.5, 5.0), "log_scale_radius": (1.2, 1.6), "bh_mass": (0.0, 5000.0)}


def sbc_trial(seed, n_stars=600, n_ranks=99, walkers=16, max_steps=3000, sampler="emcee"):
    """One SBC draw: parameters from the prior, an independent mock, an emcee fit, the rank.

    The mock (:func:`mock_pm_stars`: Plummer sphere + point mass, isotropic, errors
    20-100 microarcsec/yr, 17" field, 4.6 kpc) matches the fitted model (Plummer
    tracer without cusp, isotropic, distance known, centre and motion fixed), so
    the rank of the true M_bh among ``n_ranks`` posterior draws is uniform on
    0..n_ranks if the posterior is calibrated (Talts et al. 2018).

    Returns
    -------
    dict
        ``seed, bh_true, rank, n_ranks, q2.5, q16, q50, q84, q97.5, converged, tau``.
    """
    from mavispm.dynamics.fit import make_likelihood
    from mavispm.dynamics.likelihood import StarSample
    from mavispm.dynamics.parameters import Parameter, ParameterSpace
    from mavispm.dynamics.sampling import run_emcee
    from mavispm.dynamics.settings import DynamicsSettings

    rng = np.random.default_rng([seed, 13])
    truth = {k: rng.uniform(lo, hi) for k, (lo, hi) in SBC_PRIOR.items()}
    d = mock_pm_stars(
        seed,
        n_field=n_stars,
        mass=10 ** truth["log_mass"],
        a_arcsec=10 ** truth["log_scale_radius"],
        bh_mass=truth["bh_mass"],
        distance=4.6,
    )
    stars = StarSample(d["R"], d["pm_r"], d["pm_t"], d["pm_r_err"], d["pm_t_err"], 17.0)
    space = ParameterSpace([Parameter(k, lo=lo, hi=hi) for k, (lo, hi) in SBC_PRIOR.items()])
    s = DynamicsSettings(
        cusp=False,
        distance_error=0.0,
        log_scale_radius_range=(1.0, 2.0),
        velocity_law="free_kurtosis",
    )
    like = make_likelihood(stars, space, s, 4.6)
    if sampler == "nested":
        from mavispm.dynamics.evidence import run_dynesty
        from mavispm.dynamics.fit import nested_chain

        chain = nested_chain(run_dynesty(like, space, seed, nlive=200, dlogz=0.1), space)
    else:
        chain = run_emcee(
            like,
            space,
            seed,
            walkers=walkers,
            max_steps=max_steps,
            tau_factor=30.0,
            check_every=250,
            progress=False,
        )
    bh = chain.samples[:, space.index("bh_mass")]
    pick = np.linspace(0, bh.size - 1, n_ranks).astype(int)
    q = np.percentile(bh, [2.5, 16, 50, 84, 97.5])
    return {
        "seed": seed,
        "bh_true": truth["bh_mass"],
        "rank": int(np.sum(bh[pick] < truth["bh_mass"])),
        "n_ranks": n_ranks,
        **{f"q{p:g}": float(v) for p, v in zip((2.5, 16, 50, 84, 97.5), q)},
        "converged": bool(chain.converged),
        "tau": float(np.max(chain.tau)),
        "sampler": sampler,
    }


#: Null and IMBH cases of the validation matrix (issue 13) on the cluster generator's
#: realistic ``ngc3201-nbody`` clusters: overrides of ClusterSettings.
VALIDATION_CASES = {
    "segregated": {},
    "radial_anisotropy": {"anisotropy_radius": 300.0},
    "bh_subsystem": {"bh_subsystem_mass": 1500.0},
    "core_collapse": {"core_collapse": True},
}

#: With an IMBH the generator's cusp is the IMBH's: these cases' IMBH catalogues are the
#: segregated IMBH catalogues of the same seeds, run (and counted) once.
SAME_AS_SEGREGATED = ("core_collapse",)


#: An observer's NGC 3201 priors and their quoted errors (per trial the prior means are
#: drawn about the truth with these widths, so that no prior sits on the truth): the
#: photometric centre +- 0.5" per axis; the distance 4.74 +- 0.04 kpc (Baumgardt &
#: Vasiliev 2021); the core radius 1.30' +- 0.05 dex (Harris 1996, 2010 edition) as a
#: Plummer scale radius a = r_c / 0.644 (the projected half-density radius of a Plummer
#: profile is 0.644 a), log10(121.1") = 2.083.
OBSERVER_CENTRE_ERROR = 0.5
OBSERVER_DISTANCE_ERROR = 0.04
OBSERVER_LOG_SCALE_RADIUS = (float(np.log10(1.30 * 60.0 / 0.644)), 0.05)


def observer_priors(seed, true_distance):
    """An observer's prior means for one trial: the literature centre (offset [arcsec] of
    the assumed centre from the true one), distance [kpc] and log10 Plummer scale radius
    [arcsec], each drawn about the truth (or the photometric value) with its quoted error."""
    rng = np.random.default_rng([seed, 17])
    centre = OBSERVER_CENTRE_ERROR * rng.standard_normal(2)
    distance = true_distance + OBSERVER_DISTANCE_ERROR * rng.standard_normal()
    mean, sd = OBSERVER_LOG_SCALE_RADIUS
    return centre, float(distance), float(mean + sd * rng.standard_normal())


def realistic_stars(
    seed, case="segregated", imbh_mass=0.0, radius=15.0, pm_error=0.015, centre=(0.0, 0.0)
):
    """Luminous stars inside ``radius`` of an ``ngc3201-nbody`` catalogue, true motions plus
    Gaussian errors of ``pm_error`` mas/yr per component, with positions (for the centre fit)
    about the observer's assumed centre ``centre`` (its offset from the true centre [arcsec];
    the field is centred there). Returns the sample and the true distance [kpc]."""
    import astropy.units as u

    from mavispm.dynamics.likelihood import StarSample
    from mavispm.simulate.cluster.generator import simulate_catalogue
    from mavispm.simulate.cluster.settings import ClusterSettings

    # The field (square, about the true centre) must hold the offset circle; the star
    # number scales with its area so that the surface density does not depend on the offset.
    field = 2.0 * radius + 2.0 + 2.0 * np.ceil(np.hypot(*centre))
    s = ClusterSettings(
        preset="ngc3201-nbody",
        imbh_mass=imbh_mass,
        epochs=[0.0],
        field_size=field,
        n_stars=int(round(3500 * (field / (2.0 * radius + 2.0)) ** 2)),
        **VALIDATION_CASES[case],
    )
    epochs, attrs = simulate_catalogue(s, seed)
    t = next(iter(epochs.values()))
    x = t["x"].to_value(u.arcsec) - centre[0]
    y = t["y"].to_value(u.arcsec) - centre[1]
    R = np.hypot(x, y)
    keep = np.asarray(t["luminous"], bool) & (R < radius)
    rng = np.random.default_rng([seed, 11])
    n = int(keep.sum())
    pm = np.stack([t["pm_x"].to_value(u.mas / u.yr)[keep], t["pm_y"].to_value(u.mas / u.yr)[keep]])
    pm = pm + pm_error * rng.standard_normal((2, n))
    R = np.maximum(R[keep], 1e-9)
    cx, sy = x[keep] / R, y[keep] / R
    err = np.full(n, pm_error)
    stars = StarSample(
        R,
        pm[0] * cx + pm[1] * sy,
        -pm[0] * sy + pm[1] * cx,
        err,
        err.copy(),
        radius,
        x=x[keep],
        y=y[keep],
    )
    return stars, float(u.Quantity(attrs["distance"], u.kpc).value)


def validation_settings(**knobs):
    """Dynamics settings of the validation matrix: the four models, Plummer tracer with a
    free cusp, centre (prior sd 0.5"), distance (sd 0.04 kpc) and systemic motion fitted,
    the scale-radius prior of the photometric core radius (``OBSERVER_LOG_SCALE_RADIUS``;
    each trial replaces its mean by its own draw), nested-sampling posterior and
    evidences (nlive 100, dlogz 0.5); ``knobs`` override any of these."""
    from mavispm.dynamics.settings import DynamicsSettings

    base = dict(
        progress=False,
        posterior="nested",
        walkers=32,
        max_steps=4000,
        tau_factor=20.0,
        check_every=250,
        nlive=100,
        dlogz=0.5,
        centre_error=OBSERVER_CENTRE_ERROR,
        distance_error=OBSERVER_DISTANCE_ERROR,
        log_scale_radius_range=(1.0, 3.0),
        log_scale_radius_prior=OBSERVER_LOG_SCALE_RADIUS,
    )
    return DynamicsSettings(**{**base, **knobs})


def observer_trial_inputs(seed, case, imbh_mass, settings, log_a_shift=0.0):
    """One realistic cluster from an observer's footing: the stars about the literature
    centre and the settings with the trial's scale-radius prior (``observer_priors``
    drawn about the truth; ``log_a_shift`` [dex] moves the prior mean).

    Returns
    -------
    stars : StarSample
    distance : float
        The prior mean of the distance [kpc] (the fit's distance).
    settings : DynamicsSettings
        ``settings`` with ``log_scale_radius_prior`` the trial's.
    draws : dict
        ``centre`` (the assumed centre's offset [arcsec]), ``distance_true`` [kpc] and
        ``log_a`` (the scale-radius prior mean, log10 arcsec).
    """
    import dataclasses

    from mavispm.simulate.cluster.presets import get_preset

    centre, dist, log_a = observer_priors(seed, get_preset("ngc3201-nbody").distance)
    log_a += log_a_shift
    stars, true_distance = realistic_stars(seed, case, imbh_mass, centre=centre)
    s = dataclasses.replace(settings, log_scale_radius_prior=(log_a, OBSERVER_LOG_SCALE_RADIUS[1]))
    return stars, dist, s, {"centre": centre, "distance_true": true_distance, "log_a": log_a}


def validation_trial(seed, case, imbh_mass, settings=None):
    """Four-model comparison on one realistic cluster from an observer's footing (prior
    means of centre, distance and scale radius drawn by ``observer_priors``); the verdict
    numbers."""
    import dataclasses
    import time

    from mavispm.dynamics.fit import compare, fit_models, marginal_bh_samples

    t0 = time.process_time()
    base = dataclasses.replace(
        settings or validation_settings(),
        workers=1,  # trials run in parallel, each in one process
    )
    stars, dist, s, draws = observer_trial_inputs(seed, case, imbh_mass, base)
    fits = fit_models(stars, s, dist, seed)  # the stage's own (velocity laws weighed)
    c = compare(fits, s.bh_mass_max, s.ambiguous_ln_b)
    bh = marginal_bh_samples(fits, seed)
    q = np.percentile(bh, [2.5, 16, 50, 84, 97.5]) if bh.size else np.full(5, np.nan)
    return {
        "seed": seed,
        "case": case,
        "imbh_mass": imbh_mass,
        "n_stars": int(stars.R.size),
        "centre_offset": float(np.hypot(*draws["centre"])),
        "distance_prior": dist,
        "distance_true": draws["distance_true"],
        "log_scale_radius_prior": draws["log_a"],
        "ln_b": c.ln_bayes_factor,
        "ln_b_kin": c.ln_bayes_factor_kinematic,
        "ln_b_dark": c.ln_b_dark_centre,
        "ln_b_imbh_vs_ext": c.ln_b_imbh_vs_extended,
        "verdict": c.verdict,
        "converged": c.converged,
        **{f"q{p:g}": float(v) for p, v in zip((2.5, 16, 50, 84, 97.5), q)},
        "cpu_s": time.process_time() - t0,
    }
