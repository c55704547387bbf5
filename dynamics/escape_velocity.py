"""Gravitational potential and escape velocity of the spherical mass models.

A mass model is a sum of spherical *components*, each with two methods on
3-D radii ``r`` [pc] (plain floats, internal units pc, solMass, km/s):

``enclosed_mass(r)``
    Mass inside ``r`` [solMass].
``potential(r)``
    ``Phi(r)`` [(km/s)^2], zero at infinity (negative).

:class:`ProfileComponent` wraps any dimensionless profile of
:mod:`mavispm.dynamics.tracers` (unit mass, unit scale radius: Plummer, Dehnen,
King, cusped) with a mass and a scale radius; :class:`PointMass` is a central
black hole. :class:`SphericalMassModel` adds components; its escape velocity is
``v_esc(r) = sqrt(-2 Phi(r))`` (escape to infinity: the deepest, conservative
choice for a cluster whose tidal boundary is not modelled). Any object with the
two methods (for example an extended dark component) can be added.

Dimensionless potential of a unit-mass profile with enclosed mass ``m(x)``::

    phi(x) = -int_x^inf m(x') / x'^2 dx' = -int_{ln x}^inf m(x') / x' d ln x'

computed once per profile (cached) with Gauss-Legendre panels uniform in ln x
(1,500 panels x 4 nodes) from 1e-7 scale radii to the tidal radius (King) or
1e6 scale radii, plus the tail ``-1 / x_out`` (all mass enclosed); it is
interpolated to any radius with 4-point Lagrange weights in ln x. Beyond the
grid ``phi = -1/x``; inside it the enclosed mass is continued as the power law
of the innermost panel. Accuracy: Plummer ``-1/sqrt(1 + x^2)`` to 1e-9 and
Dehnen ``-(1 - (x/(1+x))^(2-gamma))/(2-gamma)`` to 1e-8 (tests).

A conservative no-IMBH escape velocity at a projected radius ``R`` is taken
at the 3-D radius ``r = R`` (``v_esc`` decreases outwards, so ``r = R`` is the
maximum over the radii compatible with ``R``) and at a high quantile over
posterior samples of the no-IMBH models (:func:`escape_velocity_quantile`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import astropy.units as u
import numpy as np
from numpy.typing import ArrayLike

from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.jeans import G_PC_KMS2_MSUN
from mavispm.dynamics.tracers import Plummer

__all__ = [
    "PointMass",
    "PosteriorMassModel",
    "ProfileComponent",
    "SphericalMassModel",
    "dimensionless_potential",
    "escape_speed_at_projected",
    "escape_velocity",
    "escape_velocity_quantile",
    "escape_velocity_samples",
    "mass_model_from_sample",
    "posterior_mass_models",
    "potential_table",
]

#: Potential grid: panels uniform in ln x from _X_IN to the profile's outer radius.
_X_IN = 1e-7
_X_OUT = 1e6
_PANELS = 1500
_NODES = 4


@dataclass(frozen=True, eq=False)
class _PotentialTable:
    """``phi`` at the panel edges (uniform in ln x) of one unit profile."""

    ln_edges: np.ndarray
    phi: np.ndarray
    m_in: float
    slope_in: float

    def __call__(self, x):
        shape = np.shape(x)
        x = np.atleast_1d(np.asarray(x, dtype=float)).ravel()
        return self._evaluate(x).reshape(shape)

    def _evaluate(self, x):
        lnx = np.log(np.maximum(x, 1e-300))
        e = self.ln_edges
        idx, w = cubic_weights(e[0], e[1] - e[0], e.size, lnx)
        out = interpolate(self.phi, idx, w)
        x_out = np.exp(e[-1])
        out = np.where(x > x_out, -1.0 / np.maximum(x, x_out), out)
        below = lnx < e[0]
        if np.any(below):
            # m = m_in (x / x_in)^s inside the grid: phi(x) = phi(x_in) - m_in / x_in *
            # (1 - (x / x_in)^(s - 1)) / (s - 1)   (s -> 1: logarithm)
            x_in = np.exp(e[0])
            t = np.minimum(x, x_in) / x_in
            s1 = self.slope_in - 1.0
            with np.errstate(divide="ignore"):
                if abs(s1) > 1e-6:
                    extra = (1.0 - t**s1) / s1
                else:
                    extra = -np.log(np.maximum(t, 1e-300))
            out = np.where(below, self.phi[0] - self.m_in / x_in * extra, out)
        return out


#: Evaluators of the enclosed mass at the fixed table nodes, one per profile family.
_FAMILY_EVALUATORS: dict = {}


def _enclosed_at_nodes(profile, x, x_out):
    """Mass fraction at the table nodes; profiles of one family (e.g. every cusp slope and
    radius over one base) share a cached ``at_points`` evaluator (a few vector passes)."""
    family = getattr(profile, "family", None)
    if family is None or not hasattr(profile, "at_points"):
        return np.asarray(profile.enclosed(x), dtype=float)
    key = (family, x_out)
    if key not in _FAMILY_EVALUATORS:
        if len(_FAMILY_EVALUATORS) > 32:
            _FAMILY_EVALUATORS.clear()
        _FAMILY_EVALUATORS[key] = profile.at_points(x[:1], x)
    return np.asarray(_FAMILY_EVALUATORS[key](profile)[1], dtype=float)


@functools.lru_cache(maxsize=256)
def potential_table(profile) -> _PotentialTable:
    """Cached dimensionless potential table of a unit-mass, unit-scale-radius profile.

    Parameters
    ----------
    profile : tracers profile
        Any hashable object with ``enclosed(x)`` (mass fraction inside ``x``) and
        optionally ``tidal_radius`` (no mass beyond it).
    """
    x_out = float(getattr(profile, "tidal_radius", _X_OUT))
    edges = np.linspace(np.log(_X_IN), np.log(x_out), _PANELS + 1)
    nodes, weights = np.polynomial.legendre.leggauss(_NODES)
    mid = 0.5 * (edges[1:] + edges[:-1])
    half = 0.5 * np.diff(edges)
    lnx = mid[:, None] + half[:, None] * nodes[None, :]
    x = np.exp(lnx)
    m = _enclosed_at_nodes(profile, x.ravel(), x_out).reshape(x.shape)
    panels = np.sum(m / x * half[:, None] * weights[None, :], axis=1)
    m_out = float(np.asarray(profile.enclosed(np.array([x_out])))[0])
    tail = m_out / x_out
    # phi at edge k = -(tail + sum of panels k..end), summed from the outside in
    outer = np.concatenate([np.cumsum(panels[::-1])[::-1], [0.0]])
    phi = -(tail + outer)
    m_edges = np.asarray(profile.enclosed(np.exp(edges[:2])), dtype=float)
    m_in = float(m_edges[0])
    if m_edges[0] > 0 and m_edges[1] > 0:
        slope = float(np.log(m_edges[1] / m_edges[0]) / (edges[1] - edges[0]))
    else:
        slope = 3.0
    return _PotentialTable(edges, phi, m_in, min(max(slope, 0.5), 3.0))


def dimensionless_potential(profile, x: ArrayLike):
    """``phi(x)`` of a unit-mass profile in units of ``G M / a`` (zero at infinity).

    Parameters
    ----------
    profile : tracers profile
    x : array_like
        3-D radii in scale radii (>= 0).
    """
    return potential_table(profile)(x)


@dataclass(frozen=True)
class ProfileComponent:
    """A spherical component with a dimensionless profile, a mass and a scale radius.

    Parameters
    ----------
    profile : tracers profile
        Unit mass, unit scale radius (:mod:`mavispm.dynamics.tracers`).
    mass : float
        Total mass [solMass].
    scale_radius : float
        Scale radius [pc].
    """

    profile: object
    mass: float
    scale_radius: float

    def enclosed_mass(self, r: ArrayLike):
        """Mass inside ``r`` [pc] in solMass.

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Enclosed mass [solMass].
        """
        x = np.asarray(r, dtype=float) / self.scale_radius
        return self.mass * np.asarray(self.profile.enclosed(x), dtype=float)

    def potential(self, r: ArrayLike):
        """``Phi(r)`` [(km/s)^2], zero at infinity.

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Potential [(km/s)^2].
        """
        x = np.asarray(r, dtype=float) / self.scale_radius
        return (
            G_PC_KMS2_MSUN
            * self.mass
            / self.scale_radius
            * dimensionless_potential(self.profile, x)
        )


@dataclass(frozen=True)
class PointMass:
    """A central point mass [solMass] (the IMBH).

    Parameters
    ----------
    mass : float
        Mass [solMass].
    """

    mass: float

    def enclosed_mass(self, r: ArrayLike):
        """``mass`` at every ``r`` > 0 [solMass].

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Enclosed mass [solMass], ``r``'s shape.
        """
        return np.full(np.shape(r), float(self.mass))

    def potential(self, r: ArrayLike):
        """``-G M / r`` [(km/s)^2] (r clipped to 1e-12 pc).

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Potential [(km/s)^2].
        """
        r = np.maximum(np.asarray(r, dtype=float), 1e-12)
        return -G_PC_KMS2_MSUN * self.mass / r


@dataclass(frozen=True)
class SphericalMassModel:
    """Sum of spherical components (see the module docstring for the interface).

    Parameters
    ----------
    components : tuple
        Components with ``enclosed_mass(r)`` [solMass] and ``potential(r)`` [(km/s)^2] of
        radii [pc] (:class:`ProfileComponent`, :class:`PointMass`).
    """

    components: tuple

    def enclosed_mass(self, r: ArrayLike):
        """Total mass inside ``r`` [pc] in solMass.

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Enclosed mass [solMass].
        """
        return sum(
            (np.asarray(c.enclosed_mass(r), float) for c in self.components),
            np.zeros(np.shape(r)),
        )

    def potential(self, r: ArrayLike):
        """``Phi(r)`` [(km/s)^2], zero at infinity.

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Potential [(km/s)^2].
        """
        return sum(
            (np.asarray(c.potential(r), float) for c in self.components), np.zeros(np.shape(r))
        )

    def escape_speed(self, r: ArrayLike):
        """``sqrt(-2 Phi(r))`` [km/s] at 3-D radii ``r`` [pc] (floats).

        Parameters
        ----------
        r : array_like
            3-D radii [pc].

        Returns
        -------
        ndarray
            Escape speed [km/s].
        """
        return np.sqrt(np.maximum(-2.0 * self.potential(r), 0.0))


def escape_velocity(model, r) -> u.Quantity:
    """Escape velocity ``sqrt(-2 Phi(r))`` of a mass model.

    Parameters
    ----------
    model : SphericalMassModel (``potential`` of radii in pc) or any object whose
        ``potential`` takes a length Quantity (e.g. ``mass_models.MassModel``)
    r : Quantity
        3-D radii (length).

    Returns
    -------
    Quantity
        km/s.
    """
    r = u.Quantity(r, u.pc)
    if isinstance(model, SphericalMassModel):
        phi = model.potential(r.to_value(u.pc))
    else:
        phi = model.potential(r)
    phi = u.Quantity(phi, (u.km / u.s) ** 2).to_value((u.km / u.s) ** 2)
    return np.sqrt(np.maximum(-2.0 * phi, 0.0)) * (u.km / u.s)


def escape_velocity_samples(models: Sequence[SphericalMassModel], r_pc: ArrayLike) -> np.ndarray:
    """Escape speeds [km/s] of every model at radii ``r_pc``: shape ``(n_models, n_radii)``.

    Parameters
    ----------
    models : sequence of SphericalMassModel
        The mass models.
    r_pc : array_like
        3-D radii [pc].

    Returns
    -------
    ndarray, shape (n_models, n_radii)
        Escape speeds [km/s].
    """
    r_pc = np.atleast_1d(np.asarray(r_pc, dtype=float))
    return np.stack([np.sqrt(np.maximum(-2.0 * m.potential(r_pc), 0.0)) for m in models])


def escape_velocity_quantile(
    models: Sequence[SphericalMassModel], R: u.Quantity, quantile: float = 0.99
) -> u.Quantity:
    """Conservative escape velocity at projected radii ``R``.

    Taken at the 3-D radius ``r = R`` (the largest escape velocity of all radii
    compatible with ``R``) and at ``quantile`` over the models (posterior samples).

    Parameters
    ----------
    models : sequence of mass models
    R : Quantity
        Projected radii (length).
    quantile : float
        In (0, 1].

    Returns
    -------
    Quantity
        km/s, one per radius.
    """
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must be in (0, 1], got {quantile}")
    if len(models) == 0:
        raise ValueError("no mass models")
    samples = escape_velocity_samples(models, u.Quantity(R).to_value(u.pc))
    return np.quantile(samples, quantile, axis=0) * (u.km / u.s)


@dataclass(frozen=True)
class PosteriorMassModel:
    """One posterior sample's mass model and the distance it was fitted at.

    Parameters
    ----------
    model : SphericalMassModel
    distance : float
        [kpc]; converts projected radii in arcsec to pc for this sample.
    """

    model: SphericalMassModel
    distance: float

    def escape_speed_at(self, R_arcsec: ArrayLike):
        """Escape speed [km/s] at 3-D radius ``r = R`` for projected radii [arcsec].

        ``r = R`` is the smallest 3-D radius a star at projected radius ``R`` can have, so the
        escape speed is the largest possible there.

        Parameters
        ----------
        R_arcsec : array_like
            Projected radii [arcsec], converted with this sample's distance.

        Returns
        -------
        ndarray
            Escape speed [km/s].
        """
        from mavispm.dynamics.likelihood import PC_PER_ARCSEC_KPC

        r_pc = np.asarray(R_arcsec, dtype=float) * self.distance * PC_PER_ARCSEC_KPC
        return self.model.escape_speed(r_pc)


def escape_speed_at_projected(model, R_arcsec: ArrayLike, distance: float):
    """Escape speed [km/s] at ``r = R`` of any mass model, for projected radii in arcsec.

    Parameters
    ----------
    model : PosteriorMassModel, or any object with ``potential(r)``
        ``potential`` takes a length Quantity and returns ``(km/s)^2`` (a Quantity,
        as :class:`mavispm.dynamics.mass_models.MassModel`, or floats).
    R_arcsec : array_like
    distance : float
        [kpc], for models that do not carry their own.
    """
    if hasattr(model, "escape_speed_at"):
        return np.asarray(model.escape_speed_at(R_arcsec), dtype=float)
    from mavispm.dynamics.likelihood import PC_PER_ARCSEC_KPC

    r = np.asarray(R_arcsec, dtype=float) * distance * PC_PER_ARCSEC_KPC * u.pc
    return escape_velocity(model, r).to_value(u.km / u.s)


def mass_model_from_sample(likelihood, theta) -> PosteriorMassModel:
    """The mass model of one parameter vector of a dynamics fit.

    The cluster component has the likelihood's tracer profile for ``theta``
    (mass follows light; cusp and Dehnen slope included), mass ``10**log_mass``
    and scale radius ``10**log_scale_radius`` arcsec at the sample's distance;
    a ``bh_mass`` > 0 adds a central point mass, a ``dark_mass`` > 0 a dark
    Plummer sphere of scale ``10**log_dark_radius`` arcsec (the extended dark
    component of the dynamics fit; same names as :mod:`mavispm.dynamics.mass_models`).

    Parameters
    ----------
    likelihood : mavispm.dynamics.likelihood.DiscreteLikelihood
        Defines the parameter names and the profile family.
    theta : array_like
        Physical parameter vector in ``likelihood.names`` order.
    """
    from mavispm.dynamics.likelihood import PC_PER_ARCSEC_KPC

    names = likelihood.names
    theta = np.asarray(theta, dtype=float)
    dist = float(theta[names.index("distance")]) if "distance" in names else likelihood.distance
    a_pc = 10.0 ** theta[names.index("log_scale_radius")] * dist * PC_PER_ARCSEC_KPC
    comps = [
        ProfileComponent(likelihood.tracer_of(theta), 10.0 ** theta[names.index("log_mass")], a_pc)
    ]
    bh = float(theta[names.index("bh_mass")]) if "bh_mass" in names else 0.0
    if bh > 0:
        comps.append(PointMass(bh))
    dark = float(theta[names.index("dark_mass")]) if "dark_mass" in names else 0.0
    if dark > 0:  # extended dark Plummer sphere (log_dark_radius: log10 arcsec)
        b_pc = 10.0 ** theta[names.index("log_dark_radius")] * dist * PC_PER_ARCSEC_KPC
        comps.append(ProfileComponent(Plummer(), dark, b_pc))
    return PosteriorMassModel(SphericalMassModel(tuple(comps)), dist)


def posterior_mass_models(
    likelihood, samples, n_models: int = 100, seed: int = 0, drop_point_mass: bool = False
):
    """Mass models of up to ``n_models`` posterior samples (drawn without replacement).

    Parameters
    ----------
    likelihood : DiscreteLikelihood
    samples : ndarray, shape (n, n_params)
        Posterior samples in ``likelihood.names`` order.
    n_models : int
    seed : int
    drop_point_mass : bool
        Leave out the central point mass (the stellar and dark parts of an IMBH model).

    Returns
    -------
    list of PosteriorMassModel
    """
    samples = np.asarray(samples, dtype=float)
    if samples.ndim != 2 or samples.shape[0] == 0:
        raise ValueError("no posterior samples")
    rng = np.random.default_rng(seed)
    n = min(n_models, samples.shape[0])
    rows = np.sort(rng.choice(samples.shape[0], size=n, replace=False))
    picked = samples[rows].copy()
    if drop_point_mass and "bh_mass" in likelihood.names:
        picked[:, likelihood.names.index("bh_mass")] = 0.0
    return [mass_model_from_sample(likelihood, theta) for theta in picked]
