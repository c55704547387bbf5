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
        self._cosh2 = cosh_t**2  # r^2 / R^2 at the nodes
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
        if not isinstance(anisotropy, Anisotropy):
            if not anisotropy < 1.0:
                raise ValueError(f"anisotropy beta must be < 1, got {anisotropy}")
            anisotropy = constant_anisotropy(float(anisotropy))
        tab = self._tracer_tables(tracer)
        fac = np.exp(anisotropy.ln_factor(self._lnsub))  # g(r) at sub-nodes
        tail = anisotropy.tail(self.x_max, tracer.outer_slope) * tab["nu_end"]
        parts = {"cl": (tab["f_cl"], tab["m_end"]), "bh": (tab["f_bh"], 1.0)}
        if dark_radius is not None:
            if not dark_radius > 0:
                raise ValueError(f"dark component radius must be > 0, got {dark_radius}")
            m_dark = Plummer().enclosed(self._points[: self._lnsub.size] / dark_radius)
            m_dark_end = float(Plummer().enclosed(self.x_max / dark_radius))
            parts["dark"] = (tab["f_bh"] * m_dark, m_dark_end)
        r_fac = np.exp(-anisotropy.ln_factor(self._lnnode))
        beta_node = anisotropy.beta(self.r)
        w_rad = self.w_proj * (1.0 - beta_node + beta_node / self._cosh2)
        w_tan = self.w_proj * (1.0 - beta_node)
        sigma = np.einsum("jk,jk->j", self.w_proj, tab["nu_node"])
        inv_sigma = 1.0 / np.maximum(sigma, np.finfo(float).tiny)
        out = {}
        for key, (f, m_end) in parts.items():
            gap = (f * fac).reshape(2, -1).sum(axis=0)
            # cumulative from the outside in (reverse cumsum); all terms positive
            cum = tail * m_end + np.cumsum(gap[::-1])[::-1]
            p = np.empty(self.r.size)
            p[self._order] = cum * r_fac
            p = p.reshape(self.r.shape)
            out[key] = (
                np.einsum("jk,jk->j", w_rad, p) * inv_sigma,
                np.einsum("jk,jk->j", w_tan, p) * inv_sigma,
            )
        zero = np.zeros_like(sigma)
        dark = out.get("dark", (zero, zero))
        proj_m = tab["m_X"] + np.einsum("jk,jk->j", self.w_cyl, tab["nu_node"])
        return ProjectedMoments(
            X=self.X,
            surface_density=sigma,
            projected_enclosed=proj_m,
            radial_cluster=out["cl"][0],
            radial_bh=out["bh"][0],
            tangential_cluster=out["cl"][1],
            tangential_bh=out["bh"][1],
            radial_dark=dark[0],
            tangential_dark=dark[1],
        )


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
    >>> bool(np.allclose(sigma_R.value, closed, rtol=1e-6))
    True
    >>> bool(np.allclose(sigma_T.value, closed, rtol=1e-6))
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
