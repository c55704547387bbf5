"""Spherical constant-anisotropy Jeans models projected onto the sky.

For a tracer density ``nu(r)`` in a potential of a cluster of mass ``M`` (mass
follows the tracer) plus a central point mass ``M_bh``, with constant
anisotropy ``beta = 1 - sigma_t^2 / sigma_r^2``, the Jeans equation gives

    nu sigma_r^2 (r) = r^(-2 beta) int_r^inf r'^(2 beta) nu(r') G [M m(r') + M_bh] / r'^2 dr'

and the proper-motion dispersions projected along the projected radius ``R``
(radial, ``R``) and perpendicular to it (tangential, ``T``) are

    Sigma sigma_R^2 = 2 int_R^inf [(1 - beta) + beta R^2 / r^2] nu sigma_r^2 r dr / sqrt(r^2 - R^2)
    Sigma sigma_T^2 = 2 int_R^inf (1 - beta) nu sigma_r^2 r dr / sqrt(r^2 - R^2).

Numerics (all in units of the scale radius, G = M = 1; the cluster and point-mass
terms are kept separate so that ``sigma^2 = G/a (M S_cl + M_bh S_bh)``):

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

#: Gravitational constant in pc (km/s)^2 / Msun.
G_PC_KMS2_MSUN = 4.300917270e-3
#: km/s per (mas/yr * kpc).
KMS_PER_MASYR_KPC = 4.740470463533348


@dataclass
class ProjectedMoments:
    """Dimensionless projected moments on the output radii (G = M = a = 1).

    Attributes
    ----------
    X : ndarray
        Projected radii in scale radii.
    surface_density : ndarray
        ``Sigma(X)`` of the tracer (unit mass).
    projected_enclosed : ndarray
        Tracer fraction inside projected radius ``X``.
    radial_cluster, radial_bh, tangential_cluster, tangential_bh : ndarray
        ``sigma_R^2`` and ``sigma_T^2`` per unit cluster mass and per unit point
        mass; physical ``sigma^2 = G / a * (M * cluster + M_bh * bh)``.
    """

    X: np.ndarray
    surface_density: np.ndarray
    projected_enclosed: np.ndarray
    radial_cluster: np.ndarray
    radial_bh: np.ndarray
    tangential_cluster: np.ndarray
    tangential_bh: np.ndarray


class JeansProjector:
    """Projected Jeans moments at fixed output radii with cached quadrature nodes.

    Parameters
    ----------
    X : array_like
        Output projected radii in scale radii (> 0).
    x_max : float
        Outer truncation of the projection in scale radii (>= 1e4 recommended);
        the radial Jeans integral adds the analytic tail beyond it.
    n_panels : int
        Gauss-Legendre panels in ``t`` per output radius.
    n_gl : int
        Nodes per panel.
    """

    def __init__(self, X, x_max: float = 1e4, n_panels: int = 24, n_gl: int = 6):
        X = np.atleast_1d(np.asarray(X, dtype=float))
        if np.any(~np.isfinite(X)) or np.any(X <= 0) or np.any(X >= x_max):
            raise ValueError("output radii must be finite, > 0 and < x_max")
        self.X = X
        self.x_max = float(x_max)
        gl_t, gl_w = np.polynomial.legendre.leggauss(n_gl)
        tmax = np.arccosh(self.x_max / X)  # (M,)
        edges = np.linspace(0.0, 1.0, n_panels + 1)
        mid = 0.5 * (edges[1:] + edges[:-1])
        half = 0.5 * np.diff(edges)
        unit_t = (mid[:, None] + half[:, None] * gl_t[None, :]).ravel()  # in [0, 1]
        unit_w = (half[:, None] * gl_w[None, :]).ravel()
        t = tmax[:, None] * unit_t[None, :]  # (M, K)
        w = tmax[:, None] * unit_w[None, :]
        cosh_t = np.cosh(t)
        self.r = X[:, None] * cosh_t  # projection nodes (M, K)
        self.w_proj = 2.0 * w * X[:, None] * cosh_t  # Sigma-type weights
        self.w_proj_r2 = self.w_proj / cosh_t**2  # weights times R^2 / r^2
        # 4 pi X^3 int nu cosh t sinh t e^-t dt: mass inside the cylinder outside the sphere
        self.w_cyl = 4.0 * np.pi * X[:, None] ** 3 * w * cosh_t * np.sinh(t) * np.exp(-t)
        # sorted union of nodes for the outside-in radial integral
        flat = self.r.ravel()
        self._order = np.argsort(flat)
        s = np.concatenate([flat[self._order], [self.x_max]])
        ls = np.log(s)
        gap = np.diff(ls)
        g2 = 0.5 / np.sqrt(3.0)
        mid_g = 0.5 * (ls[1:] + ls[:-1])
        self._lnsub = np.concatenate([mid_g - g2 * gap, mid_g + g2 * gap])
        self._wsub = np.concatenate([0.5 * gap, 0.5 * gap])
        self._ngap = gap.size
        self._lnnode = ls[:-1]
        # radii where the tracer density (sub-nodes, nodes, x_max) and the
        # enclosed mass (sub-nodes, X, x_max) are needed
        sub = np.exp(self._lnsub)
        self._points = np.concatenate([sub, self.r.ravel(), [self.x_max]])
        self._mass_points = np.concatenate([sub, X, [self.x_max]])
        self._evaluators = {}
        self._cache_key = None
        self._cache = None

    def _tracer_tables(self, tracer):
        """Tracer quantities at the nodes and sub-nodes (cached per tracer).

        The parameter-free parts are cached per profile family
        (``tracer.at_points``), so a new Dehnen slope or cusp costs a few
        vectorised passes over the fixed points.
        """
        if self._cache_key != tracer:
            evaluator = self._evaluators.get(tracer.family)
            if evaluator is None:
                evaluator = tracer.at_points(self._points, self._mass_points)
                self._evaluators[tracer.family] = evaluator
            nu, m = evaluator(tracer)
            n_sub = self._lnsub.size
            xs = self._points[:n_sub]
            nu_s, m_s = nu[:n_sub], m[:n_sub]
            self._cache = {
                # integrands without the r^(2 beta) factor, per d ln r: r * nu * m / r^2
                "f_cl": nu_s * m_s / xs * self._wsub,
                "f_bh": nu_s / xs * self._wsub,
                "nu_node": nu[n_sub:-1].reshape(self.r.shape),
                "m_X": m[n_sub:-1],
                "nu_end": float(nu[-1]),
                "m_end": float(m[-1]),
            }
            self._cache_key = tracer
        return self._cache

    def moments(self, tracer, beta: float) -> ProjectedMoments:
        """Projected moments for ``tracer`` and constant anisotropy ``beta`` (< 1)."""
        if not beta < 1.0:
            raise ValueError(f"anisotropy beta must be < 1, got {beta}")
        tab = self._tracer_tables(tracer)
        two_b = 2.0 * beta
        fac = np.exp(two_b * self._lnsub)  # r^(2 beta) at sub-nodes
        gap_cl = (tab["f_cl"] * fac).reshape(2, -1).sum(axis=0)
        gap_bh = (tab["f_bh"] * fac).reshape(2, -1).sum(axis=0)
        # analytic tail beyond x_max: nu ~ x^-n so r^(2b-2) nu ~ x^(2b-2-n)
        n = tracer.outer_slope
        if np.isfinite(n) and tab["nu_end"] > 0:
            base = self.x_max ** (two_b - 1.0) * tab["nu_end"] / (n + 1.0 - two_b)
            tail_cl, tail_bh = base * tab["m_end"], base
        else:
            tail_cl = tail_bh = 0.0
        # cumulative from the outside in (reverse cumsum); all terms positive
        i_cl = tail_cl + np.cumsum(gap_cl[::-1])[::-1]
        i_bh = tail_bh + np.cumsum(gap_bh[::-1])[::-1]
        r_fac = np.exp(-two_b * self._lnnode)
        p_cl = np.empty(self.r.size)
        p_bh = np.empty(self.r.size)
        p_cl[self._order] = i_cl * r_fac
        p_bh[self._order] = i_bh * r_fac
        p_cl = p_cl.reshape(self.r.shape)
        p_bh = p_bh.reshape(self.r.shape)
        sigma = np.einsum("jk,jk->j", self.w_proj, tab["nu_node"])
        a_cl = np.einsum("jk,jk->j", self.w_proj, p_cl)
        b_cl = np.einsum("jk,jk->j", self.w_proj_r2, p_cl)
        a_bh = np.einsum("jk,jk->j", self.w_proj, p_bh)
        b_bh = np.einsum("jk,jk->j", self.w_proj_r2, p_bh)
        proj_m = tab["m_X"] + np.einsum("jk,jk->j", self.w_cyl, tab["nu_node"])
        tiny = np.finfo(float).tiny
        inv_sigma = 1.0 / np.maximum(sigma, tiny)
        return ProjectedMoments(
            X=self.X,
            surface_density=sigma,
            projected_enclosed=proj_m,
            radial_cluster=((1.0 - beta) * a_cl + beta * b_cl) * inv_sigma,
            radial_bh=((1.0 - beta) * a_bh + beta * b_bh) * inv_sigma,
            tangential_cluster=(1.0 - beta) * a_cl * inv_sigma,
            tangential_bh=(1.0 - beta) * a_bh * inv_sigma,
        )


def cubic_weights(lnx_grid_start: float, step: float, n: int, lnq):
    """Indices and 4-point Lagrange weights for cubic interpolation on a uniform grid.

    Queries outside the grid are clamped to its ends.

    Parameters
    ----------
    lnx_grid_start, step, n : float, float, int
        The uniform grid ``lnx_grid_start + step * arange(n)`` (n >= 4).
    lnq : ndarray
        Query points.

    Returns
    -------
    idx : ndarray of int, shape (4, N)
    weights : ndarray, shape (4, N)
    """
    pos = np.clip((np.asarray(lnq, dtype=float) - lnx_grid_start) / step, 0.0, n - 1.0)
    i = np.clip(np.floor(pos).astype(int), 1, n - 3)
    s = pos - i
    sm1, sm2, sp1 = s - 1.0, s - 2.0, s + 1.0
    weights = np.stack(
        [-s * sm1 * sm2 / 6.0, sp1 * sm1 * sm2 / 2.0, -sp1 * s * sm2 / 2.0, sp1 * s * sm1 / 6.0]
    )
    idx = np.stack([i - 1, i, i + 1, i + 2])
    return idx, weights


def interpolate(values, idx, weights):
    """Apply :func:`cubic_weights` to grid ``values`` (..., n) -> (..., N)."""
    return np.sum(values[..., idx] * weights, axis=-2)


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
    beta : float
        Constant anisotropy (< 1).
    tracer : profile from :mod:`mavispm.dynamics.tracers`, default Plummer.
    distance : Quantity, optional
        Needed for angular radii; the result is then in mas/yr.
    x_max, n_panels, n_gl
        Quadrature settings, see :class:`JeansProjector`.

    Returns
    -------
    sigma_R, sigma_T : Quantity
        km/s (length radii) or mas/yr (angular radii with a distance).
    """
    from mavispm.dynamics.tracers import Plummer

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
    mom = JeansProjector(X, x_max=x_max, n_panels=n_panels, n_gl=n_gl).moments(tracer, beta)
    g_over_a = G_PC_KMS2_MSUN / a_pc
    m = u.Quantity(mass).to_value(u.Msun)
    mb = u.Quantity(bh_mass).to_value(u.Msun)
    s2r = g_over_a * (m * mom.radial_cluster + mb * mom.radial_bh)
    s2t = g_over_a * (m * mom.tangential_cluster + mb * mom.tangential_bh)
    out_r, out_t = np.sqrt(s2r) * u.km / u.s, np.sqrt(s2t) * u.km / u.s
    if R.unit.physical_type == "angle":
        conv = KMS_PER_MASYR_KPC * u.Quantity(distance).to_value(u.kpc)
        return (out_r.value / conv) * u.mas / u.yr, (out_t.value / conv) * u.mas / u.yr
    return out_r, out_t
