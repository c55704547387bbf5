"""Spherical Jeans models projected onto the sky.

For a tracer density ``nu(r)`` in the potential of a cluster of mass ``M`` (whose
mass has the tracer's shape ``m(r)``), a central point mass ``M_bh`` and a dark
Plummer sphere of mass ``M_dark`` and scale ``b`` (a remnant or stellar-mass
black-hole subsystem that holds no tracers), with anisotropy ``beta(r) = 1 -
sigma_t^2 / sigma_r^2`` and its integrating factor ``g(r)`` (see
:mod:`mavispm.dynamics.anisotropy`; ``g = r^(2 beta)`` for constant beta), the Jeans
equation gives

    nu sigma_r^2 (r) = g(r)^-1 int_r^inf g(r') nu(r') G [M m(r') + M_bh + M_dark m_P(r'/b)] / r'^2 dr'

and the proper-motion dispersions projected along the projected radius ``R``
(radial, ``R``) and perpendicular to it (tangential, ``T``) are

    Sigma sigma_R^2 = 2 int_R^inf [(1 - beta(r)) + beta(r) R^2 / r^2] nu sigma_r^2 r dr / sqrt(r^2 - R^2)
    Sigma sigma_T^2 = 2 int_R^inf (1 - beta(r)) nu sigma_r^2 r dr / sqrt(r^2 - R^2).

Numerics (all in units of the scale radius, G = M = 1; the cluster and point-mass
terms are kept separate so that ``sigma^2 = G/a (M S_cl + M_bh S_bh + M_dark S_dark)``):

* Projection: ``r = R cosh t`` removes the inverse-square-root singularity;
  composite Gauss-Legendre panels in ``t`` up to ``x_max`` (>= 1e4 scale radii).
  The nodes depend only on the output radii and are built once (cached).
* Radial Jeans integrals are accumulated from the outside in over the sorted
  union of all projection nodes (2-point Gauss-Legendre in ``ln r`` within each
  gap), starting from the analytic power-law tail beyond ``x_max``. Every term
  is positive, so there is no cancellation; the point-mass term near the centre
  (``nu sigma^2 ~ 1/r``) is as accurate as the outer one.
* The surface density is projected with the same nodes, so quadrature errors
  largely cancel in ``sigma^2 = (Sigma sigma^2) / Sigma``.
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np

from mavispm.dynamics.anisotropy import Anisotropy
from mavispm.dynamics.anisotropy import constant as constant_anisotropy
from mavispm.dynamics.interpolation import cubic_weights
from mavispm.dynamics.jeans_kernel import log_dispersions, row_ranges
from mavispm.dynamics.line_of_sight import line_of_sight_model, line_of_sight_nodes
from mavispm.dynamics.tracers import Plummer

__all__ = [
    "G_PC_KMS2_MSUN",
    "JeansProjector",
    "KMS_PER_MASYR_KPC",
    "ProjectedMoments",
    "projected_dispersion",
]

#: Gravitational constant in pc (km/s)^2 / Msun.
G_PC_KMS2_MSUN = 4.300917270e-3
#: km/s per (mas/yr * kpc).
KMS_PER_MASYR_KPC = 4.740470463533348


@dataclass
class ProjectedMoments:
    """Dimensionless projected moments on the output radii (G = M = a = 1).

    Parameters
    ----------
    X : ndarray
        Projected radii in scale radii.
    surface_density : ndarray
        ``Sigma(X)`` of the tracer (unit mass).
    projected_enclosed : ndarray
        Tracer fraction inside projected radius ``X``.
    radial_cluster, radial_bh, tangential_cluster, tangential_bh : ndarray
        ``sigma_R^2`` and ``sigma_T^2`` per unit cluster mass and per unit point
        mass; physical ``sigma^2 = G / a * (M * cluster + M_bh * bh + M_dark * dark)``.
    radial_dark, tangential_dark : ndarray
        The same per unit mass of the dark Plummer component (zero without one).
    """

    X: np.ndarray
    surface_density: np.ndarray
    projected_enclosed: np.ndarray
    radial_cluster: np.ndarray
    radial_bh: np.ndarray
    tangential_cluster: np.ndarray
    tangential_bh: np.ndarray
    radial_dark: np.ndarray | None = None
    tangential_dark: np.ndarray | None = None


class JeansProjector:
    """Projected Jeans moments at fixed output radii, as fixed linear operators on a radial grid.

    Everything that depends only on the output radii is built once: a uniform
    grid in ``ln r`` from the smallest output radius to ``x_max``
    (``points_per_efold`` points per e-fold), and dense projection matrices that
    map values of a function on that grid (cubic Lagrange interpolation in
    ``ln r``) to its Abel-type projections at the output radii, integrated with
    ``r = R cosh t`` on ``n_panels`` x ``n_gl`` Gauss-Legendre nodes. A call of
    :meth:`moments` then costs one tracer evaluation on the grid, three
    cumulative sums (the radial Jeans integrals) and one small matrix product.

    Parameters
    ----------
    X : array_like
        Output projected radii in scale radii (> 0).
    x_max : float
        Outer truncation of the projection in scale radii (>= 1e4 recommended);
        the radial Jeans integral adds the analytic tail beyond it.
    n_panels : int
        Gauss-Legendre panels in ``t`` per output radius (built once).
    n_gl : int
        Nodes per panel.
    points_per_efold : int
        Radial grid density [points per unit ``ln r``]; the accuracy knob of the
        radial integrals and of the interpolation between grid and projection nodes.
    """

    def __init__(
        self,
        X,
        x_max: float = 1e4,
        n_panels: int = 24,
        n_gl: int = 6,
        points_per_efold: int = 24,
    ):
        X = np.atleast_1d(np.asarray(X, dtype=float))
        if np.any(~np.isfinite(X)) or np.any(X <= 0) or np.any(X >= x_max):
            raise ValueError("output radii must be finite, > 0 and < x_max")
        if points_per_efold < 4:
            raise ValueError(f"points_per_efold must be >= 4, got {points_per_efold}")
        self.X = X
        self.x_max = float(x_max)
        # radial grid, uniform in ln r, from the smallest output radius to x_max
        ln_lo, ln_hi = np.log(X.min()) - 1e-9, np.log(self.x_max)
        n_r = max(int(np.ceil((ln_hi - ln_lo) * points_per_efold)) + 1, 8)
        self.ln_r = np.linspace(ln_lo, ln_hi, n_r)
        self.step = self.ln_r[1] - self.ln_r[0]
        self.r = np.exp(self.ln_r)
        # projection nodes r = X cosh t, t in [0, arccosh(x_max / X)]
        gl_t, gl_w = np.polynomial.legendre.leggauss(n_gl)
        tmax = np.arccosh(self.x_max / X)  # (M,)
        edges = np.linspace(0.0, 1.0, n_panels + 1)
        mid = 0.5 * (edges[1:] + edges[:-1])
        half = 0.5 * np.diff(edges)
        unit_t = (mid[:, None] + half[:, None] * gl_t[None, :]).ravel()
        unit_w = (half[:, None] * gl_w[None, :]).ravel()
        t = tmax[:, None] * unit_t[None, :]  # (M, K)
        w = tmax[:, None] * unit_w[None, :]
        cosh_t = np.cosh(t)
        w_proj = 2.0 * w * X[:, None] * cosh_t  # Sigma-type weights
        # 4 pi X^3 int nu cosh t sinh t e^-t dt: mass inside the cylinder outside the sphere
        w_cyl = 4.0 * np.pi * X[:, None] ** 3 * w * cosh_t * np.sinh(t) * np.exp(-t)
        idx, wi = cubic_weights(ln_lo, self.step, n_r, np.log(X[:, None] * cosh_t).ravel())
        rows = np.repeat(np.arange(X.size), t.shape[1])

        def operator(node_weights):
            out = np.zeros((X.size, n_r))
            for c in range(4):
                np.add.at(out, (rows, idx[c]), node_weights.ravel() * wi[c])
            return out

        self._k0 = operator(w_proj)  # int f
        self._k2 = operator(w_proj / cosh_t**2)  # int f R^2 / r^2
        self._kc = operator(w_cyl)
        self._lo, self._hi = row_ranges(self._k0, self._k2, self._kc)
        self._evaluators = {}
        self._los_nodes = {}
        self._cache_key = None
        self._cache = None

    def _tracer_tables(self, tracer):
        """Tracer density and enclosed mass on the radial grid (and mass at the outputs).

        The parameter-free parts are cached per profile family
        (``tracer.at_points``), so a new Dehnen slope or cusp costs a few
        vectorised passes over the fixed grid.
        """
        if self._cache_key != tracer:
            evaluator = self._evaluators.get(tracer.family)
            if evaluator is None:
                points = np.concatenate([self.r, [self.x_max]])
                mass_points = np.concatenate([self.r, self.X, [self.x_max]])
                evaluator = tracer.at_points(points, mass_points)
                self._evaluators[tracer.family] = evaluator
            nu, m = evaluator(tracer)
            n = self.r.size
            self._cache = {
                "nu": nu[:n],
                "m": m[:n],
                "m_X": m[n:-1],
                "nu_end": float(nu[-1]),
                "m_end": float(m[-1]),
            }
            self._cache_key = tracer
        return self._cache

    def _outside_in(self, f):
        """``int_{r_j}^{x_max} f d ln r`` on the grid (cubic, 4th order; f >= 0 stays >= 0
        to the order of the scheme)."""
        h24 = self.step / 24.0
        gaps = np.empty(f.size - 1)
        gaps[1:-1] = h24 * (13.0 * (f[1:-2] + f[2:-1]) - f[:-3] - f[3:])
        gaps[0] = h24 * (9.0 * f[0] + 19.0 * f[1] - 5.0 * f[2] + f[3])
        gaps[-1] = h24 * (9.0 * f[-1] + 19.0 * f[-2] - 5.0 * f[-3] + f[-4])
        out = np.zeros(f.size)
        out[:-1] = np.cumsum(gaps[::-1])[::-1]
        return out

    def moments(self, tracer, anisotropy, dark_radius: float | None = None) -> ProjectedMoments:
        """Projected moments of ``tracer`` in the cluster + point mass (+ dark Plummer) potential.

        Parameters
        ----------
        tracer : profile from :mod:`mavispm.dynamics.tracers`
            Tracer density, also the shape of the cluster's mass.
        anisotropy : float or Anisotropy
            Constant ``beta`` (< 1) or a radius-dependent :class:`Anisotropy`.
        dark_radius : float, optional
            Scale radius of the dark Plummer component in tracer scale radii
            (its moments are zero without it).
        """
        anisotropy = _checked(anisotropy, dark_radius)
        tab = self._tracer_tables(tracer)
        nu = tab["nu"]
        ln_fac = anisotropy.ln_factor(self.ln_r)
        fac = np.exp(ln_fac - ln_fac[-1])  # g(r) / g(x_max): no overflow
        # the analytic tail beyond x_max, in units of g(x_max)
        tail = anisotropy.tail(self.x_max, tracer.outer_slope) * tab["nu_end"] / np.exp(ln_fac[-1])
        base = fac * nu / self.r  # per d ln r, without the enclosed mass
        masses = [tab["m"]]
        ends = [tab["m_end"]]
        masses.append(None)
        ends.append(1.0)
        if dark_radius is not None:
            masses.append(Plummer().enclosed(self.r / dark_radius))
            ends.append(float(Plummer().enclosed(self.x_max / dark_radius)))
        beta = anisotropy.beta(self.r)
        cols = []
        for m, m_end in zip(masses, ends):
            f = base if m is None else base * m
            p = (self._outside_in(f) + tail * m_end) / fac  # nu sigma_r^2
            cols += [(1.0 - beta) * p, beta * p]
        cols = np.stack(cols, axis=1)  # (n_r, 2 * parts)
        a0 = self._k0 @ cols
        a2 = self._k2 @ cols
        sigma = self._k0 @ nu
        inv_sigma = 1.0 / np.maximum(sigma, np.finfo(float).tiny)
        rad = (a0[:, 0::2] + a2[:, 1::2]) * inv_sigma[:, None]  # (1-b) p + b R^2/r^2 p
        tan = a0[:, 0::2] * inv_sigma[:, None]
        zero = np.zeros_like(sigma)
        has_dark = dark_radius is not None
        proj_m = tab["m_X"] + self._kc @ nu
        return ProjectedMoments(
            X=self.X,
            surface_density=sigma,
            projected_enclosed=proj_m,
            radial_cluster=rad[:, 0],
            radial_bh=rad[:, 1],
            tangential_cluster=tan[:, 0],
            tangential_bh=tan[:, 1],
            radial_dark=rad[:, 2] if has_dark else zero,
            tangential_dark=tan[:, 2] if has_dark else zero,
        )

    def log_dispersions(self, tracer, anisotropy, dark_radius, weights):
        """ln of the weighted model dispersions, compiled: the likelihood's hot path.

        The same model as :meth:`moments` (its reference), with the components
        weighted before the projection:
        ``sigma^2 = w_cl S_cluster + w_bh S_bh + w_dark S_dark``
        (:func:`mavispm.dynamics.jeans_kernel.log_dispersions`).

        Parameters
        ----------
        tracer : profile from :mod:`mavispm.dynamics.tracers`
            Tracer density, also the shape of the cluster's mass.
        anisotropy : float or Anisotropy
            Constant ``beta`` (< 1) or a radius-dependent :class:`Anisotropy`.
        dark_radius : float or None
            Scale radius of the dark Plummer component in tracer scale radii.
        weights : array_like (3,)
            ``w_cl, w_bh, w_dark``: the masses times ``G / a`` in the unit wanted
            (``w_dark`` is ignored without a dark component).

        Returns
        -------
        ln_s2 : ndarray (2, M)
            ln radial and tangential dispersion squared at the output radii
            (floored at the smallest normal double, as the likelihood does).
        ln_sigma, ln_proj : ndarray (M,)
            ln surface density and ln projected mass fraction (floored likewise).
        """
        return log_dispersions(*self._kernel_args(tracer, anisotropy, dark_radius, weights))

    def line_of_sight(self, tracer, anisotropy, dark_radius, weights, n_nodes: int = 16):
        """Line-of-sight velocity mixture on the output radii, compiled.

        The model of :meth:`log_dispersions` at ``n_nodes`` depths along each line of
        sight (:mod:`mavispm.dynamics.line_of_sight`) instead of projected.

        Parameters
        ----------
        tracer, anisotropy, dark_radius, weights
            As :meth:`log_dispersions`.
        n_nodes : int
            Gauss-Legendre nodes per line of sight (built once per value and tracer
            extent: a truncated tracer's lines of sight end at its tidal radius).

        Returns
        -------
        mix_w, s2_r, s2_t : ndarray (M, n_nodes)
            Component weights (one per output radius in all) and sky-radial and
            sky-tangential variances (unit of ``weights``).
        ln_sigma, ln_proj : ndarray (M,)
            ln surface density and ln projected mass fraction.
        """
        base = getattr(tracer, "base", tracer)
        r_end = base.tidal_radius if np.isinf(base.outer_slope) else None
        nodes = self._los_nodes.get((n_nodes, r_end))
        if nodes is None:
            nodes = line_of_sight_nodes(
                self.X, self.ln_r[0], self.step, self.r.size, n_nodes, self.x_max, r_end
            )
            self._los_nodes[(n_nodes, r_end)] = nodes
        return line_of_sight_model(
            *self._kernel_args(tracer, anisotropy, dark_radius, weights),
            nodes.index,
            nodes.weight,
            nodes.dz,
            nodes.inv_cosh2,
        )

    def _kernel_args(self, tracer, anisotropy, dark_radius, weights):
        """Arguments of the compiled Jeans kernels for this model."""
        anisotropy = _checked(anisotropy, dark_radius)
        tab = self._tracer_tables(tracer)
        tail_nu = anisotropy.tail(self.x_max, tracer.outer_slope) * tab["nu_end"]
        return (
            self.r,
            self.ln_r,
            self.step,
            self.x_max,
            tab["nu"],
            tab["m"],
            tab["m_end"],
            tab["m_X"],
            tail_nu,
            float(anisotropy.beta_0),
            float(anisotropy.beta_inf),
            float(anisotropy.r_a),
            -1.0 if dark_radius is None else float(dark_radius),
            np.asarray(weights, dtype=float),
            self._k0,
            self._k2,
            self._kc,
            self._lo,
            self._hi,
        )


def _checked(anisotropy, dark_radius):
    """The anisotropy as an :class:`Anisotropy`; ValueError for beta >= 1 or b <= 0."""
    if not isinstance(anisotropy, Anisotropy):
        if not anisotropy < 1.0:
            raise ValueError(f"anisotropy beta must be < 1, got {anisotropy}")
        anisotropy = constant_anisotropy(float(anisotropy))
    if dark_radius is not None and not dark_radius > 0:
        raise ValueError(f"dark component radius must be > 0, got {dark_radius}")
    return anisotropy


def projected_dispersion(
    R,
    mass,
    scale_radius,
    bh_mass=0.0 * u.Msun,
    beta: float = 0.0,
    tracer=None,
    distance=None,
    x_max: float = 1e4,
    n_panels: int = 24,
    n_gl: int = 6,
    dark_mass=None,
    dark_radius=None,
):
    """Projected radial and tangential proper-motion dispersions at radii ``R``.

    Parameters
    ----------
    R : Quantity
        Projected radii (length, or angle when ``distance`` is given).
    mass : Quantity
        Cluster mass [solMass].
    scale_radius : Quantity
        Tracer/mass scale radius (same kind as ``R``).
    bh_mass : Quantity
        Central point mass [solMass].
    beta : float or Anisotropy
        Constant anisotropy (< 1) or a radius-dependent profile (radii in scale radii).
    tracer : profile from :mod:`mavispm.dynamics.tracers`, default Plummer.
    distance : Quantity, optional
        Needed for angular radii; the result is then in mas/yr.
    x_max, n_panels, n_gl
        Quadrature settings, see :class:`JeansProjector`.
    dark_mass, dark_radius : Quantity, optional
        Mass [solMass] and scale radius (same kind as ``R``) of a dark Plummer sphere.

    Returns
    -------
    sigma_R, sigma_T : Quantity
        km/s (length radii) or mas/yr (angular radii with a distance).

    Examples
    --------
    An isotropic self-consistent Plummer sphere has the closed form
    ``sigma_p^2(R) = 3 pi G M / (64 sqrt(R^2 + a^2))`` for every projected component:

    >>> import astropy.units as u
    >>> import numpy as np
    >>> R = [0.5, 1.0, 2.0] * u.pc
    >>> sigma_R, sigma_T = projected_dispersion(R, 1e5 * u.Msun, 1.0 * u.pc)
    >>> sigma_R.round(3)
    <Quantity [7.527, 6.692, 5.322] km / s>
    >>> closed = np.sqrt(3 * np.pi / 64 * G_PC_KMS2_MSUN * 1e5 / np.hypot(R.value, 1.0))
    >>> bool(np.allclose(sigma_R.value, closed, rtol=1e-4))
    True
    >>> bool(np.allclose(sigma_T.value, closed, rtol=1e-4))
    True
    """
    tracer = tracer or Plummer()
    R = u.Quantity(R)
    a = u.Quantity(scale_radius)
    if R.unit.physical_type == "angle":
        if distance is None:
            raise ValueError("angular radii need a distance")
        d = u.Quantity(distance).to_value(u.pc)
        a_pc = a.to_value(u.rad) * d
        X = (R / a).to(u.one).value
    else:
        a_pc = a.to_value(u.pc)
        X = (R / a).to(u.one).value
    b = None if dark_radius is None else (u.Quantity(dark_radius) / a).to(u.one).value
    projector = JeansProjector(X, x_max=x_max, n_panels=n_panels, n_gl=n_gl)
    mom = projector.moments(tracer, beta, dark_radius=b)
    g_over_a = G_PC_KMS2_MSUN / a_pc
    m = u.Quantity(mass).to_value(u.Msun)
    mb = u.Quantity(bh_mass).to_value(u.Msun)
    md = 0.0 if dark_mass is None else u.Quantity(dark_mass).to_value(u.Msun)
    s2r = g_over_a * (m * mom.radial_cluster + mb * mom.radial_bh + md * mom.radial_dark)
    s2t = g_over_a * (
        m * mom.tangential_cluster + mb * mom.tangential_bh + md * mom.tangential_dark
    )
    out_r, out_t = np.sqrt(s2r) * u.km / u.s, np.sqrt(s2t) * u.km / u.s
    if R.unit.physical_type == "angle":
        conv = KMS_PER_MASYR_KPC * u.Quantity(distance).to_value(u.kpc)
        return (out_r.value / conv) * u.mas / u.yr, (out_t.value / conv) * u.mas / u.yr
    return out_r, out_t
