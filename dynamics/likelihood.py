"""Discrete (per-star) likelihood of a Jeans model with an optional star-count term.

For star ``i`` at sky position ``(x_i, y_i)`` with proper motion ``(mu_x, mu_y)``,
relative to the model centre ``(x0, y0)`` and systemic motion ``(mu_x0, mu_y0)``
(fitted nuisances, or fixed at 0), the projected radius ``R_i`` and the radial and
tangential components ``v_R, v_T`` with errors ``e_R, e_T`` give

    ln L = sum_i  ln p(v_R,i, v_T,i | R_i)                   (kinematics)
         + sum_i  ln [ Sigma(R_i) c(R_i) / N_field ]             (star counts, optional)

with ``p`` the mixture over the star's depth on the line of sight of Gaussian 3-D
velocities convolved with the errors (``velocity_law = "line_of_sight"``;
:mod:`mavispm.dynamics.line_of_sight`), or the Gaussian with the projected dispersions
``N(v_R | 0, sigma_R(R)^2 + e_R^2) N(v_T | 0, sigma_T(R)^2 + e_T^2)``
(``velocity_law = "gaussian"``), or that Gaussian's variances with a fitted excess
kurtosis ``kappa`` (``velocity_law = "free_kurtosis"``, :mod:`mavispm.dynamics.shape_law`;
parameter ``kappa``, or ``kappa_inner`` and ``kappa_outer`` linear in ``ln R`` between the
10th and 90th percentiles of the stars' radii about the field centre), or the
line-of-sight mixture with each depth node's Gaussian replaced by that two-Gaussian
family with one fitted local excess kurtosis ``kappa``
(``velocity_law = "line_of_sight_kurtosis"``, :mod:`mavispm.dynamics.line_of_sight_kurtosis`).
One likelihood has one law; the stage's default weighs the free-kurtosis and line-of-sight
laws by their evidences (:func:`mavispm.dynamics.fit.fit_models`).

``N_field = int_field Sigma c dA`` is the tracer number inside the circular
field of radius ``R_field`` about the *field* centre (exact for a model centre
offset by ``d``: the fraction of the ring at ``R`` inside the field is
``arccos((R^2 + d^2 - R_field^2) / (2 R d)) / pi`` for ``|R_field - d| < R < R_field + d``),
and ``c(R)`` is the sample's completeness against radius (1 unless given). The
``c(R_i)`` factor of each star does not depend on the parameters and is dropped.

When the centre moves, the errors are rotated with the radial direction:
``e_R'^2 = e_R^2 cos^2 d + e_T^2 sin^2 d`` (``d`` the angle between the old and new
radial directions; the R/T error covariance is neglected).

Model parameters (physical): ``log_mass`` (log10 solMass), ``log_scale_radius``
(log10 arcsec), optionally ``gamma`` (cusp or Dehnen slope) and ``log_cusp_radius``
(log10 arcsec), ``bh_mass`` (solMass), ``dark_mass`` (solMass) with
``log_dark_radius`` (log10 arcsec), ``beta`` or ``log_anisotropy_radius`` (log10
arcsec, Osipkov-Merritt; with ``beta_0`` and ``beta_inf``: the general profile; neither:
isotropic), ``distance`` (kpc), ``x0``, ``y0`` (arcsec), ``pm_x0``,
``pm_y0`` (mas/yr).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavispm.core.errors import InputError
from mavispm.dynamics.anisotropy import Anisotropy, osipkov_merritt
from mavispm.dynamics.anisotropy import constant as constant_anisotropy
from mavispm.dynamics.field_counts import ln_field_number
from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.jeans import G_PC_KMS2_MSUN, KMS_PER_MASYR_KPC, JeansProjector
from mavispm.dynamics.line_of_sight import mixture_star_sums, mixture_star_sums_about
from mavispm.dynamics.line_of_sight_kurtosis import (
    kurtosis_mixture_star_sums,
    kurtosis_mixture_star_sums_about,
)
from mavispm.dynamics.shape_law import KAPPA_LIMITS, shape_star_sums, shape_star_sums_about
from mavispm.dynamics.star_sums import star_sums, star_sums_about, stars_about
from mavispm.dynamics.tracers import make_tracer

__all__ = [
    "VELOCITY_LAWS",
    "DEPTH_MIXTURE_LAWS",
    "DiscreteLikelihood",
    "PC_PER_ARCSEC_KPC",
    "StarSample",
]

#: parsec per (arcsec * kpc)
PC_PER_ARCSEC_KPC = 1e3 * np.pi / (180.0 * 3600.0)
_LN_2PI = np.log(2.0 * np.pi)
_GL16 = np.polynomial.legendre.leggauss(16)
#: Proper-motion distributions of a star at a projected radius (see DiscreteLikelihood).
VELOCITY_LAWS = ("line_of_sight", "gaussian", "free_kurtosis", "line_of_sight_kurtosis")
#: The laws whose likelihood is a mixture over each star's depth on the line of sight (the
#: dearest: on the ngc3201-nbody validation matrix 2.8-4.3x ``free_kurtosis``'s CPU per
#: trial; docs/dynamics.md).
DEPTH_MIXTURE_LAWS = ("line_of_sight", "line_of_sight_kurtosis")


@dataclass(frozen=True)
class StarSample:
    """Stars used in the fit (plain floats in fixed units).

    Parameters
    ----------
    R : ndarray
        Projected radius about the field centre [arcsec] (already clipped to ``min_radius``).
    v_r, v_t : ndarray
        Radial / tangential proper motions about the field centre [mas/yr].
    e_r, e_t : ndarray
        Their errors [mas/yr].
    field_radius : float
        Radius of the circular field the stars were selected in [arcsec].
    x, y : ndarray, optional
        Sky positions [arcsec] about the field centre; needed to fit the centre or
        the systemic motion.
    """

    R: np.ndarray
    v_r: np.ndarray
    v_t: np.ndarray
    e_r: np.ndarray
    e_t: np.ndarray
    field_radius: float
    x: np.ndarray | None = None
    y: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.R)
        names = ["R", "v_r", "v_t", "e_r", "e_t"]
        if (self.x is None) != (self.y is None):
            raise InputError("x and y go together", column="x/y")
        if self.x is not None:
            names += ["x", "y"]
        for name in names:
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (n,):
                raise InputError(f"expected {n} values, got shape {arr.shape}", column=name)
            if not np.all(np.isfinite(arr)):
                raise InputError("non-finite values (NaN or inf)", column=name)
            if name in ("R", "e_r", "e_t") and np.any(arr < 0):
                raise InputError("negative values", column=name)
        if n == 0:
            raise InputError("no stars to fit")
        if not (np.isfinite(self.field_radius) and self.field_radius > 0):
            raise InputError(f"field radius must be > 0, got {self.field_radius}")


class DiscreteLikelihood:
    """Per-star Jeans likelihood, evaluated on a radial grid and interpolated.

    Parameters
    ----------
    stars : StarSample
    names : sequence of str
        Parameter order of the vectors passed to :meth:`__call__`.
    tracer : str
        Tracer profile name ("plummer", "dehnen", "king62"); the cluster's mass has its shape.
    gamma, concentration : float
        Fixed Dehnen slope (without a ``gamma`` parameter) / King62 concentration.
    distance : float
        Distance [kpc] used when ``distance`` is not a parameter.
    scale_radius_range : (float, float)
        Prior range of the scale radius [arcsec]; sets the grid in ``R / a``.
    min_radius : float
        Radii are clipped to at least this [arcsec] (guards ``R = 0``).
    grid_size, n_panels, n_gl, x_max, points_per_efold
        Output grid points in ``ln(R / a)`` and the projection's quadrature and
        radial grid (see JeansProjector).
    star_counts : bool
        Include the star-count term.
    completeness : (radii, values), optional
        Completeness of the sample against projected radius [arcsec] (linear
        interpolation, constant beyond the ends); used by the star-count term.
    velocity_law : {"line_of_sight", "gaussian", "free_kurtosis", "line_of_sight_kurtosis"}
        Each star's proper-motion distribution (the default is the stage's,
        :class:`~mavispm.dynamics.settings.DynamicsSettings`): the projected dispersions
        with a fitted excess kurtosis (:mod:`mavispm.dynamics.shape_law`; parameters
        ``kappa`` or ``kappa_inner`` and ``kappa_outer``; without them kappa = 0, the
        Gaussian law), the mixture over its depth on the line of sight of Gaussian 3-D
        velocities (:mod:`mavispm.dynamics.line_of_sight`), a Gaussian with the projected
        dispersions (calibrated on equilibrium velocities, too narrow on Gaussian 3-D
        ones: docs/dynamics.md), or
        the line-of-sight mixture with each node's Gaussian replaced by that family with
        one fitted local excess kurtosis ``kappa``
        (:mod:`mavispm.dynamics.line_of_sight_kurtosis`; kappa = 0: the line-of-sight law).
    line_of_sight_nodes : int
        Gauss-Legendre nodes of the line-of-sight mixture (accuracy knob).
    """

    def __init__(
        self,
        stars: StarSample,
        names,
        tracer: str = "plummer",
        gamma: float = 1.0,
        concentration: float = 1.5,
        distance: float = 5.0,
        scale_radius_range=(1.0, 1000.0),
        min_radius: float = 0.01,
        grid_size: int = 48,
        n_panels: int = 12,
        n_gl: int = 6,
        x_max: float = 1e4,
        star_counts: bool = True,
        points_per_efold: int = 24,
        completeness=None,
        velocity_law: str = "free_kurtosis",
        line_of_sight_nodes: int = 16,
    ):
        self.stars = stars
        self.names = list(names)
        self._idx = {n: i for i, n in enumerate(self.names)}
        self.tracer_name = tracer
        self.gamma = gamma
        self.concentration = concentration
        self.distance = distance
        self.star_counts = star_counts
        self.min_radius = max(min_radius, 1e-6)
        if velocity_law not in VELOCITY_LAWS:
            raise InputError(
                f"velocity_law must be one of {', '.join(VELOCITY_LAWS)}, got {velocity_law!r}"
            )
        if line_of_sight_nodes < 2:
            raise InputError(f"line_of_sight_nodes must be >= 2, got {line_of_sight_nodes}")
        self.velocity_law = velocity_law
        self.line_of_sight_nodes = int(line_of_sight_nodes)
        self._fixed_tracer = make_tracer(tracer, gamma, concentration)
        for req in ("log_mass", "log_scale_radius"):
            if req not in self._idx:
                raise ValueError(f"parameter {req!r} is required")
        if "beta" in self._idx and "log_anisotropy_radius" in self._idx:
            raise ValueError(
                "give 'beta' or 'log_anisotropy_radius', not both (neither: isotropic)"
            )
        if ("beta_0" in self._idx) != ("beta_inf" in self._idx) or (
            "beta_0" in self._idx and "log_anisotropy_radius" not in self._idx
        ):
            raise ValueError("'beta_0', 'beta_inf' and 'log_anisotropy_radius' go together")
        self._moving = any(n in self._idx for n in ("x0", "y0", "pm_x0", "pm_y0"))
        if self._moving and stars.x is None:
            raise InputError("fitting the centre or systemic motion needs star positions x, y")
        a_lo, a_hi = scale_radius_range
        self._log_a_range = (np.log10(a_lo) - 1e-9, np.log10(a_hi) + 1e-9)
        r_lo = self.min_radius
        self.lnR = np.log(np.maximum(stars.R, r_lo))
        x_lo = r_lo / a_hi / 1.5
        x_hi = stars.field_radius / a_lo * 1.5
        if x_hi >= x_max / 10:
            raise InputError(
                f"field radius / smallest scale radius = {x_hi:.3g} is too close to the "
                f"projection truncation x_max = {x_max:g}; raise the scale-radius prior minimum"
            )
        if grid_size < 8:
            raise InputError(f"grid_size must be >= 8, got {grid_size}")
        self.lnX_grid = np.linspace(np.log(x_lo), np.log(x_hi), grid_size)
        self.step = self.lnX_grid[1] - self.lnX_grid[0]
        self.projector = JeansProjector(
            np.exp(self.lnX_grid),
            x_max=x_max,
            n_panels=n_panels,
            n_gl=n_gl,
            points_per_efold=points_per_efold,
        )
        self._v2 = np.ascontiguousarray(np.stack([stars.v_r**2, stars.v_t**2]), dtype=float)
        self._e2 = np.ascontiguousarray(np.stack([stars.e_r**2, stars.e_t**2]), dtype=float)
        if stars.x is not None:
            x, y = (np.ascontiguousarray(v, dtype=float) for v in (stars.x, stars.y))
            self._xy = (x, y)
            R = np.maximum(np.hypot(x, y), 1e-12)
            cx, sy = x / R, y / R
            self._pm_x = stars.v_r * cx - stars.v_t * sy
            self._pm_y = stars.v_r * sy + stars.v_t * cx
            self._cs = (cx, sy)
        self._ln_field = np.log(stars.field_radius)
        self.completeness = None
        if completeness is not None:
            r, c = (np.asarray(v, dtype=float) for v in completeness)
            self.completeness = (r, c)
        empty = np.zeros(0)
        self._comp_r, self._comp_c = self.completeness or (empty, empty)
        self.n_stars = len(stars.R)
        if "kappa" in self._idx and ("kappa_inner" in self._idx or "kappa_outer" in self._idx):
            raise ValueError("give 'kappa' or 'kappa_inner' and 'kappa_outer', not both")
        if ("kappa_inner" in self._idx) != ("kappa_outer" in self._idx):
            raise ValueError("'kappa_inner' and 'kappa_outer' go together")
        lo, hi = np.log(np.percentile(np.maximum(stars.R, r_lo), [10.0, 90.0]))
        #: ln R [ln arcsec] where kappa_inner and kappa_outer hold (about the field centre)
        self.kappa_anchors = (float(lo), float(max(hi, lo + 1e-6)))

    def _value(self, theta, name, default):
        i = self._idx.get(name)
        return default if i is None else theta[i]

    def tracer_of(self, theta):
        """Tracer profile (scale radius 1) of parameter vector ``theta``.

        Parameters
        ----------
        theta : array_like
            Physical parameter vector.

        Returns
        -------
        tracer profile
            The cusped tracer (free cusp radius and slope), a Dehnen profile (free slope) or
            the fixed tracer.
        """
        if "log_cusp_radius" in self._idx:
            a = 10.0 ** theta[self._idx["log_scale_radius"]]
            x_c = 10.0 ** theta[self._idx["log_cusp_radius"]] / a
            g = theta[self._idx["gamma"]]
            return make_tracer(self.tracer_name, g, self.concentration, cusp_radius=x_c)
        if "gamma" in self._idx:
            return make_tracer("dehnen", theta[self._idx["gamma"]])
        return self._fixed_tracer

    def anisotropy_of(self, theta):
        """Anisotropy profile (radii in scale radii) of ``theta``.

        ``beta`` alone: constant; ``log_anisotropy_radius`` alone: Osipkov-Merritt;
        ``beta_0``, ``beta_inf`` and ``log_anisotropy_radius``: the general profile
        ``beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2)``; none: isotropic.

        Parameters
        ----------
        theta : array_like
            Physical parameter vector.

        Returns
        -------
        Anisotropy
            The profile the parameters describe (above).
        """
        if "beta" in self._idx:
            return constant_anisotropy(theta[self._idx["beta"]])
        if "log_anisotropy_radius" not in self._idx:
            return constant_anisotropy(0.0)
        ln_a = np.log(10.0) * theta[self._idx["log_scale_radius"]]
        r_a = 10.0 ** theta[self._idx["log_anisotropy_radius"]] / np.exp(ln_a)
        if "beta_0" in self._idx:
            return Anisotropy(theta[self._idx["beta_0"]], theta[self._idx["beta_inf"]], r_a)
        return osipkov_merritt(r_a)

    def model_on_grid(self, theta):
        """Grid quantities for physical parameter vector ``theta``.

        Parameters
        ----------
        theta : array_like
            Physical parameter vector.

        Returns
        -------
        lnX : ndarray
            ln(R / a) grid.
        sigma2 : ndarray, shape (2, n)
            Radial and tangential model PM dispersion squared [(mas/yr)^2].
        ln_sigma, ln_proj : ndarray
            ln surface density (a = 1, unit mass) and ln projected mass fraction.
        """
        b, scale, (mass, bh, dark) = self._mass_model(theta)
        mom = self.projector.moments(self.tracer_of(theta), self.anisotropy_of(theta), b)
        radial = mass * mom.radial_cluster + bh * mom.radial_bh
        tangential = mass * mom.tangential_cluster + bh * mom.tangential_bh
        if b is not None:
            radial = radial + dark * mom.radial_dark
            tangential = tangential + dark * mom.tangential_dark
        s2 = scale * np.stack([radial, tangential])
        tiny = np.finfo(float).tiny
        return (
            self.lnX_grid,
            np.maximum(s2, tiny),
            np.log(np.maximum(mom.surface_density, tiny)),
            np.log(np.maximum(mom.projected_enclosed, tiny)),
        )

    def _mass_model(self, theta):
        """Dark radius [scale radii] (None), ``G / a`` [(mas/yr)^2 per solMass] and the
        cluster, point and dark masses [solMass] of ``theta``."""
        ln_a = np.log(10.0) * theta[self._idx["log_scale_radius"]]
        dist = self._value(theta, "distance", self.distance)
        b = None
        if "log_dark_radius" in self._idx:
            b = 10.0 ** theta[self._idx["log_dark_radius"]] / np.exp(ln_a)
        a_pc = np.exp(ln_a) * dist * PC_PER_ARCSEC_KPC
        conv = (KMS_PER_MASYR_KPC * dist) ** 2
        masses = (
            10.0 ** theta[self._idx["log_mass"]],
            self._value(theta, "bh_mass", 0.0),
            self._value(theta, "dark_mass", 0.0),
        )
        return b, G_PC_KMS2_MSUN / a_pc / conv, masses

    def log_model_on_grid(self, theta):
        """ln of the grid quantities of :meth:`model_on_grid` (its reference), compiled.

        Parameters
        ----------
        theta : array_like
            Physical parameter vector.

        Returns
        -------
        ln_s2 : ndarray, shape (2, n)
            ln radial and tangential model PM dispersion squared [ln (mas/yr)^2].
        ln_sigma, ln_proj : ndarray
            ln surface density (a = 1, unit mass) and ln projected mass fraction.
        """
        b, scale, masses = self._mass_model(theta)
        weights = np.multiply(scale, masses)
        return self.projector.log_dispersions(
            self.tracer_of(theta), self.anisotropy_of(theta), b, weights
        )

    def line_of_sight_on_grid(self, theta):
        """Line-of-sight mixture components on the grid for ``theta``, compiled.

        Parameters
        ----------
        theta : array_like
            Physical parameter vector.

        Returns
        -------
        mix_w, s2_r, s2_t : ndarray (M, K)
            Component weights and sky-radial / sky-tangential variances [(mas/yr)^2]
            (:meth:`mavispm.dynamics.jeans.JeansProjector.line_of_sight`).
        ln_sigma, ln_proj : ndarray (M,)
            ln surface density (a = 1, unit mass) and ln projected mass fraction.
        """
        b, scale, masses = self._mass_model(theta)
        return self.projector.line_of_sight(
            self.tracer_of(theta),
            self.anisotropy_of(theta),
            b,
            np.multiply(scale, masses),
            self.line_of_sight_nodes,
        )

    def dispersion_at(self, theta, R):
        """Model radial and tangential PM dispersions [mas/yr] at radii ``R`` [arcsec].

        Parameters
        ----------
        theta : array_like
            Physical parameter vector.
        R : array_like
            Projected radii [arcsec].

        Returns
        -------
        ndarray, shape (2, len(R))
            Radial and tangential dispersion [mas/yr].
        """
        lnX, s2, _, _ = self.model_on_grid(theta)
        ln_a = np.log(10.0) * theta[self._idx["log_scale_radius"]]
        idx, w = cubic_weights(lnX[0], self.step, lnX.size, np.log(np.asarray(R)) - ln_a)
        return np.sqrt(np.exp(interpolate(np.log(s2), idx, w)))

    def _stars_about(self, theta):
        """ln R, v^2 and e^2 of the stars about the model centre and systemic motion."""
        if not self._moving:
            return self.lnR, self._v2, self._e2
        get = self._value
        return stars_about(
            self.stars.x,
            self.stars.y,
            self._pm_x,
            self._pm_y,
            self._cs[0],
            self._cs[1],
            self._e2[0],
            self._e2[1],
            get(theta, "x0", 0.0),
            get(theta, "y0", 0.0),
            get(theta, "pm_x0", 0.0),
            get(theta, "pm_y0", 0.0),
            self.min_radius,
        )

    def _about_args(self, theta, ln_a):
        """Leading arguments of the compiled ``*_about`` sums: the stars, the model centre and
        systemic motion of ``theta``, the radius floor and ``ln a``."""
        get = self._value
        return (
            self._xy[0],
            self._xy[1],
            self._pm_x,
            self._pm_y,
            self._cs[0],
            self._cs[1],
            self._e2[0],
            self._e2[1],
            float(get(theta, "x0", 0.0)),
            float(get(theta, "y0", 0.0)),
            float(get(theta, "pm_x0", 0.0)),
            float(get(theta, "pm_y0", 0.0)),
            self.min_radius,
            float(ln_a),
        )

    def _star_sums(self, theta, ln_a, ln_s2, ln_sig):
        """``chi`` and the summed ln surface density of :func:`star_sums` for the stars
        about the model centre and systemic motion of ``theta`` (one compiled pass)."""
        x0 = self.lnX_grid[0]
        if not self._moving:
            return star_sums(self.lnR - ln_a, x0, self.step, ln_s2, ln_sig, self._v2, self._e2)
        return star_sums_about(
            *self._about_args(theta, ln_a),
            x0,
            self.step,
            ln_s2,
            ln_sig,
        )

    def kappa_par(self, theta):
        """``kappa_inner, kappa_outer, ln R_lo, ln R_hi`` of ``theta`` for the compiled
        sums of :mod:`mavispm.dynamics.shape_law` (a global ``kappa``: both the same; no
        kappa parameter: 0, the Gaussian law)."""
        if "kappa_inner" in self._idx:
            k_in, k_out = theta[self._idx["kappa_inner"]], theta[self._idx["kappa_outer"]]
        else:
            k_in = k_out = self._value(theta, "kappa", 0.0)
        return np.array([k_in, k_out, *self.kappa_anchors], dtype=float)

    def _shape_sums(self, theta, ln_a, ln_s2, ln_sig):
        """``chi`` (``-sum(2 ln p + ln 2 pi)``) and the summed ln surface density of the
        free-kurtosis law for the stars about the model centre and systemic motion."""
        x0 = self.lnX_grid[0]
        kpar = self.kappa_par(theta)
        if not self._moving:
            return shape_star_sums(
                self.lnR - ln_a, float(ln_a), x0, self.step, ln_s2, ln_sig, self._v2, self._e2, kpar
            )
        return shape_star_sums_about(
            *self._about_args(theta, ln_a), x0, self.step, ln_s2, ln_sig, kpar
        )

    def _mixture_sums(self, theta, ln_a, mix_w, s2_r, s2_t, ln_sig):
        """Summed ln mixture density and ln surface density of the stars about the model
        centre and systemic motion of ``theta`` (:func:`mixture_star_sums`)."""
        x0 = self.lnX_grid[0]
        if self.velocity_law == "line_of_sight_kurtosis":
            kappa = float(self._value(theta, "kappa", 0.0))
            if not self._moving:
                return kurtosis_mixture_star_sums(
                    self.lnR - ln_a, x0, self.step, mix_w, s2_r, s2_t, ln_sig,
                    self._v2, self._e2, kappa,
                )  # fmt: skip
            return kurtosis_mixture_star_sums_about(
                *self._about_args(theta, ln_a), x0, self.step, mix_w, s2_r, s2_t, ln_sig, kappa
            )
        if not self._moving:
            return mixture_star_sums(
                self.lnR - ln_a, x0, self.step, mix_w, s2_r, s2_t, ln_sig, self._v2, self._e2
            )
        return mixture_star_sums_about(
            *self._about_args(theta, ln_a),
            x0,
            self.step,
            mix_w,
            s2_r,
            s2_t,
            ln_sig,
        )

    def _stars_about_numpy(self, theta):
        """Reference implementation of :meth:`_stars_about` (numpy, for the tests)."""
        s = self.stars
        dx = s.x - self._value(theta, "x0", 0.0)
        dy = s.y - self._value(theta, "y0", 0.0)
        R = np.maximum(np.hypot(dx, dy), 1e-12)
        c, si = dx / R, dy / R
        px = self._pm_x - self._value(theta, "pm_x0", 0.0)
        py = self._pm_y - self._value(theta, "pm_y0", 0.0)
        v_r = px * c + py * si
        v_t = -px * si + py * c
        cx, sy = self._cs
        cos_d = cx * c + sy * si
        cos2 = cos_d * cos_d
        sin2 = 1.0 - cos2
        er2, et2 = s.e_r**2, s.e_t**2
        v2 = np.stack([v_r * v_r, v_t * v_t])
        e2 = np.stack([er2 * cos2 + et2 * sin2, er2 * sin2 + et2 * cos2])
        return np.log(np.maximum(R, self.min_radius)), v2, e2

    def ln_field_norm(self, ln_a, offset, ln_sig, ln_proj):
        """ln of the tracer number (unit mass, completeness-weighted) inside the field.

        Parameters
        ----------
        ln_a : float
            ln scale radius [ln arcsec].
        offset : float
            Distance of the model centre from the field centre [arcsec].
        ln_sig, ln_proj : ndarray
            ln surface density and ln projected mass fraction on the grid.
        """
        return ln_field_number(
            self.lnX_grid[0],
            self.step,
            ln_sig,
            ln_proj,
            float(ln_a),
            float(offset),
            float(self.stars.field_radius),
            self._comp_r,
            self._comp_c,
            _GL16[0],
            _GL16[1],
        )

    def __call__(self, theta) -> float:
        """ln L for physical parameter vector ``theta`` (finite, or -inf if invalid)."""
        theta = np.asarray(theta, dtype=float)
        if not np.isfinite(theta).all():  # e.g. a NaN cusp or dark radius: no model
            return -np.inf
        if "beta" in self._idx and not theta[self._idx["beta"]] < 1.0:
            return -np.inf
        if "beta_0" in self._idx and not (
            theta[self._idx["beta_0"]] < 1.0 and theta[self._idx["beta_inf"]] <= 1.0
        ):
            return -np.inf
        if self._value(theta, "bh_mass", 0.0) < 0 or self._value(theta, "dark_mass", 0.0) < 0:
            return -np.inf
        if "distance" in self._idx and not theta[self._idx["distance"]] > 0:
            return -np.inf
        if "gamma" in self._idx and not 0 <= theta[self._idx["gamma"]] < 2.5:
            return -np.inf
        log_a = theta[self._idx["log_scale_radius"]]
        if not self._log_a_range[0] <= log_a <= self._log_a_range[1]:
            return -np.inf  # outside the radial grid (Gaussian prior tails)
        for name in ("kappa", "kappa_inner", "kappa_outer"):
            if name in self._idx and not KAPPA_LIMITS[0] < theta[self._idx[name]] < KAPPA_LIMITS[1]:
                return -np.inf
        offset = float(np.hypot(self._value(theta, "x0", 0.0), self._value(theta, "y0", 0.0)))
        if offset >= 0.5 * self.stars.field_radius:
            return -np.inf
        ln_a = np.log(10.0) * log_a
        if self.velocity_law in DEPTH_MIXTURE_LAWS:
            mix_w, s2_r, s2_t, ln_sig, ln_proj = self.line_of_sight_on_grid(theta)
            lnl, ln_sigma_stars = self._mixture_sums(theta, ln_a, mix_w, s2_r, s2_t, ln_sig)
        else:
            ln_s2, ln_sig, ln_proj = self.log_model_on_grid(theta)
            if self.velocity_law == "free_kurtosis":
                chi, ln_sigma_stars = self._shape_sums(theta, ln_a, ln_s2, ln_sig)
            else:
                chi, ln_sigma_stars = self._star_sums(theta, ln_a, ln_s2, ln_sig)
            lnl = -0.5 * chi - self.n_stars * _LN_2PI
        if self.star_counts:
            ln_norm = self.ln_field_norm(ln_a, offset, ln_sig, ln_proj)
            lnl += ln_sigma_stars - self.n_stars * (2.0 * ln_a + ln_norm)
        return lnl if np.isfinite(lnl) else -np.inf
