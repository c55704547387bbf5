"""Spherical cluster mass models: tracer density, enclosed mass and potential.

The stars trace the mass (one self-consistent stellar component) and an
optional central point mass (the IMBH) adds to the potential. Densities are
built from a *shape* (Plummer or King(W0)), optionally multiplied by an inner
cusp factor, then normalised to the requested stellar mass.

Internal units are pc, solMass and km/s; :data:`G_PC` is Newton's constant in
pc (km/s)^2 / solMass. Public builders accept astropy Quantities or plain
floats in those units.

The cusp factor ``(1 + (r_cusp / r)**2) ** (gamma / 2)`` makes the density
``~ r**-gamma`` well inside ``r_cusp`` and leaves it unchanged outside, as in
N-body models of clusters around a black hole (Bahcall-Wolf like cusps,
gamma ~ 1.55). Its default radius is the BH influence radius, inside which the
cored model holds ``2 M_BH`` of stars.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import astropy.constants as const
import astropy.units as u
import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import cumulative_trapezoid, solve_ivp
from scipy.interpolate import CubicSpline
from scipy.optimize import brentq
from scipy.special import gammainc

__all__ = [
    "G_PC",
    "MassModel",
    "N_RADIAL_GRID",
    "PLUMMER_TRUNCATION",
    "TracerProfile",
    "build_mass_model",
    "build_multi_mass_model",
    "central_dispersion_cored",
    "influence_radius",
    "king_density_of_w",
    "king_solution",
    "king_w0_for_truncation",
    "plummer_shape",
    "projected_radii",
    "radial_grid",
]

#: Newton's constant in pc (km/s)^2 / solMass.
G_PC = float(const.G.to_value(u.pc * u.km**2 / u.s**2 / u.solMass))

#: Radial grid size of the tabulated model (log-spaced).
N_RADIAL_GRID = 4000
#: Plummer models are truncated at this many scale radii (density there ~1e-15 central).
PLUMMER_TRUNCATION = 1.0e3


def _value(x, unit: str) -> float:
    """Float value of ``x`` in ``unit`` (plain numbers are taken to be in ``unit``)."""
    if isinstance(x, u.Quantity):
        return float(x.to_value(unit))
    return float(x)


# ---------------------------------------------------------------- shapes
def plummer_shape(x: np.ndarray) -> np.ndarray:
    """Unnormalised Plummer density ``(1 + x**2)**-2.5`` at ``x = r / a``.

    Parameters
    ----------
    x : array_like
        Radius in units of the Plummer scale radius.

    Returns
    -------
    ndarray
        Density shape, 1 at the centre.
    """
    return (1.0 + np.asarray(x, float) ** 2) ** -2.5


def king_density_of_w(w: np.ndarray) -> np.ndarray:
    """King (1966) density as a function of the dimensionless potential W.

    ``rho(W) / rho_1 = exp(W) * gamma(5/2, W)`` (lower incomplete gamma
    function), written with the regularised ``gammainc`` so that it is stable
    for W -> 0 where it behaves as ``W**2.5``.

    Parameters
    ----------
    w : array_like
        Dimensionless potential W (negative values are clipped to 0).

    Returns
    -------
    ndarray
        ``rho(W) / rho_1`` (dimensionless).
    """
    w = np.clip(np.asarray(w, float), 0.0, None)
    return np.exp(w) * gammainc(2.5, w)


@functools.lru_cache(maxsize=512)
def king_solution(w0: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Solve King's Poisson equation for central potential ``w0``.

    Parameters
    ----------
    w0 : float
        Central dimensionless potential, in [0.1, 20].

    Returns
    -------
    x : ndarray
        Radii in King radii ``r0 = sqrt(9 sigma^2 / (4 pi G rho_0))``.
    w : ndarray
        Dimensionless potential W(x), W(x_t) = 0.
    x_t : float
        Tidal (truncation) radius in King radii.
    """
    if not 0.1 <= w0 <= 20.0:
        raise ValueError(f"king_w0 must be between 0.1 and 20, got {w0}")
    rho0 = king_density_of_w(w0)

    def rhs(x, y):
        w, dw = y
        return [dw, -9.0 * king_density_of_w(w) / rho0 - 2.0 * dw / x]

    def edge(x, y):
        return y[0]

    edge.terminal = True
    edge.direction = -1
    x0 = 1e-6
    sol = solve_ivp(
        rhs,
        (x0, 1e6),
        [w0 - 1.5 * x0**2, -3.0 * x0],
        events=edge,
        rtol=1e-10,
        atol=1e-12,
        dense_output=True,
    )
    x_t = float(sol.t_events[0][0])
    x = np.concatenate([[0.0], np.geomspace(x0, x_t, 2000)])
    w = np.concatenate([[w0], sol.sol(x[1:])[0]])
    w[-1] = 0.0
    return x, np.clip(w, 0.0, None), x_t


# ---------------------------------------------------------------- tracer
@dataclass(frozen=True)
class TracerProfile:
    """Shape of the stellar density (not normalised).

    Parameters
    ----------
    kind : {"plummer", "king"}
    scale_radius : float
        Plummer radius ``a`` or King radius ``r0`` [pc].
    king_w0 : float
        King central potential W0 (only for ``kind="king"``).
    cusp_gamma : float
        Inner logarithmic slope of the cusp (0 = no cusp).
    cusp_radius : float
        Radius inside which the cusp applies [pc] (ignored when ``cusp_gamma=0``).
    """

    kind: Literal["plummer", "king"] = "plummer"
    scale_radius: float = 1.0
    king_w0: float = 6.0
    cusp_gamma: float = 0.0
    cusp_radius: float = 0.0

    def __post_init__(self):
        if self.kind not in ("plummer", "king"):
            raise ValueError(f"tracer must be 'plummer' or 'king', got {self.kind!r}")
        if not (np.isfinite(self.scale_radius) and self.scale_radius > 0):
            raise ValueError(f"scale radius must be positive, got {self.scale_radius} pc")
        if not 0.0 <= self.cusp_gamma < 2.5:
            raise ValueError(f"cusp_gamma must be in [0, 2.5), got {self.cusp_gamma}")
        if self.cusp_gamma > 0 and not self.cusp_radius > 0:
            raise ValueError("a cusp (cusp_gamma > 0) needs a positive cusp_radius")

    @property
    def truncation_radius(self) -> float:
        """Radius beyond which the density is zero [pc]."""
        if self.kind == "king":
            return king_solution(float(self.king_w0))[2] * self.scale_radius
        return PLUMMER_TRUNCATION * self.scale_radius

    def core_shape(self, r: np.ndarray) -> np.ndarray:
        """Density shape without the cusp, 1 at the centre.

        Parameters
        ----------
        r : array_like
            Radii [pc].

        Returns
        -------
        ndarray
            Plummer or King (1966) density relative to the centre (0 beyond the King tidal
            radius).
        """
        x = np.asarray(r, float) / self.scale_radius
        if self.kind == "plummer":
            return plummer_shape(x)
        xs, ws, x_t = king_solution(float(self.king_w0))
        spline = _king_spline(float(self.king_w0))
        w = np.where(x < x_t, spline(np.clip(x, 0.0, x_t)), 0.0)
        return king_density_of_w(w) / king_density_of_w(self.king_w0)

    def cusp_factor(self, r: np.ndarray) -> np.ndarray:
        """Multiplicative inner cusp ``(1 + (r_cusp / r)^2)^(gamma/2)`` (1 without cusp).

        Parameters
        ----------
        r : array_like
            Radii [pc].

        Returns
        -------
        ndarray
            The factor (dimensionless, >= 1).
        """
        r = np.asarray(r, float)
        if self.cusp_gamma == 0:
            return np.ones_like(r)
        with np.errstate(divide="ignore"):
            return (1.0 + (self.cusp_radius / r) ** 2) ** (0.5 * self.cusp_gamma)

    def shape(self, r: np.ndarray) -> np.ndarray:
        """Unnormalised density (core shape times cusp factor).

        Parameters
        ----------
        r : array_like
            Radii [pc].

        Returns
        -------
        ndarray
            Density shape (dimensionless).
        """
        return self.core_shape(r) * self.cusp_factor(r)


@functools.lru_cache(maxsize=256)
def king_w0_for_truncation(x_t: float, guess: float | None = None) -> float:
    """King W0 whose truncation radius is ``x_t`` King radii.

    ``guess`` (a nearby W0) narrows the first bracket to ``guess +- 1.5``.

    Parameters
    ----------
    x_t : float
        Truncation radius [King radii].
    guess : float, optional
        A nearby W0.

    Returns
    -------
    float
        W0.

    Raises
    ------
    ValueError
        If ``x_t`` is outside what W0 in [0.1, 20] gives.
    """
    lo, hi = 0.1, 20.0
    f_lo = np.log(king_solution(lo)[2] / x_t)
    f_hi = np.log(king_solution(hi)[2] / x_t)
    if f_lo > 0 or f_hi < 0:
        raise ValueError(
            f"no King model (W0 in [0.1, 20]) has a truncation radius of {x_t:.3g} King radii"
        )
    if guess is not None:  # a narrow bracket first (most groups are close to the reference)
        a, b = max(lo, guess - 1.5), min(hi, guess + 1.5)
        if np.log(king_solution(a)[2] / x_t) <= 0 <= np.log(king_solution(b)[2] / x_t):
            lo, hi = a, b
    # ln x_t(W0) is smooth and monotonic: Brent's method needs a handful of King solutions
    w0 = brentq(lambda w: np.log(king_solution(w)[2] / x_t), lo, hi, xtol=1e-4, rtol=1e-8)
    return round(float(w0), 4)


@functools.lru_cache(maxsize=512)
def _king_spline(w0: float) -> CubicSpline:
    x, w, _ = king_solution(w0)
    return CubicSpline(x, w)


# ---------------------------------------------------------------- mass model
@dataclass(frozen=True)
class MassModel:
    """A normalised spherical model: stars (tracing mass) plus a central point mass.

    Build with :func:`build_mass_model`. Tables are on a log-spaced radial grid
    ``r`` [pc]; ``psi`` is the relative potential ``Phi(r_max) - Phi(r)``
    [(km/s)^2], positive and decreasing outwards.

    Parameters
    ----------
    tracer : TracerProfile
    stellar_mass : float
        Total stellar mass [solMass].
    bh_mass : float
        Central point mass [solMass].
    norm : float
        Density normalisation: ``rho = norm * tracer.shape(r)`` [solMass/pc^3].
    r, rho, mass, psi : ndarray
        Radial grid [pc], density [solMass/pc^3], enclosed stellar mass
        [solMass] and relative potential [(km/s)^2].
    potential_mass : ndarray or None
        For one component of a multi-mass model: the enclosed mass of *all*
        components [solMass] (without the point mass), which sets the potential
        together with ``bh_mass``; None when this model is the whole cluster.
    """

    tracer: TracerProfile
    stellar_mass: float
    bh_mass: float
    norm: float
    r: np.ndarray
    rho: np.ndarray
    mass: np.ndarray
    psi: np.ndarray
    potential_mass: np.ndarray | None = None

    @property
    def gravitating_mass(self) -> np.ndarray:
        """Mass inside each grid radius that sets the potential (all stars + BH) [solMass]."""
        stars = self.mass if self.potential_mass is None else self.potential_mass
        return stars + self.bh_mass

    @property
    def r_max(self) -> float:
        """Outer edge of the model [pc]."""
        return float(self.r[-1])

    def density(self, r: ArrayLike) -> np.ndarray:
        """Stellar mass density [solMass/pc^3] at radius ``r`` [pc] (analytic shape).

        Parameters
        ----------
        r : array_like
            Radii [pc].

        Returns
        -------
        ndarray
            Density [solMass/pc^3]; 0 beyond the model's edge.
        """
        r = np.asarray(r, float)
        return np.where(r <= self.r_max, self.norm * self.tracer.shape(r), 0.0)

    def enclosed_stellar_mass(self, r: ArrayLike) -> np.ndarray:
        """Stellar mass inside ``r`` [solMass] (interpolated in log-log).

        Parameters
        ----------
        r : array_like
            Radii [pc] (clipped to the grid).

        Returns
        -------
        ndarray
            Enclosed stellar mass [solMass], without the point mass.
        """
        r = np.clip(np.asarray(r, float), self.r[0], self.r_max)
        return np.exp(np.interp(np.log(r), np.log(self.r), np.log(self.mass)))

    def potential_nodes(
        self, psi_lo: float, psi_hi: float, n: int, min_log_step: float, r_lo: float | None = None
    ) -> np.ndarray:
        """Grid of Psi values [(km/s)^2] in [psi_lo, psi_hi], ascending.

        Half log-spaced in Psi, half at Psi(r) of log-spaced radii from ``r_lo``
        (default: the grid's first radius) to the edge, so that cores, where Psi is
        nearly flat, are resolved. Nodes closer than ``min_log_step`` in ln Psi are merged.

        Parameters
        ----------
        psi_lo, psi_hi : float
            Range of the grid [(km/s)^2], psi_lo > 0.
        n : int
            Number of nodes before merging.
        min_log_step : float
            Smallest step kept in ln Psi.
        r_lo : float, optional
            Innermost radius of the radius-spaced half [pc].

        Returns
        -------
        ndarray
            The nodes [(km/s)^2].
        """
        r_lo = self.r[0] if r_lo is None else r_lo
        radii = np.geomspace(r_lo, self.r_max, n - n // 2)
        nodes = np.concatenate(
            [np.geomspace(psi_lo, psi_hi, n // 2), self.relative_potential(radii)]
        )
        nodes = np.clip(np.sort(nodes), psi_lo, psi_hi)
        keep = np.concatenate([[True], np.diff(np.log(nodes)) > min_log_step])
        return nodes[keep]

    def relative_potential(self, r: ArrayLike) -> np.ndarray:
        """Relative potential Psi(r) [(km/s)^2] including the point mass.

        Parameters
        ----------
        r : array_like
            Radii [pc] (clipped to the grid).

        Returns
        -------
        ndarray
            Psi [(km/s)^2], interpolated in log-log.
        """
        r = np.clip(np.asarray(r, float), self.r[0], self.r_max)
        return np.exp(np.interp(np.log(r), np.log(self.r), np.log(self.psi)))


def _cumulative_mass(r: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Enclosed mass on a log grid, with the analytic power-law inner piece."""
    lnr = np.log(r)
    integrand = 4.0 * np.pi * r**3 * rho
    # inner piece: rho ~ r^-s below r[0]
    s = -np.log(rho[1] / rho[0]) / (lnr[1] - lnr[0])
    s = min(max(s, 0.0), 2.9)
    inner = 4.0 * np.pi * rho[0] * r[0] ** 3 / (3.0 - s)
    return inner + cumulative_trapezoid(integrand, lnr, initial=0.0)


def _relative_potential(r, rho, mass, bh_mass):
    """Psi(r) = Phi(r_max) - Phi(r) for stars plus point mass [(km/s)^2]."""
    lnr = np.log(r)
    outer = cumulative_trapezoid((4.0 * np.pi * r**2 * rho)[::-1], lnr[::-1], initial=0.0)[::-1]
    outer = -outer  # integral of 4 pi r rho dr from r to r_max (lnr decreasing above)
    total = mass[-1] + bh_mass
    psi = G_PC * ((mass + bh_mass) / r + outer - total / r[-1])
    # keep Psi strictly positive at the outer edge for log interpolation
    floor = G_PC * total / r[-1] * 1e-9
    return np.maximum(psi, floor)


def central_dispersion_cored(tracer: TracerProfile, stellar_mass: float) -> float:
    """Central 1-D dispersion [km/s] of the cored model without point mass.

    ``sigma_0^2 = (1/rho_0) int_0^inf rho G M(r) / r^2 dr`` (isotropic Jeans).

    Parameters
    ----------
    tracer : TracerProfile
        The tracer (its cusp is ignored).
    stellar_mass : float
        Total stellar mass [solMass].

    Returns
    -------
    float
        sigma_0 [km/s].
    """
    core = TracerProfile(tracer.kind, tracer.scale_radius, tracer.king_w0)
    r = np.geomspace(core.scale_radius * 1e-5, core.truncation_radius, 2000)
    shape = core.shape(r)
    m = _cumulative_mass(r, shape)
    norm = stellar_mass / m[-1]
    integrand = shape * G_PC * m * norm / r  # d r = r dlnr
    return float(np.sqrt(np.trapezoid(integrand, np.log(r))))


def influence_radius(tracer: TracerProfile, stellar_mass: float, bh_mass: float) -> float:
    """BH influence radius [pc]: where the cored model encloses ``2 M_BH`` of stars.

    Inside it the point mass dominates the potential gradient. (A cusp confined to
    the smaller radius ``G M_BH / sigma_0^2`` leaves a stretch where the flat core
    sits in a BH-dominated potential, which has no non-negative isotropic DF.)

    Parameters
    ----------
    tracer : TracerProfile
        The tracer (its cusp is ignored).
    stellar_mass : float
        Total stellar mass [solMass].
    bh_mass : float
        Point mass [solMass].

    Returns
    -------
    float
        The radius [pc] (at least 1e-9 scale radii).
    """
    core = TracerProfile(tracer.kind, tracer.scale_radius, tracer.king_w0)
    r = np.geomspace(core.scale_radius * 1e-7, core.truncation_radius, 3000)
    m = _cumulative_mass(r, core.shape(r))
    target = min(2.0 * bh_mass / stellar_mass, 0.5)
    radius = float(np.exp(np.interp(np.log(target), np.log(m / m[-1]), np.log(r))))
    # a negligible BH still gets a resolvable (if irrelevant) cusp radius
    return max(radius, 1e-9 * tracer.scale_radius)


def radial_grid(r_lo: float, r_hi: float, n: int) -> np.ndarray:
    """Radii [pc]: log-spaced out to ``r_hi / 2``, then log-spaced in ``r_hi - r``.

    The second part resolves the outer edge, where the relative potential goes
    to zero linearly and the low-energy end of the DF is decided.

    Parameters
    ----------
    r_lo, r_hi : float
        Inner and outer radius [pc].
    n : int
        Number of radii.

    Returns
    -------
    ndarray
        Ascending radii [pc].
    """
    n_edge = max(n // 5, 8)
    inner = np.geomspace(r_lo, 0.5 * r_hi, n - n_edge)
    edge = r_hi - np.geomspace(0.5 * r_hi, 1e-9 * r_hi, n_edge + 1)[1:]
    return np.concatenate([inner, edge])


def build_mass_model(
    tracer: TracerProfile,
    stellar_mass: float,
    bh_mass: float = 0.0,
    r_min: float | None = None,
    n_grid: int = N_RADIAL_GRID,
) -> MassModel:
    """Tabulate a normalised mass model.

    Parameters
    ----------
    tracer : TracerProfile
        Density shape (with cusp if any).
    stellar_mass : float or Quantity
        Total stellar mass [solMass].
    bh_mass : float or Quantity
        Central point mass [solMass] (0 for none).
    r_min : float or Quantity, optional
        Innermost tabulated radius [pc]; default ``1e-6`` scale radii.
    n_grid : int
        Number of radii (see :func:`radial_grid`).

    Returns
    -------
    MassModel
    """
    stellar_mass = _value(stellar_mass, "solMass")
    bh_mass = _value(bh_mass, "solMass")
    if not (np.isfinite(stellar_mass) and stellar_mass > 0):
        raise ValueError(f"stellar mass must be positive, got {stellar_mass} solMass")
    if not (np.isfinite(bh_mass) and bh_mass >= 0):
        raise ValueError(f"IMBH mass must be >= 0, got {bh_mass} solMass")
    r_hi = tracer.truncation_radius
    r_lo = tracer.scale_radius * 1e-6 if r_min is None else _value(r_min, "pc")
    if tracer.cusp_gamma > 0:
        r_lo = max(min(r_lo, tracer.cusp_radius * 1e-4), tracer.scale_radius * 1e-13)
    r = radial_grid(r_lo, r_hi, n_grid)
    shape = tracer.shape(r)
    shape = np.maximum(shape, np.finfo(float).tiny)
    m_shape = _cumulative_mass(r, shape)
    norm = stellar_mass / m_shape[-1]
    rho = norm * shape
    mass = norm * m_shape
    psi = _relative_potential(r, rho, mass, bh_mass)
    return MassModel(tracer, stellar_mass, bh_mass, norm, r, rho, mass, psi)


def build_multi_mass_model(
    tracers: Sequence[TracerProfile],
    masses: Sequence[float],
    bh_mass: float = 0.0,
    n_grid: int = N_RADIAL_GRID,
) -> list[MassModel]:
    """Components of a multi-mass model, all in the total potential.

    Each component ``k`` has density ``M_k * shape_k(r) / int shape_k dV``; the
    relative potential is that of the sum of all components plus the point mass.

    Parameters
    ----------
    tracers : sequence of TracerProfile
        Density shape of each component.
    masses : sequence of float
        Total mass of each component [solMass].
    bh_mass : float
        Central point mass [solMass].
    n_grid : int
        Number of radii of the shared grid.

    Returns
    -------
    list of MassModel
        One per component, sharing the radial grid and ``psi``; ``potential_mass``
        is the enclosed mass of all components.
    """
    masses = [_value(m, "solMass") for m in masses]
    bh_mass = _value(bh_mass, "solMass")
    if not masses or any(not (np.isfinite(m) and m > 0) for m in masses):
        raise ValueError(f"component masses must be positive, got {masses} solMass")
    if not (np.isfinite(bh_mass) and bh_mass >= 0):
        raise ValueError(f"IMBH mass must be >= 0, got {bh_mass} solMass")
    r_hi = max(t.truncation_radius for t in tracers)
    r_lo = min(t.scale_radius for t in tracers) * 1e-6
    for t in tracers:
        if t.cusp_gamma > 0:
            r_lo = max(min(r_lo, t.cusp_radius * 1e-4), t.scale_radius * 1e-13)
    r = radial_grid(r_lo, r_hi, n_grid)
    parts = []
    for tracer, m in zip(tracers, masses):
        shape = np.maximum(tracer.shape(r), 1e-300)  # Plummer shapes run to the common edge
        m_shape = _cumulative_mass(r, shape)
        norm = m / m_shape[-1]
        parts.append((tracer, m, norm, norm * shape, norm * m_shape))
    rho_tot = np.sum([p[3] for p in parts], axis=0)
    mass_tot = np.sum([p[4] for p in parts], axis=0)
    psi = _relative_potential(r, rho_tot, mass_tot, bh_mass)
    return [
        MassModel(tracer, m, bh_mass, norm, r, rho, mass, psi, mass_tot)
        for tracer, m, norm, rho, mass in parts
    ]


def projected_radii(tracer: TracerProfile, n: int = 200) -> tuple[float, float]:
    """Core radius (Sigma = Sigma_0 / 2) and projected half-mass radius [pc].

    Computed from the tracer shape (cusp included) by line-of-sight integration
    on a grid; used to scale models to observed radii.

    Parameters
    ----------
    tracer : TracerProfile
        The tracer.
    n : int
        Number of projected radii of the grid.

    Returns
    -------
    core, half : float
        Core radius and projected half-mass radius [pc].
    """
    r_t = tracer.truncation_radius
    radii = np.geomspace(tracer.scale_radius * 1e-4, r_t * (1 - 1e-6), n)
    t = np.arcsinh(np.sqrt(r_t**2 - radii**2) / radii)[:, None] * np.linspace(0, 1, 600)
    sigma = 2 * np.trapezoid(
        tracer.shape(radii[:, None] * np.cosh(t)) * radii[:, None] * np.cosh(t), t, axis=1
    )
    core = float(np.interp(0.5, sigma[::-1] / sigma[0], radii[::-1]))
    cum = cumulative_trapezoid(sigma * 2 * np.pi * radii**2, np.log(radii), initial=0.0)
    half = float(np.exp(np.interp(0.5, cum / cum[-1], np.log(radii))))
    return core, half
