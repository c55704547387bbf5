"""Velocity anisotropy profiles ``beta(r) = 1 - sigma_t^2 / sigma_r^2`` for the Jeans equation.

One family covers both models of the fit:

    beta(r) = beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2)

* constant anisotropy: ``beta_0 = beta_inf = beta`` (``r_a`` irrelevant);
* Osipkov (1979) - Merritt (1985): ``beta_0 = 0``, ``beta_inf = 1`` -- isotropic
  inside the anisotropy radius ``r_a``, radial outside.

The Jeans equation ``d(nu sigma_r^2)/dr + 2 beta nu sigma_r^2 / r = -nu G M / r^2``
has the integrating factor

    g(r) = exp(int 2 beta / r dr) = r^(2 beta_0) (r^2 + r_a^2)^(beta_inf - beta_0),

so that ``nu sigma_r^2 (r) = g(r)^-1 int_r^inf g nu G M / r'^2 dr'``.
Radii are in units of the tracer scale radius.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "Anisotropy",
    "constant",
    "osipkov_merritt",
]


@dataclass(frozen=True)
class Anisotropy:
    """``beta(r) = beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2)``.

    Parameters
    ----------
    beta_0, beta_inf : float
        Central and outer anisotropy (both < 1).
    r_a : float
        Anisotropy radius in scale radii (> 0; unused when ``beta_0 == beta_inf``).
    """

    beta_0: float = 0.0
    beta_inf: float = 0.0
    r_a: float = 1.0

    def __post_init__(self):
        if not (self.beta_0 < 1.0 and self.beta_inf <= 1.0 and self.r_a > 0):
            raise ValueError(
                f"anisotropy needs beta_0 < 1, beta_inf <= 1 and r_a > 0, got "
                f"{self.beta_0}, {self.beta_inf}, {self.r_a}"
            )

    @property
    def constant(self) -> bool:
        """Whether beta does not depend on radius."""
        return self.beta_0 == self.beta_inf

    def beta(self, r: ArrayLike):
        """``beta(r)``.

        Parameters
        ----------
        r : array_like
            Radii [scale radii].

        Returns
        -------
        ndarray
            Anisotropy (dimensionless, < 1).
        """
        r2 = np.asarray(r, dtype=float) ** 2
        if self.constant:
            return np.full_like(r2, self.beta_0)
        return self.beta_0 + (self.beta_inf - self.beta_0) * r2 / (r2 + self.r_a**2)

    def ln_factor(self, ln_r: ArrayLike):
        """``ln g(r)`` of the integrating factor at ``ln r``.

        ``g(r) = r^(2 beta_0) (r^2 + r_a^2)^(beta_inf - beta_0)``, the solution of
        ``d ln g / d ln r = 2 beta(r)``.

        Parameters
        ----------
        ln_r : array_like
            Natural log of the radius [scale radii].

        Returns
        -------
        ndarray
            ``ln g``.
        """
        ln_r = np.asarray(ln_r, dtype=float)
        out = 2.0 * self.beta_0 * ln_r
        if not self.constant:
            out = out + (self.beta_inf - self.beta_0) * np.logaddexp(
                2.0 * ln_r, 2.0 * np.log(self.r_a)
            )
        return out

    def tail(self, x_max: float, outer_slope: float) -> float:
        """``int_{x_max}^inf g(r) (r / x_max)^-n r^-2 dr`` for ``nu ~ r^-n`` beyond ``x_max``.

        Exact for constant beta; for a radius-dependent beta, ``g`` is taken as the
        power law ``g(x_max) (r / x_max)^(2 beta_inf)`` (relative error ``~ (r_a /
        x_max)^2``, negligible for ``r_a << x_max``). Zero for a truncated profile.

        Parameters
        ----------
        x_max : float
            Radius where the tail starts [scale radii].
        outer_slope : float
            Outer logarithmic density slope ``n`` (inf: truncated profile).

        Returns
        -------
        float
            The integral (in units of the scale radius, G = M = 1).

        Raises
        ------
        ValueError
            When ``n + 1 - 2 beta_inf <= 0`` (the integral diverges).
        """
        n = outer_slope
        if not np.isfinite(n):
            return 0.0
        slope = 2.0 * self.beta_inf
        if not n + 1.0 - slope > 0:
            raise ValueError(f"outer density slope {n} too shallow for beta_inf {self.beta_inf}")
        g_end = float(np.exp(self.ln_factor(np.log(x_max))))
        return g_end / x_max / (n + 1.0 - slope)


def constant(beta: float) -> Anisotropy:
    """Constant anisotropy ``beta`` (< 1).

    Parameters
    ----------
    beta : float
        The anisotropy.

    Returns
    -------
    Anisotropy
        ``beta_0 = beta_inf = beta``.
    """
    return Anisotropy(beta, beta, 1.0)


def osipkov_merritt(r_a: float) -> Anisotropy:
    """Osipkov-Merritt anisotropy, isotropic inside ``r_a`` and radial outside.

    Parameters
    ----------
    r_a : float
        Anisotropy radius [scale radii] (> 0).

    Returns
    -------
    Anisotropy
        ``beta(r) = r^2 / (r^2 + r_a^2)``.
    """
    return Anisotropy(0.0, 1.0, r_a)
