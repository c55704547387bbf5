"""Distribution functions by Eddington inversion in the total potential.

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

Osipkov-Merritt anisotropy (Osipkov 1979; Merritt 1985, AJ 90, 1027): the DF
is ``f(Q)`` with ``Q = E - L^2 / (2 r_a^2)``; the same inversion applies to the
augmented density ``rho_Q(r) = (1 + r^2 / r_a^2) rho(r)`` expressed through Psi.
Since ``rho_Q(Psi) = 4 pi int_0^Psi f(Q) sqrt(2 (Psi - Q)) dQ``, a non-negative
f needs ``rho_Q`` to rise with Psi: models where it does not (``r_a`` too small)
are refused naming ``anisotropy_radius``. The anisotropy is
``beta(r) = r^2 / (r^2 + r_a^2)``.

For one component of a multi-mass model the density is the component's and
the potential the total one (all components plus the point mass).
"""

from __future__ import annotations

import functools
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
        Relative energies ``E = Psi - v^2/2`` (or ``Q`` for Osipkov-Merritt)
        [(km/s)^2], ascending, log-spaced.
    f : ndarray
        DF values [solMass / (pc^3 (km/s)^3)], non-negative.
    min_raw : float
        Most negative raw value before clipping, relative to max(f) (<= 0 or 0).
    anisotropy_radius : float
        Osipkov-Merritt radius r_a [pc]; ``inf`` for an isotropic DF f(E).
    """

    energy: np.ndarray
    f: np.ndarray
    min_raw: float
    anisotropy_radius: float = np.inf

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


@functools.lru_cache(maxsize=16)
def _gauss_legendre(n: int):
    """Gauss-Legendre nodes and weights on [-1, 1] (cached)."""
    return np.polynomial.legendre.leggauss(n)


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
    model: MassModel,
    n_energy: int = 800,
    n_nodes: int | None = None,
    anisotropy_radius: float = np.inf,
) -> DistributionFunction:
    """Tabulate the DF of ``model`` by Eddington (or Osipkov-Merritt) inversion.

    Parameters
    ----------
    model : MassModel
        Normalised stellar density and total relative potential.
    anisotropy_radius : float
        Osipkov-Merritt radius [pc]; ``inf`` (default) for isotropy.
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
        For a cored tracer around a point mass, if ``rho_Q`` does not rise with
        Psi (Osipkov-Merritt radius too small), or if the inversion gives a
        significantly negative DF (the model is not consistent with this DF family).
    """
    check_isotropic_df_exists(model.tracer.cusp_gamma, model.bh_mass)
    ra = float(anisotropy_radius)
    if not ra > 0:
        raise NoIsotropicDFError(f"anisotropy_radius must be > 0 pc, got {ra:g}")
    r, rho = model.r, model.rho
    dlnrho_dlnr = np.gradient(np.log(rho), np.log(r))
    if np.isfinite(ra):
        rho = rho * (1.0 + (r / ra) ** 2)
        dlnrho_dlnr = dlnrho_dlnr + 2.0 * r**2 / (r**2 + ra**2)
        _check_rising_augmented_density(r, model.rho, dlnrho_dlnr, ra)
    dpsi_dr = -G_PC * model.gravitating_mass / r**2
    g = rho / r * dlnrho_dlnr / dpsi_dr  # d rho / d Psi, on the radial grid
    lnpsi = np.maximum.accumulate(np.log(model.psi[::-1]))  # ascending Psi
    lng = np.log(np.maximum(g[::-1], np.finfo(float).tiny))
    psi_lo, psi_hi = float(np.exp(lnpsi[0])), float(np.exp(lnpsi[-1]))

    def drho_dpsi(psi):
        return np.exp(np.interp(np.log(psi), lnpsi, lng))

    energy = model.potential_nodes(psi_lo * (1 + 1e-6), psi_hi, n_energy, MIN_LOG_ENERGY_STEP)
    x, w = _gauss_legendre(n_nodes or max(96, n_energy // 8))
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
        what = "isotropic" if not np.isfinite(ra) else f"Osipkov-Merritt (r_a = {ra:.3g} pc)"
        raise NoIsotropicDFError(
            f"the {what} DF of this model is negative (f/f_max = {min_raw:.2e} at "
            f"E = {e_bad:.3g} (km/s)^2); the density cannot be supported by this DF in "
            "this potential. Steepen or widen the cusp (cusp_gamma, cusp_radius), change "
            "imbh_mass, lower segregation, raise anisotropy_radius, lower bh_subsystem_mass or "
            "raise bh_subsystem_radius, or refine resolution.n_energy if the model is nearly "
            "singular"
        )
    return DistributionFunction(energy, np.maximum(f, 0.0), min_raw, ra)


#: Relative rise of rho_Q outwards tolerated as numerical noise.
RISE_TOLERANCE = 1e-6


def _check_rising_augmented_density(r, rho, dlnrhoq_dlnr, ra: float) -> None:
    """Refuse an Osipkov-Merritt radius for which rho_Q(r) rises outwards somewhere.

    Only radii where the density is above 1e-12 of its maximum count (the
    truncated edge, where rho -> 0, is excluded by this threshold).
    """
    live = rho > 1e-12 * np.max(rho)
    bad = live & (dlnrhoq_dlnr > RISE_TOLERANCE)
    if np.any(bad):
        r_bad = float(r[np.argmax(bad)])
        raise NoIsotropicDFError(
            f"anisotropy_radius = {ra:.3g} pc is too small for this density: "
            f"rho (1 + r^2/r_a^2) rises outwards at r = {r_bad:.3g} pc, so the "
            "Osipkov-Merritt DF would be negative (Merritt 1985); raise anisotropy_radius"
        )
