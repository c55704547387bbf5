"""Model parameters, their priors and the order-unity scaling used by the samplers.

Each :class:`Parameter` has a prior (uniform, uniform in log10, or Gaussian)
and maps between three spaces:

* physical value (what the likelihood uses; units in the name),
* scaled value ``z`` of order unity, sampled by emcee: uniform priors map to
  [-1, 1], Gaussian priors to ``(v - mean) / sd``,
* the unit cube ``q`` in [0, 1] used by dynesty's prior transform.

The log-prior density is expressed in ``z`` so emcee and dynesty sample the
same posterior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri


@dataclass(frozen=True)
class Parameter:
    """One model parameter.

    Parameters
    ----------
    name : str
        Name (with unit, e.g. ``bh_mass`` in solMass, ``log_scale_radius`` in log10 arcsec).
    prior : {"uniform", "gaussian"}
        Uniform on [lo, hi] or Gaussian (mean, sd).
    lo, hi : float
        Uniform prior bounds.
    mean, sd : float
        Gaussian prior.
    label : str
        Plot label.
    """

    name: str
    prior: str = "uniform"
    lo: float = 0.0
    hi: float = 1.0
    mean: float = 0.0
    sd: float = 1.0
    label: str = ""

    def __post_init__(self):
        if self.prior == "uniform" and not self.hi > self.lo:
            raise ValueError(
                f"parameter {self.name}: prior needs hi > lo, got {self.lo}, {self.hi}"
            )
        if self.prior == "gaussian" and not self.sd > 0:
            raise ValueError(f"parameter {self.name}: Gaussian prior needs sd > 0")
        if self.prior not in ("uniform", "gaussian"):
            raise ValueError(f"parameter {self.name}: unknown prior {self.prior!r}")

    def from_scaled(self, z):
        """Physical value from the order-unity scaled value."""
        if self.prior == "uniform":
            return 0.5 * (self.hi + self.lo) + 0.5 * (self.hi - self.lo) * z
        return self.mean + self.sd * z

    def to_scaled(self, v):
        """Order-unity scaled value from the physical value."""
        if self.prior == "uniform":
            return (v - 0.5 * (self.hi + self.lo)) / (0.5 * (self.hi - self.lo))
        return (v - self.mean) / self.sd

    def log_prior_scaled(self, z):
        """Log prior density in the scaled space (-inf outside the support)."""
        if self.prior == "uniform":
            return np.where(np.abs(z) <= 1.0, -np.log(2.0), -np.inf)
        return -0.5 * z * z - 0.5 * np.log(2 * np.pi)

    def from_unit(self, q):
        """Physical value from the unit cube (dynesty prior transform)."""
        if self.prior == "uniform":
            return self.lo + (self.hi - self.lo) * q
        return self.mean + self.sd * ndtri(q)


class ParameterSpace:
    """An ordered set of parameters.

    Parameters
    ----------
    params : sequence of Parameter
    """

    def __init__(self, params):
        self.params = list(params)
        self.names = [p.name for p in self.params]

    def __len__(self):
        return len(self.params)

    def index(self, name: str) -> int:
        """Position of parameter ``name``."""
        return self.names.index(name)

    def from_scaled(self, z):
        """Physical vector(s) from scaled vector(s) (last axis = parameters)."""
        z = np.asarray(z, dtype=float)
        return np.stack([p.from_scaled(z[..., i]) for i, p in enumerate(self.params)], axis=-1)

    def to_scaled(self, v):
        """Scaled vector(s) from physical vector(s)."""
        v = np.asarray(v, dtype=float)
        return np.stack([p.to_scaled(v[..., i]) for i, p in enumerate(self.params)], axis=-1)

    def log_prior_scaled(self, z) -> float:
        """Sum of the log prior densities of a scaled vector."""
        return float(sum(p.log_prior_scaled(z[i]) for i, p in enumerate(self.params)))

    def from_unit(self, q):
        """Physical vector from a unit-cube vector (dynesty)."""
        return np.array([p.from_unit(q[i]) for i, p in enumerate(self.params)])

    def as_dict(self, v) -> dict:
        """Physical vector as {name: value}."""
        return {n: float(x) for n, x in zip(self.names, v)}
