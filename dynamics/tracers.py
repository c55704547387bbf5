"""Tracer (and mass) density profiles in units of the scale radius.

Every profile is dimensionless: radii ``x = r / a`` in units of the scale
radius ``a``, densities normalised to unit total mass, so that a cluster of
mass ``M`` and scale radius ``a`` has ``rho(r) = M / a**3 * density(r / a)``.
The Jeans model assumes mass follows light: the same profile describes the
tracer stars and the cluster mass (plus an optional central point mass).

Profiles
--------
Plummer
    ``nu = 3 / (4 pi) (1 + x^2)^(-5/2)``; everything analytic.
Dehnen (gamma)
    ``nu = (3 - gamma) / (4 pi) x^-gamma (1 + x)^(gamma - 4)``: an inner cusp of
    slope ``gamma`` (N-body clusters with an IMBH have gamma ~ 1.55 inside the
    influence radius) turning over to ``x^-4`` outside ``a``. The surface density
    has no elementary closed form and is projected numerically by the Jeans
    projector.
King (1962), concentration ``c = log10(r_t / r_c)``
    Analytic surface density and 3-D density, truncated at ``x_t = 10**c``; the
    enclosed mass is tabulated once per concentration (cached).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

_FOUR_PI = 4.0 * np.pi


@dataclass(frozen=True)
class Plummer:
    """Plummer (1911) sphere with unit mass and unit scale radius."""

    name = "plummer"
    #: logarithmic outer slope of the density (nu ~ x**-outer_slope)
    outer_slope = 5.0

    def density(self, x):
        """3-D density ``nu(x)`` (unit mass, unit scale radius)."""
        x = np.asarray(x, dtype=float)
        return 3.0 / _FOUR_PI * (1.0 + x * x) ** -2.5

    def enclosed(self, x):
        """Mass fraction inside 3-D radius ``x``."""
        x = np.asarray(x, dtype=float)
        return x**3 * (1.0 + x * x) ** -1.5

    def surface_density(self, X):
        """Projected density ``Sigma(X)`` (unit mass, per unit area in a**2)."""
        X = np.asarray(X, dtype=float)
        return 1.0 / np.pi * (1.0 + X * X) ** -2

    def projected_enclosed(self, X):
        """Mass fraction inside projected radius ``X``."""
        X = np.asarray(X, dtype=float)
        return X * X / (1.0 + X * X)


@dataclass(frozen=True)
class Dehnen:
    """Dehnen (1993) profile with inner slope ``gamma`` in [0, 2.5].

    Parameters
    ----------
    gamma : float
        Inner logarithmic density slope (0 core, 1 Hernquist, 1.55 IMBH cusp).
    """

    gamma: float = 1.0
    name = "dehnen"
    outer_slope = 4.0

    def __post_init__(self):
        if not (0.0 <= self.gamma < 2.5):
            raise ValueError(f"Dehnen gamma must be in [0, 2.5), got {self.gamma}")

    def density(self, x):
        """3-D density ``nu(x)`` (unit mass, unit scale radius)."""
        x = np.asarray(x, dtype=float)
        g = self.gamma
        return (3.0 - g) / _FOUR_PI * x**-g * (1.0 + x) ** (g - 4.0)

    def enclosed(self, x):
        """Mass fraction inside 3-D radius ``x``."""
        x = np.asarray(x, dtype=float)
        return (x / (1.0 + x)) ** (3.0 - self.gamma)

    # surface density and projected mass: numerical (see jeans.JeansProjector)
    surface_density = None
    projected_enclosed = None


@dataclass(frozen=True)
class King:
    """King (1962) profile with core radius 1 and concentration ``c``.

    Parameters
    ----------
    concentration : float
        ``log10(r_t / r_c)``, in (0.3, 3].
    """

    concentration: float = 1.5
    name = "king"
    outer_slope = np.inf  # truncated: no density beyond the tidal radius

    def __post_init__(self):
        if not (0.3 < self.concentration <= 3.0):
            raise ValueError(f"King concentration must be in (0.3, 3], got {self.concentration}")

    @property
    def tidal_radius(self) -> float:
        """Truncation radius in core radii."""
        return 10.0**self.concentration

    def _raw_density(self, x):
        xt = self.tidal_radius
        z2 = (1.0 + np.asarray(x, dtype=float) ** 2) / (1.0 + xt * xt)
        inside = z2 < 1.0
        z2c = np.where(inside, z2, 0.5)
        z = np.sqrt(z2c)
        val = (np.arccos(z) / z - np.sqrt(1.0 - z2c)) / z2c
        return np.where(inside, val, 0.0)

    def density(self, x):
        """3-D density ``nu(x)`` (unit mass, unit core radius)."""
        return self._raw_density(x) / _king_table(self.concentration)[2]

    def enclosed(self, x):
        """Mass fraction inside 3-D radius ``x`` (tabulated, cached)."""
        lx, lm, _ = _king_table(self.concentration)
        x = np.asarray(x, dtype=float)
        with np.errstate(divide="ignore"):
            lnx = np.log(np.maximum(x, 1e-300))
        out = np.exp(np.interp(lnx, lx, lm, left=-np.inf, right=0.0))
        small = lnx < lx[0]  # central density is flat: m ~ x^3
        return np.where(small, np.exp(lm[0] + 3.0 * (lnx - lx[0])), out)

    def surface_density(self, X):
        """Projected density (unit mass), zero beyond the tidal radius."""
        X = np.asarray(X, dtype=float)
        c = 1.0 / np.sqrt(1.0 + self.tidal_radius**2)
        shape = np.where(X < self.tidal_radius, (1.0 / np.sqrt(1.0 + X * X) - c) ** 2, 0.0)
        return shape / self._projected_raw(self.tidal_radius)

    def _projected_raw(self, X):
        X = np.minimum(np.asarray(X, dtype=float), self.tidal_radius)
        c = 1.0 / np.sqrt(1.0 + self.tidal_radius**2)
        q = 1.0 + X * X
        return np.pi * (np.log(q) - 4.0 * c * (np.sqrt(q) - 1.0) + c * c * (q - 1.0))

    def projected_enclosed(self, X):
        """Mass fraction inside projected radius ``X``."""
        return self._projected_raw(X) / self._projected_raw(self.tidal_radius)


@functools.lru_cache(maxsize=16)
def _king_table(concentration: float):
    """ln x, ln m(x) on a fine grid and the density normalisation (cached)."""
    king = King.__new__(King)
    object.__setattr__(king, "concentration", concentration)
    xt = 10.0**concentration
    # Gauss-Legendre panels in ln x (interior), plus the tidal radius
    edges = np.linspace(np.log(1e-4), np.log(xt), 2001)
    nodes, weights = np.polynomial.legendre.leggauss(6)
    mid = 0.5 * (edges[1:] + edges[:-1])
    half = 0.5 * np.diff(edges)
    lnx = (mid[:, None] + half[:, None] * nodes[None, :]).ravel()
    w = (half[:, None] * weights[None, :]).ravel()
    x = np.exp(lnx)
    f = _FOUR_PI * x**3 * king._raw_density(x) * w
    # mass inside 1e-4 from the flat core: 4/3 pi x^3 nu(0)
    m0 = _FOUR_PI / 3.0 * 1e-12 * float(king._raw_density(0.0))
    cum = m0 + np.cumsum(f.reshape(-1, 6).sum(axis=1))
    total = cum[-1]
    return edges, np.log(np.concatenate([[m0], cum]) / total), total


@dataclass(frozen=True)
class Cusped:
    """A cored profile with an inner cusp: ``nu ~ base(x) (1 + (x_c / x)^2)^(gamma / 2)``.

    The same multiplier as the cluster generator's cusp: ``nu ~ x^-gamma`` inside
    ``x_c`` and the base profile (King core, Plummer) outside it. Renormalised to
    unit mass; the enclosed mass is integrated numerically per instance
    (Gauss-Legendre panels in ``ln x``, analytic power law inside ``1e-8``).

    Parameters
    ----------
    base : Plummer or King
        Cored profile (unit mass, unit scale radius).
    gamma : float
        Inner slope in [0, 2.5).
    cusp_radius : float
        ``x_c`` in scale radii (> 0).
    """

    base: Plummer | King = Plummer()
    gamma: float = 1.55
    cusp_radius: float = 0.5
    name = "cusped"

    def __post_init__(self):
        if not (0.0 <= self.gamma < 2.5 and self.cusp_radius > 0):
            raise ValueError(
                f"cusp needs gamma in [0, 2.5) and cusp radius > 0, got "
                f"{self.gamma}, {self.cusp_radius}"
            )

    @property
    def outer_slope(self):
        """Outer slope of the base profile (the multiplier tends to 1)."""
        return self.base.outer_slope

    def _shape(self, x):
        x = np.maximum(np.asarray(x, dtype=float), 1e-300)
        return self.base.density(x) * (1.0 + (self.cusp_radius / x) ** 2) ** (0.5 * self.gamma)

    @functools.cached_property
    def _table(self):
        x_hi = getattr(self.base, "tidal_radius", 1e5)
        edges = np.linspace(np.log(1e-8), np.log(x_hi), 801)
        nodes, weights = np.polynomial.legendre.leggauss(4)
        mid = 0.5 * (edges[1:] + edges[:-1])
        half = 0.5 * np.diff(edges)
        x = np.exp((mid[:, None] + half[:, None] * nodes[None, :]).ravel())
        f = _FOUR_PI * x**3 * self._shape(x) * (half[:, None] * weights[None, :]).ravel()
        g = self.gamma
        m0 = _FOUR_PI * float(self.base.density(0.0)) * self.cusp_radius**g * 1e-8 ** (3.0 - g)
        cum = np.concatenate(
            [[m0 / (3.0 - g)], m0 / (3.0 - g) + np.cumsum(f.reshape(-1, 4).sum(1))]
        )
        total = cum[-1] + (1.0 - float(self.base.enclosed(x_hi)))  # multiplier ~ 1 beyond x_hi
        return edges, cum, total, x_hi

    def density(self, x):
        """3-D density ``nu(x)`` (unit mass, unit scale radius)."""
        return self._shape(x) / self._table[2]

    def enclosed(self, x):
        """Mass fraction inside 3-D radius ``x``."""
        edges, cum, total, x_hi = self._table
        x = np.asarray(x, dtype=float)
        lnx = np.log(np.maximum(x, 1e-300))
        inside = np.exp(np.interp(lnx, edges, np.log(cum)))
        small = cum[0] * np.exp((3.0 - self.gamma) * (lnx - edges[0]))
        outside = cum[-1] + self.base.enclosed(np.maximum(x, x_hi)) - self.base.enclosed(x_hi)
        out = np.where(lnx < edges[0], small, np.where(x > x_hi, outside, inside))
        return np.minimum(out / total, 1.0)

    surface_density = None
    projected_enclosed = None


#: Known tracer profiles by name (for settings).
TRACERS = {"plummer": Plummer, "dehnen": Dehnen, "king": King}


def make_tracer(
    name: str, gamma: float = 1.0, concentration: float = 1.5, cusp_radius: float | None = None
):
    """Build a tracer profile by name.

    Parameters
    ----------
    name : {"plummer", "dehnen", "king"}
    gamma : float
        Dehnen inner slope, or the cusp slope of a Plummer/King with ``cusp_radius``.
    concentration : float
        King concentration ``log10(r_t/r_c)`` (ignored otherwise).
    cusp_radius : float, optional
        Cusp radius in scale radii: a Plummer or King profile gets an inner cusp
        of slope ``gamma`` (:class:`Cusped`).
    """
    if cusp_radius is not None and name in ("plummer", "king"):
        return Cusped(make_tracer(name, concentration=concentration), gamma, cusp_radius)
    if name == "plummer":
        return Plummer()
    if name == "dehnen":
        return Dehnen(gamma=float(gamma))
    if name == "king":
        return King(concentration=float(concentration))
    raise ValueError(f"unknown tracer profile {name!r}; expected one of {sorted(TRACERS)}")
