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
from numpy.typing import ArrayLike
from scipy.special import ndtri

__all__ = [
    "Parameter",
    "ParameterSpace",
]


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

    def from_scaled(self, z: ArrayLike):
        """Physical value from the order-unity scaled value.

        Uniform prior: ``z`` in [-1, 1] maps to [lo, hi]; Gaussian: ``mean + sd z``.

        Parameters
        ----------
        z : array_like
            Scaled value(s).

        Returns
        -------
        ndarray or float
            Physical value(s), in the parameter's unit.
        """
        if self.prior == "uniform":
            return 0.5 * (self.hi + self.lo) + 0.5 * (self.hi - self.lo) * z
        return self.mean + self.sd * z

    def to_scaled(self, v: ArrayLike):
        """Order-unity scaled value from the physical value.

        Parameters
        ----------
        v : array_like
            Physical value(s), in the parameter's unit.

        Returns
        -------
        ndarray or float
            Scaled value(s) (inverse of :meth:`from_scaled`).
        """
        if self.prior == "uniform":
            return (v - 0.5 * (self.hi + self.lo)) / (0.5 * (self.hi - self.lo))
        return (v - self.mean) / self.sd

    def log_prior_scaled(self, z: ArrayLike):
        """Log prior density in the scaled space (-inf outside the support).

        Parameters
        ----------
        z : array_like
            Scaled value(s).

        Returns
        -------
        ndarray or float
            ``ln(1/2)`` inside [-1, 1] for a uniform prior; the standard normal log density for a
            Gaussian.
        """
        if self.prior == "uniform":
            return np.where(np.abs(z) <= 1.0, -np.log(2.0), -np.inf)
        return -0.5 * z * z - 0.5 * np.log(2 * np.pi)

    def from_unit(self, q: ArrayLike):
        """Physical value from the unit cube (dynesty prior transform).

        Parameters
        ----------
        q : array_like
            Value(s) in [0, 1].

        Returns
        -------
        ndarray or float
            Physical value(s): ``lo + (hi - lo) q`` or the Gaussian quantile.
        """
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
        # the unit-cube transform, vectorised (dynesty calls it once per proposal)
        self._gauss = np.array([p.prior == "gaussian" for p in self.params], dtype=bool)
        self._lo = np.array([p.lo for p in self.params], dtype=float)
        self._span = np.array([p.hi - p.lo for p in self.params], dtype=float)
        self._mean = np.array([p.mean for p in self.params], dtype=float)[self._gauss]
        self._sd = np.array([p.sd for p in self.params], dtype=float)[self._gauss]

    def __len__(self):
        return len(self.params)

    def index(self, name: str) -> int:
        """Position of parameter ``name``.

        Parameters
        ----------
        name : str
            Parameter name.

        Returns
        -------
        int
            Its index in the parameter vector.

        Raises
        ------
        ValueError
            When the model has no such parameter.
        """
        return self.names.index(name)

    def from_scaled(self, z: ArrayLike):
        """Physical vector(s) from scaled vector(s) (last axis = parameters).

        Parameters
        ----------
        z : array_like, shape (..., n_params)
            Scaled vector(s).

        Returns
        -------
        ndarray, shape (..., n_params)
            Physical vector(s).
        """
        z = np.asarray(z, dtype=float)
        return np.stack([p.from_scaled(z[..., i]) for i, p in enumerate(self.params)], axis=-1)

    def to_scaled(self, v: ArrayLike):
        """Scaled vector(s) from physical vector(s).

        Parameters
        ----------
        v : array_like, shape (..., n_params)
            Physical vector(s).

        Returns
        -------
        ndarray, shape (..., n_params)
            Scaled vector(s).
        """
        v = np.asarray(v, dtype=float)
        return np.stack([p.to_scaled(v[..., i]) for i, p in enumerate(self.params)], axis=-1)

    def log_prior_scaled(self, z: ArrayLike) -> float:
        """Sum of the log prior densities of a scaled vector.

        Parameters
        ----------
        z : array_like, shape (n_params,)
            Scaled vector.

        Returns
        -------
        float
            Log prior density (-inf outside the support).
        """
        return float(sum(p.log_prior_scaled(z[i]) for i, p in enumerate(self.params)))

    def from_unit(self, q: ArrayLike):
        """Physical vector from a unit-cube vector (dynesty).

        Parameters
        ----------
        q : array_like, shape (n_params,)
            Unit-cube vector.

        Returns
        -------
        ndarray, shape (n_params,)
            Physical vector.
        """
        q = np.asarray(q, dtype=float)
        out = self._lo + self._span * q  # Parameter.from_unit, element by element
        if self._mean.size:
            out[self._gauss] = self._mean + self._sd * ndtri(q[self._gauss])
        return out

    def as_dict(self, v: ArrayLike) -> dict:
        """Physical vector as {name: value}.

        Parameters
        ----------
        v : array_like, shape (n_params,)
            Physical vector.

        Returns
        -------
        dict of str to float
            Parameter name to value.
        """
        return {n: float(x) for n, x in zip(self.names, v)}
