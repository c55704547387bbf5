"""Isotropic distribution function by Eddington inversion in the total potential.

``f(E) = 1 / (sqrt(8) pi^2) * dF/dE``, ``F(E) = int_0^E (d rho / dPsi) dPsi / sqrt(E - Psi)``

with ``rho(Psi)`` the stellar density expressed through the relative potential
of stars *plus* the central point mass. ``d rho / dPsi = (d rho / dr) / (dPsi / dr)``
with ``dPsi/dr = -G M(<r) / r^2`` is evaluated on the radial grid (well
conditioned even where Psi is flat in the core) and interpolated in ln Psi.
The Abel integral is split at ``Psi = E/2``: below, Gauss-Legendre nodes in
``ln Psi``; above, the substitution ``Psi = E - t^2`` removes the inverse square
root. ``dF/dE`` comes from a cubic spline of ``ln F`` against ``ln E``.
Everything is vectorised over the energy grid.

A cored tracer (inner slope gamma < 1/2) around a point mass has no
non-negative isotropic DF (An & Evans 2006, ApJ 642, 752): such models are
refused before any work with :class:`NoIsotropicDFError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from mavispm.simulate.cluster.profiles import G_PC, MassModel

#: Minimum inner slope for an isotropic DF around a point mass (An & Evans 2006).
MIN_GAMMA_WITH_BH = 0.5
#: Negative DF values below this fraction of max(f) are numerical noise and clipped.
NEGATIVE_TOLERANCE = 1e-6
#: Smallest step in ln E of the DF grid (finer steps amplify quadrature noise in dF/dE).
MIN_LOG_ENERGY_STEP = 2e-3


class NoIsotropicDFError(ValueError):
    """The requested model has no non-negative isotropic distribution function."""


@dataclass(frozen=True)
class DistributionFunction:
    """A tabulated isotropic DF f(E).

    Attributes
    ----------
    energy : ndarray
        Relative energies ``E = Psi - v^2/2`` [(km/s)^2], ascending, log-spaced.
    f : ndarray
        DF values [solMass / (pc^3 (km/s)^3)], non-negative.
    min_raw : float
        Most negative raw value before clipping, relative to max(f) (<= 0 or 0).
    """

    energy: np.ndarray
    f: np.ndarray
    min_raw: float

    def __call__(self, energy) -> np.ndarray:
        """f(E) by log-log interpolation; 0 for E <= 0; flat beyond the table."""
        e = np.asarray(energy, float)
        out = np.zeros_like(e)
        pos = e > 0
        le = np.log(np.clip(e[pos], self.energy[0], self.energy[-1]))
        logf = np.log(np.maximum(self.f, np.finfo(float).tiny))
        out[pos] = np.exp(np.interp(le, np.log(self.energy), logf))
        below = pos & (e < self.energy[0])
        if np.any(below):  # power-law extrapolation towards E -> 0 using the first two nodes
            slope = (logf[1] - logf[0]) / np.log(self.energy[1] / self.energy[0])
            out[below] = self.f[0] * (e[below] / self.energy[0]) ** max(slope, 0.0)
        return out


def check_isotropic_df_exists(cusp_gamma: float, bh_mass: float) -> None:
    """Refuse a cored tracer around a point mass.

    Raises
    ------
    NoIsotropicDFError
        If ``bh_mass > 0`` and ``cusp_gamma < 1/2``.
    """
    if bh_mass > 0 and cusp_gamma < MIN_GAMMA_WITH_BH:
        raise NoIsotropicDFError(
            f"a tracer with inner slope gamma={cusp_gamma:g} around a central point mass "
            f"({bh_mass:g} solMass) has no non-negative isotropic distribution function "
            "(An & Evans 2006 need gamma >= 1/2); set cusp_gamma >= 0.5 (N-body models give "
            "~1.55) or imbh_mass = 0"
        )


def eddington_df(
    model: MassModel, n_energy: int = 800, n_nodes: int | None = None
) -> DistributionFunction:
    """Tabulate the isotropic DF of ``model`` by Eddington inversion.

    Parameters
    ----------
    model : MassModel
        Normalised stellar density and total relative potential.
    n_energy : int
        Energy grid size: half log-spaced over the model's Psi range, half at the
        potential of log-spaced radii (fine where Psi is flat, in cores).
    n_nodes : int, optional
        Gauss-Legendre nodes per half of the Abel integral; default
        ``max(96, n_energy // 8)`` (dF/dE amplifies quadrature noise on fine grids).

    Returns
    -------
    DistributionFunction

    Raises
    ------
    NoIsotropicDFError
        For a cored tracer around a point mass, or if the inversion gives a
        significantly negative DF (the model is not consistent with isotropy).
    """
    check_isotropic_df_exists(model.tracer.cusp_gamma, model.bh_mass)
    r, rho = model.r, model.rho
    dlnrho_dlnr = np.gradient(np.log(rho), np.log(r))
    dpsi_dr = -G_PC * (model.mass + model.bh_mass) / r**2
    g = rho / r * dlnrho_dlnr / dpsi_dr  # d rho / d Psi, on the radial grid
    lnpsi = np.maximum.accumulate(np.log(model.psi[::-1]))  # ascending Psi
    lng = np.log(np.maximum(g[::-1], np.finfo(float).tiny))
    psi_lo, psi_hi = float(np.exp(lnpsi[0])), float(np.exp(lnpsi[-1]))

    def drho_dpsi(psi):
        return np.exp(np.interp(np.log(psi), lnpsi, lng))

    energy = model.potential_nodes(psi_lo * (1 + 1e-6), psi_hi, n_energy, MIN_LOG_ENERGY_STEP)
    x, w = np.polynomial.legendre.leggauss(n_nodes or max(96, n_energy // 8))
    # F(E) = int_0^E rho'(Psi) dPsi / sqrt(E - Psi); lower part Psi in [psi_lo, E/2] in ln Psi
    split = np.maximum(energy / 2.0, psi_lo)
    a, b = np.log(psi_lo), np.log(split)
    half = 0.5 * (b - a)
    psi = np.exp(a + half[:, None] * (x[None, :] + 1.0))
    low = np.sum(w * drho_dpsi(psi) * psi / np.sqrt(energy[:, None] - psi), axis=1) * half
    # upper part: Psi = E - t^2, t in [0, sqrt(E - split)]
    tmax = np.sqrt(energy - split)
    t = 0.5 * tmax[:, None] * (x[None, :] + 1.0)
    high = np.sum(w * drho_dpsi(energy[:, None] - t**2), axis=1) * tmax  # 2 * (tmax / 2)
    # below psi_lo the density is ~ linear in Psi down to 0 (rho(Psi=0) ~ 0)
    edge = drho_dpsi(np.array([psi_lo]))[0] * 2.0 * (np.sqrt(energy) - np.sqrt(energy - psi_lo))
    big_f = low + high + edge
    lnf_spline = CubicSpline(np.log(energy), np.log(np.maximum(big_f, np.finfo(float).tiny)))
    f = big_f / energy * lnf_spline.derivative(1)(np.log(energy)) / (np.sqrt(8.0) * np.pi**2)
    fmax = float(np.max(f))
    if not np.all(np.isfinite(f)) or fmax <= 0:
        raise NoIsotropicDFError("Eddington inversion failed: the DF is not finite and positive")
    min_raw = float(min(np.min(f), 0.0) / fmax)
    if min_raw < -NEGATIVE_TOLERANCE:
        e_bad = energy[np.argmin(f)]
        raise NoIsotropicDFError(
            f"the isotropic DF of this model is negative (f/f_max = {min_raw:.2e} at "
            f"E = {e_bad:.3g} (km/s)^2); the density cannot be supported isotropically in "
            "this potential. Steepen or widen the cusp (cusp_gamma, cusp_radius), change the "
            "IMBH mass, or refine resolution.n_energy if the model is nearly singular"
        )
    return DistributionFunction(energy, np.maximum(f, 0.0), min_raw)
