"""Field-only sampling of positions and velocities from an isotropic cluster model.

Only the stars that fall in the imaged square field (half-size ``h``) or in
the surrounding margin frame (out to half-size ``H = h + margin``) are drawn,
without generating the rest of the cluster:

1. projected radius ``R`` by inverse CDF of ``Sigma(R) R A(R)``, where
   ``A(R)`` is the angle (out of 2 pi) of the circle of radius ``R`` inside the
   region (square field, or frame between the two squares);
2. the position angle uniformly over those arcs (exact, no rejection);
3. the line-of-sight offset ``z`` from ``p(z | R) ~ rho(sqrt(R^2 + z^2))``
   (quantile table in ``t = asinh(z / R)``, rows in ``ln R``);
4. the speed from ``p(v | r) ~ v^2 f(Psi(r) - v^2/2)`` (quantile table of
   ``q = v / v_esc`` on rows in ``ln Psi``) and an isotropic direction.
   For an Osipkov-Merritt DF ``f(Q)``, ``Q = Psi - (v_r^2 + w_t^2) / 2`` with
   ``w_t = v_t sqrt(1 + r^2/r_a^2)``: the vector ``(v_r, w_t)`` is drawn exactly
   as an isotropic velocity from ``f(Q)`` and the tangential part is divided
   by ``sqrt(1 + r^2/r_a^2)`` (the Jacobian of this map is constant at fixed
   r, so the density is ``rho_Q / (1 + r^2/r_a^2) = rho``).
   For a constant-beta DF ``L^(-2 beta) g(E)``, in polar coordinates of the
   ``(v_r, v_t)`` plane the density separates: the speed follows
   ``v^(2 - 2 beta) g(Psi - v^2/2)`` and ``mu = cos(angle to r)`` follows
   ``(1 - mu^2)^(-beta)``, i.e. ``(1 + mu) / 2 ~ Beta(1 - beta, 1 - beta)``
   (exact inverse CDF), with a uniform azimuth about the radius vector.

Every star is bound by construction (``q < 1``). All draws are inverse-CDF
maps of uniform numbers, so two models fed the same uniforms give coupled
samples (common random numbers).

Units: pc, km/s, solMass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.special import betaincinv

from mavispm.simulate.cluster.eddington import DistributionFunction
from mavispm.simulate.cluster.inverse_cdf import (
    QuantileTable,
    probability_levels,
    quantiles_from_pdf,
)
from mavispm.simulate.cluster.profiles import MassModel

__all__ = [
    "FieldSampler",
    "SamplerResolution",
    "arc_intervals",
    "arc_measure",
    "build_field_sampler",
    "sample_angle",
]

Region = Literal["field", "frame"]


@dataclass(frozen=True)
class SamplerResolution:
    """Table sizes (the accuracy / speed knobs of the sampler).

    Parameters
    ----------
    n_rows : int
        Rows (conditioning values) of the line-of-sight and speed tables (speed rows:
        half log-spaced in Psi, half at Psi of log-spaced radii).
    n_levels : int
        Probability levels per row.
    n_los : int
        Line-of-sight grid points per row when building the z table.
    n_speed : int
        Speed grid points per row when building the speed table.
    n_radius : int
        Points of the projected-radius CDF.
    n_energy : int
        Energy grid of the Eddington DF table.
    """

    n_energy: int = 800
    n_rows: int = 160
    n_levels: int = 513
    n_los: int = 512
    n_speed: int = 512
    n_radius: int = 4096

    def __post_init__(self):
        for name in ("n_energy", "n_rows", "n_levels", "n_los", "n_speed", "n_radius"):
            if getattr(self, name) < 8:
                raise ValueError(f"{name} must be at least 8, got {getattr(self, name)}")


# ---------------------------------------------------------------- geometry
def _alpha(radius: np.ndarray, half: float) -> np.ndarray:
    """Angle from the axis at which a circle of ``radius`` leaves a square of half-size ``half``."""
    ratio = np.minimum(half / np.maximum(radius, 1e-300), 1.0)
    return np.arccos(ratio)


def arc_intervals(radius: np.ndarray, half: float, outer: float, region: Region):
    """Per-quadrant arcs of a circle inside a region.

    Parameters
    ----------
    radius : ndarray
        Circle radii [pc].
    half : float
        Half-size of the square field [pc].
    outer : float
        Half-size of the outer square (field plus margin) [pc].
    region : {"field", "frame"}
        The square field, or the frame between the two squares.

    Returns
    -------
    start1, len1, start2, len2 : ndarray
        Angles [rad] measured within one quadrant; the region holds
        ``[start1, start1+len1] U [start2, start2+len2]`` in each of the four quadrants.
    """
    a_in = np.minimum(_alpha(radius, half), np.pi / 4)
    if region == "field":
        length = np.pi / 2 - 2 * a_in
        return a_in, length, a_in, np.zeros_like(length)
    a_out = np.minimum(_alpha(radius, outer), np.pi / 4)
    length = np.maximum(a_in - a_out, 0.0)
    return a_out, length, np.pi / 2 - a_in, length


def arc_measure(radius: np.ndarray, half: float, outer: float, region: Region) -> np.ndarray:
    """Total angle [rad] of the circle of ``radius`` inside the region.

    Parameters
    ----------
    radius : ndarray
        Circle radii [pc].
    half : float
        Half-size of the square field [pc].
    outer : float
        Half-size of the outer square [pc].
    region : {"field", "frame"}
        The region.

    Returns
    -------
    ndarray
        Angle in [0, 2 pi] [rad].
    """
    _, l1, _, l2 = arc_intervals(radius, half, outer, region)
    return 4.0 * (l1 + l2)


def sample_angle(
    radius: np.ndarray, uniform: np.ndarray, half: float, outer: float, region: Region
) -> np.ndarray:
    """Position angle uniform over the region's arcs at each radius (one uniform each).

    Parameters
    ----------
    radius : ndarray
        Projected radii [pc].
    uniform : ndarray
        Uniform numbers in [0, 1), one per radius.
    half : float
        Half-size of the square field [pc].
    outer : float
        Half-size of the outer square [pc].
    region : {"field", "frame"}
        The region.

    Returns
    -------
    ndarray
        Position angles in [0, 2 pi) [rad].
    """
    s1, l1, s2, l2 = arc_intervals(radius, half, outer, region)
    t = 4.0 * np.asarray(uniform)
    quadrant = np.minimum(np.floor(t), 3.0)
    s = (t - quadrant) * (l1 + l2)
    within = np.where(s < l1, s1 + s, s2 + (s - l1))
    return quadrant * (np.pi / 2) + within


# ---------------------------------------------------------------- sampler
@dataclass(frozen=True)
class FieldSampler:
    """Tables to draw stars of one model in one field geometry.

    Build with :func:`build_field_sampler`.

    Parameters
    ----------
    half_size, outer_half_size : float
        Half-size of the field and of field plus margin [pc].
    radius_grid : ndarray
        Projected radii of the R CDFs [pc] (first point 0).
    radius_cdf : dict
        Region to normalised CDF on ``radius_grid``.
    region_mass : dict
        Region to stellar mass in that region (projected) [solMass].
    los_table : QuantileTable
        ``t = asinh(z / R)`` quantiles on rows of ``ln R``.
    speed_table : QuantileTable
        ``v / v_esc`` quantiles on rows of ``ln Psi``.
    sigma_rows : tuple of ndarray
        ``(R, Sigma)`` surface density [pc, solMass/pc^2] on the table rows.
    model : MassModel
    anisotropy_radius : float
        Osipkov-Merritt radius [pc] of the DF (``inf``: isotropic).
    beta : float
        Constant anisotropy of the DF (0: isotropic or Osipkov-Merritt).
    """

    half_size: float
    outer_half_size: float
    radius_grid: np.ndarray
    radius_cdf: dict
    region_mass: dict
    los_table: QuantileTable
    speed_table: QuantileTable
    sigma_rows: tuple
    model: MassModel
    anisotropy_radius: float = np.inf
    beta: float = 0.0

    def sample(self, region: Region, u_pos: np.ndarray, u_vel: np.ndarray) -> dict:
        """Map uniforms to stars in ``region``.

        Parameters
        ----------
        region : {"field", "frame"}
        u_pos : ndarray, shape (n, 4)
            Uniforms for R, angle, line-of-sight quantile and its sign.
        u_vel : ndarray, shape (n, 3)
            Uniforms for speed quantile, cos(polar angle), azimuth.

        Returns
        -------
        dict of ndarray
            ``x, y`` (sky plane) and ``z`` (line of sight, away from the observer)
            [pc], ``r3d`` [pc], ``vx, vy, vz`` [km/s], ``psi`` [(km/s)^2].
        """
        n = u_pos.shape[0]
        if n == 0:
            empty = np.zeros(0)
            return {k: empty for k in ("x", "y", "z", "r3d", "vx", "vy", "vz", "psi")}
        R = np.interp(u_pos[:, 0], self.radius_cdf[region], self.radius_grid)
        R = np.maximum(R, self.radius_grid[1] * 1e-3)
        theta = sample_angle(R, u_pos[:, 1], self.half_size, self.outer_half_size, region)
        t = self.los_table(np.log(R), u_pos[:, 2])
        z = R * np.sinh(np.maximum(t, 0.0)) * np.where(u_pos[:, 3] < 0.5, -1.0, 1.0)
        r3d = np.hypot(R, z)
        r3d = np.minimum(r3d, self.model.r_max)
        psi = self.model.relative_potential(r3d)
        q = np.clip(self.speed_table(np.log(psi), u_vel[:, 0]), 0.0, 1.0 - 1e-12)
        speed = np.sqrt(2.0 * psi) * q
        cos_pol = 2.0 * u_vel[:, 1] - 1.0
        sin_pol = np.sqrt(np.maximum(1.0 - cos_pol**2, 0.0))
        phi = 2.0 * np.pi * u_vel[:, 2]
        x, y = R * np.cos(theta), R * np.sin(theta)
        if self.beta != 0:
            v = _constant_beta_velocity(np.stack([x, y, z]), speed, u_vel, self.beta)
        else:
            v = np.stack([sin_pol * np.cos(phi), sin_pol * np.sin(phi), cos_pol]) * speed
        if np.isfinite(self.anisotropy_radius):
            v = _osipkov_merritt_velocity(v, np.stack([x, y, z]), self.anisotropy_radius)
        return {
            "x": x,
            "y": y,
            "z": z,
            "r3d": r3d,
            "vx": v[0],
            "vy": v[1],
            "vz": v[2],
            "psi": psi,
        }


def _constant_beta_velocity(pos, speed, u_vel, beta: float) -> np.ndarray:
    """Velocities of a constant-beta DF: ``mu = cos(v, r)`` from ``(1 - mu^2)^(-beta)``."""
    mu = 2.0 * betaincinv(1.0 - beta, 1.0 - beta, u_vel[:, 1]) - 1.0
    phi = 2.0 * np.pi * u_vel[:, 2]
    r = np.sqrt(np.sum(pos**2, axis=0))
    rhat = pos / np.maximum(r, 1e-300)
    # an orthonormal basis (rhat, e1, e2): e1 from the axis least aligned with rhat
    helper = np.where(np.abs(rhat[2]) < 0.9, 1.0, 0.0)
    ref = np.stack([1.0 - helper, np.zeros_like(helper), helper])
    e1 = np.cross(rhat, ref, axis=0)
    e1 /= np.sqrt(np.sum(e1**2, axis=0))
    e2 = np.cross(rhat, e1, axis=0)
    sin_mu = np.sqrt(np.maximum(1.0 - mu**2, 0.0))
    return speed * (mu * rhat + sin_mu * (np.cos(phi) * e1 + np.sin(phi) * e2))


def _osipkov_merritt_velocity(w: np.ndarray, pos: np.ndarray, ra: float) -> np.ndarray:
    """Velocities from isotropic ``(v_r, w_t)`` draws: ``v_t = w_t / sqrt(1 + r^2/r_a^2)``."""
    r = np.sqrt(np.sum(pos**2, axis=0))
    rhat = pos / np.maximum(r, 1e-300)
    v_r = np.sum(w * rhat, axis=0)
    tangential = w - v_r * rhat
    return v_r * rhat + tangential / np.sqrt(1.0 + (r / ra) ** 2)


def _los_quantiles(model: MassModel, radii: np.ndarray, res: SamplerResolution, levels):
    """Quantiles of t = asinh(z/R) and the surface density at each row radius."""
    zmax = np.sqrt(np.maximum(model.r_max**2 - radii**2, 0.0))
    tmax = np.arcsinh(zmax / radii)
    t = tmax[:, None] * np.linspace(0.0, 1.0, res.n_los)[None, :]
    pdf = model.density(radii[:, None] * np.cosh(t)) * radii[:, None] * np.cosh(t)
    sigma = 2.0 * np.trapezoid(pdf, t, axis=1)
    return quantiles_from_pdf(t, pdf, levels), sigma


def _speed_quantiles(df: DistributionFunction, psi_rows: np.ndarray, res, levels):
    """Quantiles of q = v / sqrt(2 Psi) on rows of Psi (``q^(2 - 2 beta) f``)."""
    q = np.linspace(0.0, 1.0, res.n_speed)
    pdf = q[None, :] ** (2.0 - 2.0 * df.beta) * df(psi_rows[:, None] * (1.0 - q[None, :] ** 2))
    return quantiles_from_pdf(q, pdf, levels)


def build_field_sampler(
    model: MassModel,
    df: DistributionFunction,
    half_size: float,
    margin: float,
    resolution: SamplerResolution | None = None,
) -> FieldSampler:
    """Tabulate what is needed to sample stars in the field and its margin.

    Parameters
    ----------
    model : MassModel
    df : DistributionFunction
        DF of ``model`` (from :func:`~mavispm.simulate.cluster.eddington.eddington_df`),
        isotropic or Osipkov-Merritt.
    half_size : float
        Half the side of the square field [pc].
    margin : float
        Width of the frame around the field [pc] (>= 0).
    resolution : SamplerResolution, optional

    Returns
    -------
    FieldSampler
    """
    res = resolution or SamplerResolution()
    if not half_size > 0 or margin < 0:
        raise ValueError("field half-size must be > 0 and margin >= 0")
    outer = half_size + margin
    levels = probability_levels(res.n_levels)
    r_top = min(outer * np.sqrt(2.0), model.r_max * (1 - 1e-6))
    r_bottom = min(half_size * 1e-4, r_top * 1e-4)
    rows = np.geomspace(r_bottom, r_top, res.n_rows)
    los, sigma = _los_quantiles(model, rows, res, levels)
    los_table = QuantileTable(np.log(rows), np.nan_to_num(los, nan=0.0))

    grid = np.concatenate([[0.0], np.geomspace(r_bottom, r_top, res.n_radius)])
    lns = np.log(np.maximum(sigma, np.finfo(float).tiny))
    sig_grid = np.exp(np.interp(np.log(np.maximum(grid, r_bottom)), np.log(rows), lns))
    sig_grid[grid >= model.r_max] = 0.0
    cdfs, masses = {}, {}
    for region in ("field", "frame"):
        pdf = sig_grid * grid * arc_measure(grid, half_size, outer, region)
        cum = cumulative_trapezoid(pdf, grid, initial=0.0)
        masses[region] = float(cum[-1])
        norm = cum[-1] if cum[-1] > 0 else 1.0
        cdfs[region] = cum / norm + np.linspace(0.0, 1e-12, grid.size)
        cdfs[region] /= cdfs[region][-1]

    psi_hi = float(model.relative_potential(rows[0] * 0.999))
    psi_lo = float(model.relative_potential(model.r_max * 0.999))
    psi_lo = max(psi_lo, psi_hi * 1e-12)
    psi_rows = model.potential_nodes(psi_lo, psi_hi, res.n_rows, 1e-4, r_lo=rows[0])
    speed = _speed_quantiles(df, psi_rows, res, levels)
    speed_table = QuantileTable(np.log(psi_rows), np.nan_to_num(speed, nan=0.5))
    return FieldSampler(
        half_size,
        outer,
        grid,
        cdfs,
        masses,
        los_table,
        speed_table,
        (rows, sigma),
        model,
        df.anisotropy_radius,
        df.beta,
    )
