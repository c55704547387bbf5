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
King (1962) "King62", concentration ``c = log10(r_t / r_c)``
    Analytic surface density and 3-D density, truncated at ``x_t = 10**c``; the
    enclosed mass is tabulated once per concentration (cached).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mavispm.dynamics.cusp_kernel import cusped_at_points
from mavispm.dynamics.interpolation import cubic_weights

__all__ = [
    "AtPoints",
    "Cusped",
    "CuspedAtPoints",
    "Dehnen",
    "DehnenAtPoints",
    "King62",
    "Plummer",
    "TRACERS",
    "cusp_factor",
    "make_tracer",
]

_FOUR_PI = 4.0 * np.pi


class _ClosedFormEnclosedMass:
    """Shared methods of the profiles whose enclosed mass needs no per-call quadrature
    (Plummer analytic, King62 tabulated once per concentration)."""

    @property
    def family(self):
        """Profiles sharing :meth:`at_points` tables (just this one)."""
        return self

    def at_points(self, points, mass_points=None):
        """Evaluator of ``(nu, m)`` at fixed points."""
        return AtPoints(points, mass_points)

    def radius_enclosing(self, q: float) -> float:
        """3-D radius inside which the mass fraction is ``q`` (0 < q < 1)."""
        if not 0.0 < q < 1.0:
            raise ValueError(f"mass fraction must be in (0, 1), got {q}")
        return self._inverse_enclosed(q)


@dataclass(frozen=True)
class Plummer(_ClosedFormEnclosedMass):
    """Plummer (1911) sphere with unit mass and unit scale radius."""

    name = "plummer"
    #: logarithmic outer slope of the density (nu ~ x**-outer_slope)
    outer_slope = 5.0

    def density(self, x: ArrayLike):
        """3-D density ``nu(x)`` (unit mass, unit scale radius).

        Parameters
        ----------
        x : array_like
            3-D radii [scale radii].

        Returns
        -------
        ndarray
            Density (unit total mass, per unit volume in scale radii cubed).
        """
        x = np.asarray(x, dtype=float)
        return 3.0 / _FOUR_PI * (1.0 + x * x) ** -2.5

    def enclosed(self, x: ArrayLike):
        """Mass fraction inside 3-D radius ``x``.

        Parameters
        ----------
        x : array_like
            3-D radii [scale radii].

        Returns
        -------
        ndarray
            Enclosed mass fraction in [0, 1].
        """
        x = np.asarray(x, dtype=float)
        return x**3 * (1.0 + x * x) ** -1.5

    def surface_density(self, X: ArrayLike):
        """Projected density ``Sigma(X)`` (unit mass, per unit area in a**2).

        Parameters
        ----------
        X : array_like
            Projected radii [scale radii].

        Returns
        -------
        ndarray
            Surface density (unit total mass, per unit area in scale radii squared).
        """
        X = np.asarray(X, dtype=float)
        return 1.0 / np.pi * (1.0 + X * X) ** -2

    def projected_enclosed(self, X: ArrayLike):
        """Mass fraction inside projected radius ``X``.

        Parameters
        ----------
        X : array_like
            Projected radii [scale radii].

        Returns
        -------
        ndarray
            Projected mass fraction in [0, 1].
        """
        X = np.asarray(X, dtype=float)
        return X * X / (1.0 + X * X)

    def _inverse_enclosed(self, q: float) -> float:
        q23 = q ** (2.0 / 3.0)
        return float(q ** (1.0 / 3.0) / np.sqrt(1.0 - q23))


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

    def density(self, x: ArrayLike):
        """3-D density ``nu(x)`` (unit mass, unit scale radius).

        Parameters
        ----------
        x : array_like
            3-D radii [scale radii].

        Returns
        -------
        ndarray
            Density (unit total mass, per unit volume in scale radii cubed).
        """
        x = np.asarray(x, dtype=float)
        g = self.gamma
        return (3.0 - g) / _FOUR_PI * x**-g * (1.0 + x) ** (g - 4.0)

    def enclosed(self, x: ArrayLike):
        """Mass fraction inside 3-D radius ``x``.

        Parameters
        ----------
        x : array_like
            3-D radii [scale radii].

        Returns
        -------
        ndarray
            Enclosed mass fraction in [0, 1].
        """
        x = np.asarray(x, dtype=float)
        return (x / (1.0 + x)) ** (3.0 - self.gamma)

    @property
    def family(self):
        """Profiles sharing :meth:`at_points` tables (every gamma)."""
        return ("dehnen",)

    def at_points(self, points: ArrayLike, mass_points: ArrayLike | None = None):
        """Evaluator of ``(nu, m)`` at fixed points for any Dehnen ``gamma``.

        Parameters
        ----------
        points : array_like
            Radii where the density is needed [scale radii] (> 0).
        mass_points : array_like, optional
            Radii where the enclosed mass is needed (default: ``points``).

        Returns
        -------
        DehnenAtPoints
            Callable on a profile of the family, giving ``(nu, m)``.
        """
        return DehnenAtPoints(points, mass_points)

    # surface density and projected mass: numerical (see jeans.JeansProjector)
    surface_density = None
    projected_enclosed = None


@dataclass(frozen=True)
class King62(_ClosedFormEnclosedMass):
    """King (1962) profile ("King62") with core radius 1 and concentration ``c``.

    Not the King (1966) lowered-isothermal model of the cluster generator
    (:mod:`mavispm.simulate.cluster.profiles`, parameter W0): this one is the
    empirical surface-density law of King (1962).

    Parameters
    ----------
    concentration : float
        ``log10(r_t / r_c)``, in (0.3, 3].
    """

    concentration: float = 1.5
    name = "king62"
    outer_slope = np.inf  # truncated: no density beyond the tidal radius

    def __post_init__(self):
        if not (0.3 < self.concentration <= 3.0):
            raise ValueError(f"King62 concentration must be in (0.3, 3], got {self.concentration}")

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

    def density(self, x: ArrayLike):
        """3-D density ``nu(x)`` (unit mass, unit core radius).

        Parameters
        ----------
        x : array_like
            3-D radii [core radii].

        Returns
        -------
        ndarray
            Density (unit total mass, per unit volume in core radii cubed).
        """
        return self._raw_density(x) / _king_table(self.concentration)[2]

    def enclosed(self, x: ArrayLike):
        """Mass fraction inside 3-D radius ``x`` (tabulated, cached).

        Parameters
        ----------
        x : array_like
            3-D radii [core radii].

        Returns
        -------
        ndarray
            Enclosed mass fraction in [0, 1].
        """
        lx, lm, _ = _king_table(self.concentration)
        x = np.asarray(x, dtype=float)
        with np.errstate(divide="ignore"):
            lnx = np.log(np.maximum(x, 1e-300))
        out = np.exp(np.interp(lnx, lx, lm, left=-np.inf, right=0.0))
        small = lnx < lx[0]  # central density is flat: m ~ x^3
        return np.where(small, np.exp(lm[0] + 3.0 * (lnx - lx[0])), out)

    def surface_density(self, X: ArrayLike):
        """Projected density (unit mass), zero beyond the tidal radius.

        Parameters
        ----------
        X : array_like
            Projected radii [core radii].

        Returns
        -------
        ndarray
            Surface density (unit total mass, per unit area in core radii squared).
        """
        X = np.asarray(X, dtype=float)
        c = 1.0 / np.sqrt(1.0 + self.tidal_radius**2)
        shape = np.where(X < self.tidal_radius, (1.0 / np.sqrt(1.0 + X * X) - c) ** 2, 0.0)
        return shape / self._projected_raw(self.tidal_radius)

    def _projected_raw(self, X):
        X = np.minimum(np.asarray(X, dtype=float), self.tidal_radius)
        c = 1.0 / np.sqrt(1.0 + self.tidal_radius**2)
        q = 1.0 + X * X
        return np.pi * (np.log(q) - 4.0 * c * (np.sqrt(q) - 1.0) + c * c * (q - 1.0))

    def projected_enclosed(self, X: ArrayLike):
        """Mass fraction inside projected radius ``X``.

        Parameters
        ----------
        X : array_like
            Projected radii [core radii].

        Returns
        -------
        ndarray
            Projected mass fraction in [0, 1].
        """
        return self._projected_raw(X) / self._projected_raw(self.tidal_radius)

    def _inverse_enclosed(self, q: float) -> float:
        lx, lm, _ = _king_table(self.concentration)
        lq = np.log(q)
        if lq < lm[0]:  # flat core: m ~ x^3
            return float(np.exp(lx[0] + (lq - lm[0]) / 3.0))
        return float(np.exp(np.interp(lq, lm, lx)))


@functools.lru_cache(maxsize=16)
def _king_table(concentration: float):
    """ln x, ln m(x) on a fine grid and the density normalisation (cached)."""
    king = King62.__new__(King62)
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


#: Cumulative-mass grid of the cusped profiles: ``_CUSP_PANELS`` Gauss-Legendre panels
#: of ``_CUSP_NODES`` nodes, uniform in ln x from ``_CUSP_X_IN`` to the base profile's
#: outer radius (tidal radius, or 1e5 scale radii).
_CUSP_X_IN = 1e-8
_CUSP_PANELS = 800
_CUSP_NODES = 4


def cusp_factor(cusp_radius: float, gamma: float, inv_x2: ArrayLike):
    """Cusp multiplier ``(1 + (x_c / x)^2)^(gamma / 2)`` from precomputed ``1 / x^2``.

    Parameters
    ----------
    cusp_radius : float
        Cusp radius ``x_c`` [scale radii].
    gamma : float
        Inner logarithmic slope added.
    inv_x2 : array_like
        ``1 / x^2`` [scale radii^-2].

    Returns
    -------
    ndarray
        The multiplier (>= 1 for gamma >= 0).
    """
    return np.exp(0.5 * gamma * np.log1p(cusp_radius * cusp_radius * inv_x2))


def _inverse_square(x):
    """``1 / x^2`` capped at 1e300 (x = 0 allowed)."""
    x = np.asarray(x, dtype=float)
    return 1.0 / np.maximum(x * x, 1e-300)


@dataclass(frozen=True, eq=False)
class _CuspMassGrid:
    """Parameter-free part of the cumulative mass of ``base x cusp_factor`` (one per base).

    Attributes
    ----------
    ln_edges : ndarray (P + 1,)
        Uniform panel edges in ln x.
    f_base : ndarray (P, n)
        ``4 pi x^3 nu_base(x)`` times the Gauss-Legendre weight (in ln x) at the nodes.
    inv_x2 : ndarray (P, n)
        ``1 / x^2`` at the nodes.
    ln_inv_x2 : ndarray (P, n)
        Its logarithm.
    nu0 : float
        Central density of the base profile.
    x_hi, m_out : float
        Outer edge of the grid and the base mass beyond it (0 for a King62 profile).
    """

    ln_edges: np.ndarray
    f_base: np.ndarray
    inv_x2: np.ndarray
    ln_inv_x2: np.ndarray
    nu0: float
    x_hi: float
    m_out: float

    def cumulative(self, gamma: float, cusp_radius: float):
        """Unnormalised mass inside each edge and the total mass.

        The mass inside ``x_in = exp(ln_edges[0])`` is the analytic power law
        ``4 pi nu0 x_c^gamma x_in^(3 - gamma) / (3 - gamma)`` (the cusp factor is
        ``(x_c / x)^gamma`` there to relative order ``(x_in / x_c)^2``); beyond the
        grid the cusp factor is 1 and the base profile's own mass is added.
        """
        x_in = np.exp(self.ln_edges[0])
        m_in = _FOUR_PI * self.nu0 * cusp_radius**gamma * x_in ** (3.0 - gamma) / (3.0 - gamma)
        panels = np.einsum("pk,pk->p", self.f_base, cusp_factor(cusp_radius, gamma, self.inv_x2))
        cum = np.empty(panels.size + 1)
        cum[0] = m_in
        np.cumsum(panels, out=cum[1:])
        cum[1:] += m_in
        return cum, cum[-1] + self.m_out


@functools.lru_cache(maxsize=8)
def _cusp_mass_grid(base) -> _CuspMassGrid:
    x_hi = float(getattr(base, "tidal_radius", 1e5))
    edges = np.linspace(np.log(_CUSP_X_IN), np.log(x_hi), _CUSP_PANELS + 1)
    nodes, weights = np.polynomial.legendre.leggauss(_CUSP_NODES)
    mid = 0.5 * (edges[1:] + edges[:-1])
    half = 0.5 * np.diff(edges)
    x = np.exp(mid[:, None] + half[:, None] * nodes[None, :])
    f = _FOUR_PI * x**3 * base.density(x) * half[:, None] * weights[None, :]
    return _CuspMassGrid(
        ln_edges=edges,
        f_base=f,
        inv_x2=_inverse_square(x),
        ln_inv_x2=np.log(_inverse_square(x)),
        nu0=float(base.density(0.0)),
        x_hi=x_hi,
        m_out=float(1.0 - base.enclosed(x_hi)),
    )


class AtPoints:
    """Density and enclosed mass of any profile of one family at fixed points.

    The generic version simply calls the profile; subclasses cache what does not
    depend on the profile's parameters (used by the Jeans projector, whose
    quadrature points are fixed).

    Parameters
    ----------
    points : array_like
        Radii where the density is needed, in scale radii (> 0).
    mass_points : array_like, optional
        Radii where the enclosed mass is needed (default: ``points``).
    """

    def __init__(self, points, mass_points=None):
        self.points = np.asarray(points, dtype=float)
        self.mass_points = self.points if mass_points is None else np.asarray(mass_points, float)

    def __call__(self, tracer):
        """``(nu at points, m at mass_points)`` of ``tracer``."""
        return tracer.density(self.points), tracer.enclosed(self.mass_points)


class DehnenAtPoints(AtPoints):
    """Dehnen profiles of any ``gamma`` at fixed points (ln x and ln(1 + x) cached).

    Parameters
    ----------
    points : array_like
        Radii where the density is needed [scale radii] (> 0).
    mass_points : array_like, optional
        Radii where the enclosed mass is needed (default: ``points``).
    """

    def __init__(self, points, mass_points=None):
        super().__init__(points, mass_points)
        self._logs = [
            (np.log(x), np.log1p(x))
            for x in (np.maximum(self.points, 1e-300), np.maximum(self.mass_points, 1e-300))
        ]

    def __call__(self, tracer):
        g = tracer.gamma
        (lnx, ln1px), (lnm, ln1pm) = self._logs
        nu = (3.0 - g) / _FOUR_PI * np.exp((g - 4.0) * ln1px - g * lnx)
        return nu, np.exp((3.0 - g) * (lnm - ln1pm))


class CuspedAtPoints(AtPoints):
    """Cusped profiles over one base profile at fixed points, for any slope and cusp radius.

    The base density at the points, the base part of the mass integrand on the
    cumulative grid and the cubic (4-point Lagrange) interpolation of ``ln m``
    from the grid edges to the mass points (a sparse matrix) are built once; a
    call costs two cusp-factor evaluations (grid nodes and points), one
    cumulative sum and one sparse matrix-vector product.

    Parameters
    ----------
    base : Plummer or King62
    points, mass_points : array_like
        See :class:`AtPoints` (radii >= 0 in scale radii).
    """

    def __init__(self, base, points, mass_points=None):
        super().__init__(points, mass_points)
        from scipy.sparse import csr_array

        self.grid = _cusp_mass_grid(base)
        x = self.mass_points
        lnx = np.log(np.maximum(x, 1e-300))
        edges = self.grid.ln_edges
        idx, w = cubic_weights(edges[0], edges[1] - edges[0], edges.size, lnx)
        rows = np.broadcast_to(np.arange(x.size), idx.shape)
        self._interp = csr_array(
            (w.ravel(), (rows.ravel(), idx.ravel())), shape=(x.size, edges.size)
        )
        self._below = lnx < edges[0]
        self._dln_below = np.minimum(lnx - edges[0], 0.0)
        self._above = x > self.grid.x_hi
        x_hi = self.grid.x_hi
        self._outer = base.enclosed(np.maximum(x, x_hi)) - base.enclosed(x_hi)
        self._base_nu = base.density(self.points)
        self._inv_x2 = _inverse_square(self.points)
        self._ln_inv_x2 = np.log(self._inv_x2)

    def __call__(self, tracer):
        """``(nu at points, m at mass points)`` of ``tracer`` (compiled; the same numerics
        as :meth:`call_numpy`, see :mod:`mavispm.dynamics.cusp_kernel`)."""
        grid = self.grid
        return cusped_at_points(
            float(tracer.gamma),
            float(tracer.cusp_radius),
            float(grid.ln_edges[0]),
            grid.nu0,
            grid.m_out,
            grid.f_base,
            grid.inv_x2,
            grid.ln_inv_x2,
            self._interp.indptr,
            self._interp.indices,
            self._interp.data,
            self._below,
            self._dln_below,
            self._above,
            self._outer,
            self._base_nu,
            self._inv_x2,
            self._ln_inv_x2,
        )

    def call_numpy(self, tracer):
        """Reference implementation of :meth:`__call__` (numpy, for the tests).

        Parameters
        ----------
        tracer : Cusped
            A profile of this family.

        Returns
        -------
        nu, m : ndarray
            Density at the points and enclosed mass fraction at the mass points.
        """
        g, xc = tracer.gamma, tracer.cusp_radius
        cum, total = self.grid.cumulative(g, xc)
        m = np.exp(self._interp @ np.log(cum))
        if self._below.any():
            m = np.where(self._below, cum[0] * np.exp((3.0 - g) * self._dln_below), m)
        if self._above.any():
            m = np.where(self._above, cum[-1] + self._outer, m)
        nu = self._base_nu * cusp_factor(xc, g, self._inv_x2) / total
        return nu, np.minimum(m / total, 1.0)


@dataclass(frozen=True)
class Cusped:
    """A cored profile with an inner cusp: ``nu ~ base(x) (1 + (x_c / x)^2)^(gamma / 2)``.

    The same multiplier as the cluster generator's cusp: ``nu ~ x^-gamma`` inside
    ``x_c`` and the base profile (King62 core, Plummer) outside it. Renormalised to
    unit mass. The enclosed mass is a cumulative Gauss-Legendre quadrature in
    ``ln x`` on a fixed grid (800 panels x 4 nodes from 1e-8 to the base's outer
    radius, analytic power law inside 1e-8) whose parameter-free part is cached
    per base profile, interpolated to any radius with cubic Lagrange weights in
    ``ln m`` (see :class:`CuspedAtPoints`).

    Parameters
    ----------
    base : Plummer or King62
        Cored profile (unit mass, unit scale radius).
    gamma : float
        Inner slope in [0, 2.5).
    cusp_radius : float
        ``x_c`` in scale radii (> 0).
    """

    base: Plummer | King62 = Plummer()
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

    @property
    def family(self):
        """Profiles sharing :meth:`at_points` tables (same base, any gamma / cusp radius)."""
        return ("cusped", self.base)

    def at_points(self, points: ArrayLike, mass_points: ArrayLike | None = None) -> CuspedAtPoints:
        """Evaluator of ``(nu, m)`` at fixed points for every profile of this family.

        Parameters
        ----------
        points : array_like
            Radii where the density is needed [scale radii] (> 0).
        mass_points : array_like, optional
            Radii where the enclosed mass is needed (default: ``points``).

        Returns
        -------
        CuspedAtPoints
            Callable on a profile of the family, giving ``(nu, m)``.
        """
        return CuspedAtPoints(self.base, points, mass_points)

    def _evaluate(self, x):
        x = np.asarray(x, dtype=float)
        nu, m = self.at_points(x.ravel())(self)
        return nu.reshape(x.shape), m.reshape(x.shape)

    def density(self, x: ArrayLike):
        """3-D density ``nu(x)`` (unit mass, unit scale radius).

        Parameters
        ----------
        x : array_like
            3-D radii [scale radii].

        Returns
        -------
        ndarray
            Density (unit total mass, per unit volume in scale radii cubed).
        """
        return self._evaluate(x)[0]

    def enclosed(self, x: ArrayLike):
        """Mass fraction inside 3-D radius ``x``.

        Parameters
        ----------
        x : array_like
            3-D radii [scale radii].

        Returns
        -------
        ndarray
            Enclosed mass fraction in [0, 1].
        """
        return self._evaluate(x)[1]

    surface_density = None
    projected_enclosed = None


#: Known tracer profiles by name (for settings).
TRACERS = {"plummer": Plummer, "dehnen": Dehnen, "king62": King62}


def make_tracer(
    name: str, gamma: float = 1.0, concentration: float = 1.5, cusp_radius: float | None = None
):
    """Build a tracer profile by name.

    Parameters
    ----------
    name : {"plummer", "dehnen", "king62"}
    gamma : float
        Dehnen inner slope, or the cusp slope of a Plummer/King62 with ``cusp_radius``.
    concentration : float
        King62 concentration ``log10(r_t/r_c)`` (ignored otherwise).
    cusp_radius : float, optional
        Cusp radius in scale radii: a Plummer or King62 profile gets an inner cusp
        of slope ``gamma`` (:class:`Cusped`).
    """
    if cusp_radius is not None and name in ("plummer", "king62"):
        return Cusped(make_tracer(name, concentration=concentration), gamma, cusp_radius)
    if name == "plummer":
        return Plummer()
    if name == "dehnen":
        return Dehnen(gamma=float(gamma))
    if name == "king62":
        return King62(concentration=float(concentration))
    raise ValueError(f"unknown tracer profile {name!r}; expected one of {sorted(TRACERS)}")
