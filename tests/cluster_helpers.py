"""Independent references for the cluster tests (not the sampler's tables).

The isotropic Jeans equation and its projection are integrated with
``scipy.integrate.quad`` from the model's density *function* only:

``M(r) = int 4 pi r^2 rho``, ``rho sigma^2(r) = int_r^inf rho G (M + M_BH) / r^2 dr``,
``Sigma sigma_p^2(R) = 2 int_0^inf rho sigma^2(sqrt(R^2 + z^2)) dz``,
``Sigma(R) = 2 int_0^inf rho(sqrt(R^2 + z^2)) dz``.

For an isotropic model the dispersion of any sky-plane component (radial or
tangential proper motion) equals the line-of-sight one, ``sigma_p(R)``.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.integrate import IntegrationWarning, quad
from scipy.interpolate import CubicSpline

from mavispm.simulate.cluster.profiles import G_PC


def _quad(fn, a, b, **kw):
    """``scipy.integrate.quad`` value, silencing round-off warnings at tiny tails."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IntegrationWarning)
        return quad(fn, a, b, **kw)[0]


class JeansReference:
    """Isotropic Jeans profiles of a density ``rho(r)`` plus a point mass.

    Parameters
    ----------
    density : callable
        ``rho(r)`` [solMass/pc^3] for scalar ``r`` [pc].
    bh_mass : float
        Central point mass [solMass].
    r_min, r_max : float
        Inner and outer radii [pc]; rho = 0 beyond ``r_max``.
    """

    def __init__(self, density, bh_mass, r_min, r_max, n=240):
        self.rho = lambda r: float(density(np.asarray(r, float)))
        self.bh = bh_mass
        self.r_max = r_max
        r = np.geomspace(r_min, r_max, n)
        # inner mass by a power-law fit of the two innermost densities
        s = -np.log(self.rho(r[1]) / self.rho(r[0])) / np.log(r[1] / r[0])
        mass = [4 * np.pi * self.rho(r[0]) * r[0] ** 3 / (3 - min(max(s, 0.0), 2.9))]
        for a, b in zip(r[:-1], r[1:]):
            mass.append(mass[-1] + _quad(lambda x: 4 * np.pi * x * x * self.rho(x), a, b))
        self._lnm = CubicSpline(np.log(r), np.log(mass))
        self.total_mass = mass[-1]

        def jeans_integrand(x):
            return self.rho(x) * G_PC * (self.mass(x) + self.bh) / x**2

        p = [0.0]
        for a, b in zip(r[::-1][1:], r[::-1][:-1]):
            p.append(p[-1] + _quad(jeans_integrand, a, b, limit=100))
        p = np.array(p[::-1])
        self._r = r
        self._lnp = CubicSpline(np.log(r[:-1]), np.log(p[:-1]))

    def mass(self, r):
        """Stellar mass inside ``r`` [solMass]."""
        return float(np.exp(self._lnm(np.log(r))))

    def rho_sigma2(self, r):
        """``rho sigma_r^2`` [solMass/pc^3 (km/s)^2]."""
        if r >= self._r[-2]:
            return 0.0
        return float(np.exp(self._lnp(np.log(max(r, self._r[0])))))

    def surface_density(self, R):
        """``Sigma(R)`` [solMass/pc^2]."""
        zmax = np.sqrt(max(self.r_max**2 - R * R, 0.0))
        return 2 * _quad(lambda z: self.rho(np.hypot(R, z)), 0, zmax, limit=200, points=[R])

    def projected_dispersion2(self, R):
        """Projected 1-D velocity dispersion squared ``sigma_p^2(R)`` [(km/s)^2]."""
        zmax = np.sqrt(max(self.r_max**2 - R * R, 0.0))
        num = _quad(lambda z: self.rho_sigma2(np.hypot(R, z)), 0, zmax, limit=200, points=[R])
        return 2 * num / self.surface_density(R)


def binned_dispersion_chi2(R, v, model_sigma2_at, n_bins, min_per_bin):
    """Chi^2 of binned mean(v^2) against the model's sigma^2 at the stars' radii.

    Bins hold equal numbers of stars. The model expectation of a bin is the mean of
    ``sigma_p^2(R_i)`` over its stars; the error of ``mean(v^2)`` is the sample
    standard deviation of ``v^2`` over sqrt(n) (no Gaussian assumption).

    Returns
    -------
    chi2 : float
    dof : int
    """
    order = np.argsort(R)
    chi2 = 0.0
    bins = np.array_split(order, n_bins)
    for idx in bins:
        assert idx.size >= min_per_bin
        v2 = v[idx] ** 2
        expect = np.mean(model_sigma2_at(R[idx]))
        err = np.std(v2, ddof=1) / np.sqrt(idx.size)
        chi2 += ((np.mean(v2) - expect) / err) ** 2
    return chi2, len(bins)


def sigma2_interpolator(ref: JeansReference, r_lo, r_hi, n=40):
    """``sigma_p^2`` on a log grid, returned as a vectorised interpolator in ln R."""
    grid = np.geomspace(r_lo, r_hi, n)
    values = np.array([ref.projected_dispersion2(R) for R in grid])
    spline = CubicSpline(np.log(grid), values)
    return lambda R: spline(np.log(np.clip(R, r_lo, r_hi)))


class MultiMassJeansReference:
    """Osipkov-Merritt (or isotropic) Jeans profiles of one mass group in a total potential.

    Independent of the generator's tables: only density *functions* are used, and
    every integral is a ``scipy.integrate.quad``.

    ``(r^2 + r_a^2) rho sigma_r^2 = int_r^inf (s^2 + r_a^2) rho G (M_tot(s) + M_BH) / s^2 ds``
    (the OM Jeans equation with its integrating factor), ``beta = r^2 / (r^2 + r_a^2)``;
    sky-plane projections (e.g. van der Marel & Anderson 2010):
    ``Sigma sigma_R^2 = 2 int_0^inf (1 - beta + beta R^2 / r^2) rho sigma_r^2 dz``,
    ``Sigma sigma_T^2 = 2 int_0^inf (1 - beta) rho sigma_r^2 dz``.

    Parameters
    ----------
    density : callable
        The group's density ``rho(r)`` [solMass/pc^3].
    total_density : callable or JeansReference
        Density of all groups (the potential's source) [solMass/pc^3], or a
        :class:`JeansReference` of it (to share its enclosed mass between groups).
    bh_mass : float
        Central point mass [solMass].
    r_min, r_max : float
        Inner and outer radii [pc].
    anisotropy_radius : float
        OM radius [pc] (``inf``: isotropic).
    beta : float
        Constant anisotropy instead (needs ``anisotropy_radius = inf``):
        ``r^(2 beta) rho sigma_r^2 = int_r^inf s^(2 beta) rho G M / s^2 ds``.
    """

    def __init__(
        self, density, total_density, bh_mass, r_min, r_max, anisotropy_radius=np.inf, beta=0.0
    ):
        # M_tot(r) only; a prebuilt JeansReference of the total density may be passed
        self.total = (
            total_density
            if isinstance(total_density, JeansReference)
            else JeansReference(total_density, bh_mass, r_min, r_max)
        )
        self.rho = lambda r: float(density(np.asarray(r, float)))
        self.bh = bh_mass
        self.ra2 = anisotropy_radius**2
        self.beta0 = beta
        self.r_max = r_max
        r = np.geomspace(r_min, r_max, 240)

        def integrand(x):
            w = (x * x + self.ra2) if np.isfinite(self.ra2) else x ** (2 * beta)
            return w * self.rho(x) * G_PC * (self.total.mass(x) + self.bh) / x**2

        p = [0.0]
        for a, b in zip(r[::-1][1:], r[::-1][:-1]):
            p.append(p[-1] + _quad(integrand, a, b, limit=100))
        p = np.array(p[::-1])
        self._r = r
        self._lnp = CubicSpline(np.log(r[:-1]), np.log(p[:-1]))

    def beta(self, r):
        """Anisotropy ``r^2 / (r^2 + r_a^2)`` (or the constant ``beta``)."""
        return self.beta0 if not np.isfinite(self.ra2) else r * r / (r * r + self.ra2)

    def rho_sigma_r2(self, r):
        """``rho sigma_r^2`` [solMass/pc^3 (km/s)^2]."""
        if r >= self._r[-2]:
            return 0.0
        value = float(np.exp(self._lnp(np.log(max(r, self._r[0])))))
        return (
            value * r ** (-2 * self.beta0)
            if not np.isfinite(self.ra2)
            else value / (r * r + self.ra2)
        )

    def projected_pm2(self, R):
        """Sky-plane radial and tangential dispersions squared at ``R`` [(km/s)^2]."""
        zmax = np.sqrt(max(self.r_max**2 - R * R, 0.0))
        kw = {"limit": 200, "points": [R]}

        def radial(z):
            r = np.hypot(R, z)
            b = self.beta(r)
            return (1 - b + b * R * R / (r * r)) * self.rho_sigma_r2(r)

        def tangential(z):
            r = np.hypot(R, z)
            return (1 - self.beta(r)) * self.rho_sigma_r2(r)

        sigma = 2 * _quad(lambda z: self.rho(np.hypot(R, z)), 0, zmax, **kw)
        return (
            2 * _quad(radial, 0, zmax, **kw) / sigma,
            2 * _quad(tangential, 0, zmax, **kw) / sigma,
        )


def pm2_interpolators(ref: MultiMassJeansReference, r_lo, r_hi, n=20):
    """Vectorised ``sigma_R^2(R)``, ``sigma_T^2(R)`` interpolators (cubic in ln R)."""
    grid = np.geomspace(r_lo, r_hi, n)
    values = np.array([ref.projected_pm2(R) for R in grid])
    splines = [CubicSpline(np.log(grid), values[:, k]) for k in range(2)]
    return [lambda R, s=s: s(np.log(np.clip(R, r_lo, r_hi))) for s in splines]


def sky_components(stars):
    """Projected radius [pc] and sky-plane radial / tangential velocities [km/s]."""
    R = np.hypot(stars["x"], stars["y"])
    cx, sy = stars["x"] / R, stars["y"] / R
    return R, stars["vx"] * cx + stars["vy"] * sy, -stars["vx"] * sy + stars["vy"] * cx
