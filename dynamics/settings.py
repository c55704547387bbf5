"""Settings of the dynamics stage (one frozen dataclass, GSParams style).

Build with :func:`mavispm.dynamics.cli.validate_settings` (TOML table
``[dynamics]``); every key is documented in ``docs/dynamics.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from mavispm.core.config import unit_field
from mavispm.dynamics.fast_stars import FastStarSettings
from mavispm.dynamics.tracers import TRACERS


@dataclass(frozen=True)
class DynamicsSettings:
    """All knobs of the dynamics fit.

    Model: ``tracer`` ("plummer", "dehnen", "king62"), ``dehnen_gamma`` (fixed
    inner slope) or ``fit_gamma`` with ``gamma_range``; ``king_concentration``;
    ``cusp`` gives a Plummer/King62 an inner cusp ``(1 + (r_c/r)^2)^(gamma/2)`` with
    fitted ``gamma`` (``gamma_range``) and ``log_cusp_radius`` (``log_cusp_radius_range``,
    log10 arcsec), or with ``cusp_link = "influence"`` the cusp radius is the BH
    influence radius (no cusp without a BH).
    Priors: ``log_mass_range`` (log10 solMass), ``log_scale_radius_range`` (log10
    arcsec; with ``log_scale_radius_prior = (mean, sd)`` a Gaussian prior inside it,
    e.g. from the cluster's surface-brightness profile), ``bh_mass_max`` (uniform on [0, max], solMass), ``beta_range``;
    ``distance`` [kpc] overrides the product's, ``distance_error`` [kpc] > 0 makes it
    a Gaussian-prior parameter. Data: ``field_radius`` [arcsec] (default: the
    largest circle inside the data's x/y extent), ``min_radius`` [arcsec] (R
    floor), ``pm_error_scale`` and ``pm_error_floor`` [mas/yr] (errors become
    ``sqrt((scale e)^2 + floor^2)``), ``use_flagged``, ``star_counts``. Numerics: ``grid_size``,
    ``projection_panels``, ``projection_nodes``, ``truncation`` (scale radii).
    Profile: ``bin_size``, ``n_bootstrap``. emcee: ``walkers``, ``max_steps``,
    ``tau_factor``, ``check_every``. Evidence: ``evidence``, ``nlive``, ``dlogz``.
    Fast-star test: ``fast_stars`` (a ``[dynamics.fast_stars]`` table,
    :class:`~mavispm.dynamics.fast_stars.FastStarSettings`; None = no test).
    """

    tracer: str = "plummer"
    dehnen_gamma: float = 1.0
    fit_gamma: bool = False
    gamma_range: tuple[float, float] = (0.0, 2.0)
    king_concentration: float = 1.5
    cusp: bool = False
    cusp_link: str = "free"
    log_cusp_radius_range: tuple[float, float] = (0.0, 2.5)
    log_mass_range: tuple[float, float] = (3.0, 7.0)
    log_scale_radius_range: tuple[float, float] = (0.0, 3.0)
    log_scale_radius_prior: tuple[float, float] | None = None
    bh_mass_max: float = unit_field(1.0e4, "solMass", "upper edge of the uniform M_bh prior")
    beta_range: tuple[float, float] = (-0.5, 0.5)
    distance: float | None = unit_field(None, "kpc", "overrides the product's distance")
    distance_error: float = unit_field(0.0, "kpc", "Gaussian prior width; 0 = fixed")
    field_radius: float | None = unit_field(None, "arcsec", "circular field used")
    min_radius: float = unit_field(0.01, "arcsec", "radii are clipped to at least this")
    pm_error_scale: float = 1.0
    pm_error_floor: float = unit_field(0.0, "mas/yr", "added in quadrature to every PM error")
    use_flagged: bool = False
    star_counts: bool = True
    grid_size: int = 64
    projection_panels: int = 16
    projection_nodes: int = 6
    truncation: float = 1.0e4
    bin_size: int = 300
    n_bootstrap: int = 200
    walkers: int = 32
    max_steps: int = 20000
    tau_factor: float = 50.0
    check_every: int = 500
    evidence: bool = True
    nlive: int = 250
    dlogz: float = 0.1
    progress: bool = True
    fast_stars: FastStarSettings | None = None

    def __post_init__(self):
        if self.tracer not in TRACERS:
            raise ValueError(f"tracer must be one of {sorted(TRACERS)}, got {self.tracer!r}")
        if self.fit_gamma and self.tracer != "dehnen":
            raise ValueError("fit_gamma needs tracer = 'dehnen'")
        if self.cusp and self.tracer == "dehnen":
            raise ValueError("cusp needs tracer = 'plummer' or 'king' (Dehnen has gamma)")
        if self.cusp_link not in ("free", "influence"):
            raise ValueError(f"cusp_link must be 'free' or 'influence', got {self.cusp_link!r}")
        for name in (
            "gamma_range",
            "log_cusp_radius_range",
            "log_mass_range",
            "log_scale_radius_range",
            "beta_range",
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
        if not (0.0 <= self.gamma_range[0] and self.gamma_range[1] < 2.5):
            raise ValueError("gamma_range must lie in [0, 2.5)")
        positive = {
            "bh_mass_max": self.bh_mass_max,
            "min_radius": self.min_radius,
            "bin_size": self.bin_size - 1,
            "grid_size": self.grid_size - 7,
            "projection_panels": self.projection_panels,
            "projection_nodes": self.projection_nodes,
            "walkers": self.walkers,
            "max_steps": self.max_steps,
            "tau_factor": self.tau_factor,
            "check_every": self.check_every,
            "nlive": self.nlive,
            "dlogz": self.dlogz,
        }
        for name, val in positive.items():
            if not val > 0:
                raise ValueError(f"{name} is too small: {getattr(self, name)}")
        if self.truncation < 1e3:
            raise ValueError(f"truncation must be >= 1e3 scale radii, got {self.truncation}")
        if self.distance_error < 0 or (self.distance is not None and self.distance <= 0):
            raise ValueError("distance must be > 0 and distance_error >= 0")
        if not (self.pm_error_scale > 0 and self.pm_error_floor >= 0):
            raise ValueError("pm_error_scale must be > 0 and pm_error_floor >= 0")
        if self.field_radius is not None and self.field_radius <= 0:
            raise ValueError("field_radius must be > 0")

    def fast(self) -> DynamicsSettings:
        """Cheaper sampler settings for tests and quick looks (--fast)."""
        return dataclasses.replace(
            self,
            walkers=24,
            max_steps=min(self.max_steps, 2500),
            tau_factor=min(self.tau_factor, 20.0),
            check_every=250,
            nlive=min(self.nlive, 100),
            dlogz=max(self.dlogz, 0.5),
            n_bootstrap=min(self.n_bootstrap, 50),
        )
