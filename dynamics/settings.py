"""Settings of the dynamics stage (one frozen dataclass, GSParams style).

Build with :func:`mavispm.dynamics.cli.validate_settings` (TOML table
``[dynamics]``); every key is documented in ``docs/dynamics.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from mavispm.core.config import unit_field
from mavispm.dynamics.fast_stars import FastStarSettings
from mavispm.dynamics.likelihood import VELOCITY_LAWS
from mavispm.dynamics.shape_law import KAPPA_LIMITS
from mavispm.dynamics.tracers import TRACERS

__all__ = [
    "DYNAMICS_KNOB_HOMES",
    "DynamicsKnobs",
    "DynamicsSettings",
    "MODELS",
    "POSTERIORS",
    "WEIGHED",
    "WEIGHED_LAWS",
]

#: Mass models of the comparison: which dark central components each one has.
MODELS = {
    "none": {"bh": False, "dark": False},
    "imbh": {"bh": True, "dark": False},
    "dark": {"bh": False, "dark": True},
    "imbh_dark": {"bh": True, "dark": True},
}
ANISOTROPY = ("constant", "osipkov-merritt", "general")
#: The ``velocity_law`` that weighs the laws of ``compare_velocity_laws`` by evidence.
WEIGHED = "weighed"
#: The laws weighed by default: one calibrated on equilibrium velocities, one on Gaussian
#: 3-D velocities (docs/dynamics.md, "Weighing the velocity laws by evidence").
WEIGHED_LAWS = ("free_kurtosis", "line_of_sight")
#: Radial form of the fitted excess kurtosis (velocity_law = "free_kurtosis").
KAPPA_PROFILES = ("constant", "radial")
#: Where the posterior comes from: the nested-sampling run (default) or emcee.
POSTERIORS = ("nested", "emcee")
#: Where the star-count term's completeness comes from.
COMPLETENESS_SOURCES = ("table", "artificial_stars")


@dataclass(frozen=True)
class DynamicsKnobs:
    """Accuracy and speed knobs of the dynamics stage (``[dynamics.knobs]``).

    None of them changes the models, priors or data, only how accurately and how fast
    the posteriors and evidences are computed (GalSim's GSParams pattern). They are
    also fields of :class:`DynamicsSettings` (``settings.walkers`` is
    ``settings.knobs.walkers``) and may be given as flat ``[dynamics]`` keys as before.

    Parameters
    ----------
    grid_size : int
        Output grid points in ln(R / a) of the Jeans model (>= 8).
    projection_panels, projection_nodes : int
        Gauss-Legendre panels and nodes per panel of the line-of-sight projection.
    radial_points_per_efold : int
        Radial grid of the Jeans integrals [points per unit ln r] (>= 4).
    truncation : float
        Outer truncation of the projection [scale radii] (>= 1e3).
    line_of_sight_nodes : int
        Gauss-Legendre depths per line of sight of the line-of-sight velocity mixture
        (>= 2; used with ``velocity_law = "line_of_sight"``).
    reweight : bool
        Nested sampling with the Gaussian law, its posterior draws importance-reweighted
        to the line-of-sight law (a direct run where the ratios' Pareto shape > 0.7).
    bin_size, n_bootstrap : int
        Stars per bin and bootstrap resamples of the binned dispersion profile.
    walkers, max_steps, check_every : int
        emcee walkers, step limit and steps between convergence checks.
    tau_factor : float
        Required emcee chain length [autocorrelation times].
    posterior : {"nested", "emcee"}
        Posterior from the nested-sampling run (default; no emcee), or from emcee (whose
        chains on the default four-model fit with free nuisances do not converge).
    nlive : int
        dynesty live points.
    dlogz : float
        dynesty stopping criterion on the remaining ln Z.
    walks : int
        dynesty random-walk steps per new live point, where dynesty walks (10-20
        parameters, its own choice of sampler); 0 (default): dynesty's ``ndim + 20``
        (31-35 for the four models with every nuisance fitted). Fewer steps make fewer
        likelihood calls but can miss a model's best region: with 25 the extended dark
        component's was missed on one matrix trial, a false ``imbh`` verdict
        (docs/dynamics.md, "Speed", "Faster free-kurtosis sums; fewer random-walk steps
        tried and refused").
    workers : int
        Models fitted in parallel processes (the result does not depend on it).
    """

    grid_size: int = 64
    projection_panels: int = 16
    projection_nodes: int = 6
    radial_points_per_efold: int = 24
    truncation: float = 1.0e4
    line_of_sight_nodes: int = 16
    reweight: bool = False
    bin_size: int = 300
    n_bootstrap: int = 200
    walkers: int = 32
    max_steps: int = 20000
    tau_factor: float = 50.0
    check_every: int = 500
    posterior: str = "nested"
    nlive: int = 250
    dlogz: float = 0.1
    walks: int = 0
    workers: int = 1


#: Knob -> its home before ``[dynamics.knobs]`` existed (a flat key of ``[dynamics]``).
DYNAMICS_KNOB_HOMES = {f.name: () for f in dataclasses.fields(DynamicsKnobs)}
_K = DynamicsKnobs


@dataclass(frozen=True)
class DynamicsSettings:
    """All knobs of the dynamics fit (see docs/dynamics.md for each key and its default).

    Tracer: ``tracer`` ("plummer", "dehnen", "king62"); with ``cusp`` (default) the
    tracer has a free inner cusp in every model: Plummer/King62 get
    ``(1 + (r_c/r)^2)^(gamma/2)`` (``gamma_range``, ``log_cusp_radius_range`` in log10
    arcsec), Dehnen a free inner slope; without it the Dehnen slope is ``dehnen_gamma``.
    ``king_concentration`` (King 1962 ``log10 r_t/r_c``). Mass: cluster (tracer shape,
    ``log_mass_range``) + point mass (``bh_mass_max``, uniform) + dark Plummer sphere
    (``dark_mass_max``, uniform; ``log_dark_radius_range`` log10 arcsec), combined per
    ``models``. ``anisotropy``: "general" (the default since 2026-12-05: ``beta_0`` in
    ``beta_range``, ``beta_inf`` in ``beta_inf_range``, ``r_a`` in
    ``log_anisotropy_radius_range``; holds the other two as special cases), "constant"
    (``beta_range``; the default before) or "osipkov-merritt"
    (``log_anisotropy_radius_range``, log10 arcsec). Nuisances: ``log_scale_radius_range``
    or ``log_scale_radius_prior`` (mean, sd; e.g. from the surface-brightness profile);
    ``distance`` [kpc] overrides the product's, ``distance_error`` [kpc] (None: 3 % of the
    distance; 0: fixed); ``centre_error`` [arcsec] and ``systemic_error`` [mas/yr]
    (Gaussian priors about 0; 0 fixes them). Data: ``field_radius``, ``min_radius``
    [arcsec], ``pm_error_scale``, ``pm_error_floor``, ``use_flagged``; ``star_counts``
    (the positional term), ``completeness_radius`` [arcsec] / ``completeness`` (tabulated
    completeness of the sample vs radius), ``completeness_source`` ("table": that table,
    flat without one; "artificial_stars": measured from the artificial-star (truth)
    catalogue of the run, :mod:`~mavispm.dynamics.completeness`, for the stars brighter
    than ``completeness_mag_limit`` [mag], default the faintest fitted star),
    ``kinematic_evidence`` (also the evidence
    without the star counts). Numerics: ``grid_size``, ``projection_panels``,
    ``projection_nodes``, ``radial_points_per_efold``, ``truncation``,
    ``line_of_sight_nodes``. Velocities: ``velocity_law`` ("weighed", the default since
    2026-12-04: each model is fitted with each law of ``compare_velocity_laws``, default
    "free_kurtosis" and "line_of_sight", its evidence is the laws' mean, equal prior odds
    per law, its posterior tables the law with the highest evidence and its M_BH marginal
    the evidence-weighted mixture over models and laws; needs ``evidence``;
    :func:`~mavispm.dynamics.fit.fit_models`; docs/dynamics.md, "Weighing the velocity
    laws by evidence"), or one law:
    "free_kurtosis" (the projected dispersions with a fitted excess kurtosis, uniform on
    ``kappa_range``, one value (``kappa_profile = "constant"``) or inner and outer values
    linear in ln R (``"radial"``), :mod:`~mavispm.dynamics.shape_law`; the default for a
    few hours of 2026-12-04); "gaussian": a Gaussian with the projected dispersions;
    "line_of_sight": each star's motion is the mixture over its depth of Gaussian 3-D
    velocities (the default before 2026-12-04: low on equilibrium velocities,
    docs/dynamics.md, "Calibration on equilibrium (DF) velocities");
    "line_of_sight_kurtosis": the line-of-sight mixture with each node's Gaussian replaced
    by that family, one fitted local ``kappa`` on ``kappa_range``, ``kappa_profile =
    "constant"`` only; :mod:`~mavispm.dynamics.line_of_sight_kurtosis`). Profile: ``bin_size``, ``n_bootstrap``. emcee:
    ``walkers``, ``max_steps``, ``tau_factor``, ``check_every``; ``posterior`` ("nested", the
    default: the posterior from the nested-sampling run, no emcee; or "emcee"). Evidence:
    ``evidence``, ``nlive``, ``dlogz``, ``walks``. Verdict: ``ambiguous_ln_b``. ``workers``: models
    fitted in parallel processes (1: in this process; the result does not depend on it).
    Fast-star test: ``fast_stars`` (a ``[dynamics.fast_stars]`` table,
    :class:`~mavispm.dynamics.fast_stars.FastStarSettings`; None = no test).
    """

    tracer: str = "plummer"
    cusp: bool = True
    dehnen_gamma: float = 1.0
    gamma_range: tuple[float, float] = (0.0, 2.0)
    log_cusp_radius_range: tuple[float, float] = (-1.0, 2.5)
    king_concentration: float = 1.5
    log_mass_range: tuple[float, float] = (3.0, 7.0)
    log_scale_radius_range: tuple[float, float] = (0.0, 3.0)
    log_scale_radius_prior: tuple[float, float] | None = None
    models: tuple[str, ...] = ("none", "imbh", "dark", "imbh_dark")
    bh_mass_max: float = unit_field(1.0e4, "solMass", "upper edge of the uniform M_bh prior")
    dark_mass_max: float = unit_field(2.0e4, "solMass", "upper edge of the uniform M_dark prior")
    log_dark_radius_range: tuple[float, float] = (-0.5, 1.5)
    anisotropy: str = "general"
    velocity_law: str = WEIGHED
    compare_velocity_laws: tuple[str, ...] = WEIGHED_LAWS
    kappa_range: tuple[float, float] = (-1.5, 2.5)
    kappa_profile: str = "constant"
    beta_range: tuple[float, float] = (-0.5, 0.5)
    log_anisotropy_radius_range: tuple[float, float] = (0.0, 3.0)
    beta_inf_range: tuple[float, float] = (-0.5, 0.95)
    distance: float | None = unit_field(None, "kpc", "overrides the product's distance")
    distance_error: float | None = unit_field(
        None, "kpc", "Gaussian prior width; None = 3% of the distance, 0 = fixed"
    )
    centre_error: float = unit_field(0.5, "arcsec", "Gaussian prior width of x0, y0; 0 = fixed")
    systemic_error: float = unit_field(
        0.05, "mas/yr", "Gaussian prior width of the mean motion; 0 = fixed at 0"
    )
    field_radius: float | None = unit_field(None, "arcsec", "circular field used")
    min_radius: float = unit_field(0.01, "arcsec", "radii are clipped to at least this")
    pm_error_scale: float = 1.0
    pm_error_floor: float = unit_field(0.0, "mas/yr", "added in quadrature to every PM error")
    use_flagged: bool = False
    star_counts: bool = True
    completeness_radius: tuple[float, ...] | None = None
    completeness: tuple[float, ...] | None = None
    completeness_source: str = "table"
    completeness_mag_limit: float | None = unit_field(
        None, "mag", "faintest magnitude of the tracer population (artificial stars)"
    )
    kinematic_evidence: bool = True
    ambiguous_ln_b: float = 1.0
    grid_size: int = _K.grid_size
    projection_panels: int = _K.projection_panels
    projection_nodes: int = _K.projection_nodes
    radial_points_per_efold: int = _K.radial_points_per_efold
    truncation: float = _K.truncation
    line_of_sight_nodes: int = _K.line_of_sight_nodes
    reweight: bool = _K.reweight
    bin_size: int = _K.bin_size
    n_bootstrap: int = _K.n_bootstrap
    walkers: int = _K.walkers
    max_steps: int = _K.max_steps
    tau_factor: float = _K.tau_factor
    check_every: int = _K.check_every
    posterior: str = _K.posterior
    evidence: bool = True
    nlive: int = _K.nlive
    dlogz: float = _K.dlogz
    walks: int = _K.walks
    progress: bool = True
    workers: int = _K.workers
    fast_stars: FastStarSettings | None = None

    def __post_init__(self):
        if self.tracer == "king":
            raise ValueError(
                "tracer 'king' was renamed 'king62' (King 1962 concentration law; the "
                "generator's King 1966 W0 model is a different profile)"
            )
        if self.tracer not in TRACERS:
            raise ValueError(f"tracer must be one of {sorted(TRACERS)}, got {self.tracer!r}")
        if self.posterior not in POSTERIORS:
            raise ValueError(f"posterior must be 'emcee' or 'nested', got {self.posterior!r}")
        if self.posterior == "nested" and not self.evidence:
            raise ValueError(
                "posterior = 'nested' (the default) needs evidence = true; set "
                "posterior = 'emcee' for a fit without nested sampling (no ln B)"
            )
        if self.velocity_law not in (WEIGHED, *VELOCITY_LAWS):
            raise ValueError(
                f"velocity_law must be one of {(WEIGHED, *VELOCITY_LAWS)}, "
                f"got {self.velocity_law!r}"
            )
        laws = tuple(self.compare_velocity_laws)
        object.__setattr__(self, "compare_velocity_laws", laws)
        for law in laws:
            if law not in VELOCITY_LAWS:
                raise ValueError(
                    f"compare_velocity_laws: each law must be one of {VELOCITY_LAWS}, got {law!r}"
                )
        if self.velocity_law == WEIGHED:
            if len(set(laws)) < 2:
                raise ValueError(
                    "compare_velocity_laws needs at least two different laws for velocity_law "
                    f"= 'weighed' (the default), got {laws}; set velocity_law to one law to "
                    "fit it alone"
                )
            if not self.evidence:
                raise ValueError(
                    "velocity_law = 'weighed' (the default) weighs the laws by their nested "
                    "evidences: it needs evidence = true; set velocity_law to one law (e.g. "
                    "'free_kurtosis') for a fit without evidence"
                )
        elif laws not in ((), WEIGHED_LAWS):
            raise ValueError(
                f"compare_velocity_laws {laws} is weighed with velocity_law = 'weighed' (the "
                f"default), got velocity_law = {self.velocity_law!r}: drop one of the two"
            )
        if self.kappa_profile not in KAPPA_PROFILES:
            raise ValueError(
                f"kappa_profile must be one of {KAPPA_PROFILES}, got {self.kappa_profile!r}"
            )
        if "line_of_sight_kurtosis" in self.laws and self.kappa_profile != "constant":
            raise ValueError(
                "velocity_law 'line_of_sight_kurtosis' fits one kappa: kappa_profile must be "
                f"'constant', got {self.kappa_profile!r}"
            )
        lo, hi = self.kappa_range
        if not (KAPPA_LIMITS[0] < lo < hi < KAPPA_LIMITS[1]):
            raise ValueError(
                f"kappa_range needs {KAPPA_LIMITS[0]} < lo < hi < {KAPPA_LIMITS[1]}, "
                f"got {self.kappa_range}"
            )
        if self.anisotropy not in ANISOTROPY:
            raise ValueError(f"anisotropy must be one of {ANISOTROPY}, got {self.anisotropy!r}")
        models = tuple(self.models)
        bad = [m for m in models if m not in MODELS]
        if bad or not models or len(set(models)) != len(models):
            raise ValueError(f"models must be distinct names from {sorted(MODELS)}, got {models}")
        object.__setattr__(self, "models", models)
        for name in (
            "gamma_range",
            "log_cusp_radius_range",
            "log_mass_range",
            "log_scale_radius_range",
            "beta_range",
            "log_dark_radius_range",
            "log_anisotropy_radius_range",
            "beta_inf_range",
        ):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"{name} needs lo < hi, got ({lo}, {hi})")
        if self.log_scale_radius_prior is not None:
            mean, sd = self.log_scale_radius_prior
            lo, hi = self.log_scale_radius_range
            if not (sd > 0 and lo <= mean - 5 * sd and mean + 5 * sd <= hi):
                raise ValueError(
                    "log_scale_radius_prior (mean, sd) needs sd > 0 and mean +- 5 sd inside "
                    f"log_scale_radius_range {self.log_scale_radius_range}, got ({mean}, {sd})"
                )
        if not self.beta_range[1] < 1.0:
            raise ValueError("beta_range must stay below 1")
        if not self.beta_inf_range[1] <= 1.0:
            raise ValueError("beta_inf_range must stay at or below 1")
        if not (0.0 <= self.gamma_range[0] and self.gamma_range[1] < 2.5):
            raise ValueError("gamma_range must lie in [0, 2.5)")
        if self.completeness_source not in COMPLETENESS_SOURCES:
            raise ValueError(
                f"completeness_source must be one of {COMPLETENESS_SOURCES}, got "
                f"{self.completeness_source!r}"
            )
        if self.completeness_source == "artificial_stars" and self.completeness is not None:
            raise ValueError(
                "completeness_source = 'artificial_stars' measures the completeness: "
                "drop completeness_radius / completeness (or use completeness_source = 'table')"
            )
        if (self.completeness_radius is None) != (self.completeness is None):
            raise ValueError("completeness_radius and completeness go together")
        if self.completeness is not None:
            r, c = self.completeness_radius, self.completeness
            if len(r) != len(c) or len(r) < 2 or any(b <= a for a, b in zip(r, r[1:])):
                raise ValueError(
                    "completeness_radius must increase, with one completeness value each (>= 2)"
                )
            if not all(0.0 < v <= 1.0 for v in c) or r[0] < 0:
                raise ValueError("completeness values must be in (0, 1] at radii >= 0")
        positive = {
            "bh_mass_max": self.bh_mass_max,
            "dark_mass_max": self.dark_mass_max,
            "min_radius": self.min_radius,
            "bin_size": self.bin_size - 1,
            "grid_size": self.grid_size - 7,
            "projection_panels": self.projection_panels,
            "projection_nodes": self.projection_nodes,
            "line_of_sight_nodes": self.line_of_sight_nodes - 1,
            "radial_points_per_efold": self.radial_points_per_efold - 3,
            "walkers": self.walkers,
            "max_steps": self.max_steps,
            "tau_factor": self.tau_factor,
            "check_every": self.check_every,
            "nlive": self.nlive,
            "dlogz": self.dlogz,
            "ambiguous_ln_b": self.ambiguous_ln_b,
            "workers": self.workers,
        }
        for name, val in positive.items():
            if not val > 0:
                raise ValueError(f"{name} is too small: {getattr(self, name)}")
        if isinstance(self.walks, bool) or not isinstance(self.walks, int) or self.walks < 0:
            raise ValueError(
                f"walks must be an integer >= 0 (0: dynesty's ndim + 20), got {self.walks!r}"
            )
        if self.truncation < 1e3:
            raise ValueError(f"truncation must be >= 1e3 scale radii, got {self.truncation}")
        if self.distance_error is not None and self.distance_error < 0:
            raise ValueError("distance_error must be >= 0 (0 = fixed distance)")
        if self.distance is not None and self.distance <= 0:
            raise ValueError("distance must be > 0")
        if self.centre_error < 0 or self.systemic_error < 0:
            raise ValueError("centre_error and systemic_error must be >= 0 (0 = fixed)")
        if not (self.pm_error_scale > 0 and self.pm_error_floor >= 0):
            raise ValueError("pm_error_scale must be > 0 and pm_error_floor >= 0")
        if self.field_radius is not None and self.field_radius <= 0:
            raise ValueError("field_radius must be > 0")

    @property
    def laws(self) -> tuple[str, ...]:
        """The velocity laws fitted: ``compare_velocity_laws`` when ``velocity_law`` is
        "weighed", else ``velocity_law`` alone."""
        return self.compare_velocity_laws if self.velocity_law == WEIGHED else (self.velocity_law,)

    def distance_sd(self, distance: float) -> float:
        """Gaussian prior width of the distance [kpc] (0: fixed)."""
        return 0.03 * distance if self.distance_error is None else float(self.distance_error)

    @property
    def knobs(self) -> DynamicsKnobs:
        """The accuracy and speed knobs of these settings (:class:`DynamicsKnobs`)."""
        return DynamicsKnobs(**{name: getattr(self, name) for name in DYNAMICS_KNOB_HOMES})

    def fast(self) -> DynamicsSettings:
        """Cheaper sampler settings for tests and quick looks (--fast)."""
        return dataclasses.replace(
            self,
            walkers=max(self.walkers, 32),
            max_steps=min(self.max_steps, 3000),
            tau_factor=min(self.tau_factor, 20.0),
            check_every=250,
            nlive=min(self.nlive, 100),
            dlogz=max(self.dlogz, 0.5),
            n_bootstrap=min(self.n_bootstrap, 50),
        )
