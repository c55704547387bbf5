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

Constant anisotropy beta (Cuddeford 1991, MNRAS 253, 414, with r_a -> inf):
``f(E, L) = L^(-2 beta) g(E)``, ``-1/2 < beta < 1/2``. Then
``r^(2 beta) rho = C_beta int_0^Psi (Psi - E)^(1/2 - beta) g(E) dE`` with
``C_beta = 2^(3/2 - beta) pi^(3/2) Gamma(1 - beta) / Gamma(3/2 - beta)``, inverted as
``g(E) = d/dE int_0^E (d rho_beta / d Psi) (E - Psi)^(beta - 1/2) dPsi /
(C_beta Gamma(3/2 - beta) Gamma(1/2 + beta))`` (beta = 0 is Eddington's formula).
A positive DF needs ``gamma >= 2 beta`` at the centre, and ``gamma >= beta + 1/2``
around a point mass (An & Evans 2006); both are checked first.

For one component of a multi-mass model the density is the component's and
the potential the total one (all components plus the point mass).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import special
from scipy.interpolate import CubicSpline

from mavispm.simulate.cluster.profiles import G_PC, MassModel

__all__ = [
    "DistributionFunction",
    "MIN_GAMMA_WITH_BH",
    "MIN_LOG_ENERGY_STEP",
    "NEGATIVE_TOLERANCE",
    "NoIsotropicDFError",
    "RISE_TOLERANCE",
    "check_isotropic_df_exists",
    "eddington_df",
]

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

    Parameters
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
    beta : float
        Constant anisotropy: the DF is ``L^(-2 beta) f(E)`` (0: isotropic or OM).
    """

    energy: np.ndarray
    f: np.ndarray
    min_raw: float
    anisotropy_radius: float = np.inf
    beta: float = 0.0

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


def check_isotropic_df_exists(cusp_gamma: float, bh_mass: float, beta: float = 0.0) -> None:
    """Refuse a cored tracer around a point mass, and too radial a centre.

    Parameters
    ----------
    cusp_gamma : float
        Inner logarithmic density slope of the tracer.
    bh_mass : float
        Central point mass [solMass].
    beta : float
        Constant velocity anisotropy (0: isotropic).

    Raises
    ------
    NoIsotropicDFError
        If ``bh_mass > 0`` and ``cusp_gamma < 1/2 + beta``, or ``cusp_gamma < 2 beta``
        (An & Evans 2006).
    """
    if beta != 0 and (cusp_gamma < 2 * beta or (bh_mass > 0 and cusp_gamma < beta + 0.5)):
        need = max(2 * beta, beta + 0.5 if bh_mass > 0 else -np.inf)
        raise NoIsotropicDFError(
            f"anisotropy_beta = {beta:g} needs an inner density slope gamma >= {need:g} "
            f"(An & Evans 2006), the model has cusp_gamma = {cusp_gamma:g}; lower "
            "anisotropy_beta or set a steeper cusp_gamma"
        )
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
    beta: float = 0.0,
) -> DistributionFunction:
    """Tabulate the DF of ``model`` by Eddington (or Osipkov-Merritt) inversion.

    Parameters
    ----------
    model : MassModel
        Normalised stellar density and total relative potential.
    anisotropy_radius : float
        Osipkov-Merritt radius [pc]; ``inf`` (default) for isotropy.
    beta : float
        Constant anisotropy in (-1/2, 1/2) (Cuddeford DF ``L^(-2 beta) g(E)``); only
        with ``anisotropy_radius = inf``.
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
    beta = float(beta)
    check_isotropic_df_exists(model.tracer.cusp_gamma, model.bh_mass, beta)
    ra = float(anisotropy_radius)
    if not ra > 0:
        raise NoIsotropicDFError(f"anisotropy_radius must be > 0 pc, got {ra:g}")
    if not -0.5 < beta < 0.5:
        raise NoIsotropicDFError(f"anisotropy_beta must be in (-0.5, 0.5), got {beta:g}")
    if beta != 0 and np.isfinite(ra):
        raise NoIsotropicDFError(
            "anisotropy_beta and anisotropy_radius cannot be combined; give one of them"
        )
    r, rho = model.r, model.rho
    dlnrho_dlnr = np.gradient(np.log(rho), np.log(r))
    if np.isfinite(ra):
        rho = rho * (1.0 + (r / ra) ** 2)
        dlnrho_dlnr = dlnrho_dlnr + 2.0 * r**2 / (r**2 + ra**2)
        _check_rising_augmented_density(
            r, model.rho, dlnrho_dlnr, f"anisotropy_radius = {ra:.3g} pc"
        )
    elif beta != 0:
        rho = rho * r ** (2.0 * beta)
        dlnrho_dlnr = dlnrho_dlnr + 2.0 * beta
        _check_rising_augmented_density(r, model.rho, dlnrho_dlnr, f"anisotropy_beta = {beta:g}")
    k = beta + 0.5  # F(E) = int rho'(Psi) (E - Psi)^(k - 1) dPsi
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
    low = np.sum(w * drho_dpsi(psi) * psi * (energy[:, None] - psi) ** (k - 1.0), axis=1) * half
    # upper part: Psi = E - u^(1/k), u in [0, (E - split)^k] removes the singularity
    umax = (energy - split) ** k
    uu = 0.5 * umax[:, None] * (x[None, :] + 1.0)
    high = np.sum(w * drho_dpsi(energy[:, None] - uu ** (1.0 / k)), axis=1) * (0.5 * umax / k)
    # below psi_lo the density is ~ linear in Psi down to 0 (rho(Psi=0) ~ 0)
    edge = drho_dpsi(np.array([psi_lo]))[0] * (energy**k - (energy - psi_lo) ** k) / k
    big_f = low + high + edge
    lnf_spline = CubicSpline(np.log(energy), np.log(np.maximum(big_f, np.finfo(float).tiny)))
    norm = (
        2.0 * np.pi**1.5 * 2.0 ** (0.5 - beta) * special.gamma(1.0 - beta) * special.gamma(k)
    )  # C_beta Gamma(3/2 - beta) Gamma(1/2 + beta); sqrt(8) pi^2 for beta = 0
    f = big_f / energy * lnf_spline.derivative(1)(np.log(energy)) / norm
    fmax = float(np.max(f))
    if not np.all(np.isfinite(f)) or fmax <= 0:
        raise NoIsotropicDFError("Eddington inversion failed: the DF is not finite and positive")
    min_raw = float(min(np.min(f), 0.0) / fmax)
    if min_raw < -NEGATIVE_TOLERANCE:
        e_bad = energy[np.argmin(f)]
        what = "isotropic" if not np.isfinite(ra) else f"Osipkov-Merritt (r_a = {ra:.3g} pc)"
        if beta != 0:
            what = f"constant-beta (anisotropy_beta = {beta:g})"
        raise NoIsotropicDFError(
            f"the {what} DF of this model is negative (f/f_max = {min_raw:.2e} at "
            f"E = {e_bad:.3g} (km/s)^2); the density cannot be supported by this DF in "
            "this potential. Steepen or widen the cusp (cusp_gamma, cusp_radius), change "
            "imbh_mass, lower segregation, raise anisotropy_radius or lower |anisotropy_beta|, "
            "lower bh_subsystem_mass or "
            "raise bh_subsystem_radius, or refine resolution.n_energy if the model is nearly "
            "singular"
        )
    return DistributionFunction(energy, np.maximum(f, 0.0), min_raw, ra, beta)


#: Relative rise of rho_Q outwards tolerated as numerical noise.
RISE_TOLERANCE = 1e-6


def _check_rising_augmented_density(r, rho, dlnrhoq_dlnr, what: str) -> None:
    """Refuse an anisotropy for which the augmented density rises outwards somewhere.

    ``(1 + r^2/r_a^2) rho`` (Osipkov-Merritt) or ``r^(2 beta) rho`` (constant beta)
    must fall outwards, i.e. rise with Psi, for a non-negative DF.

    Only radii where the density is above 1e-12 of its maximum count (the
    truncated edge, where rho -> 0, is excluded by this threshold).
    """
    live = rho > 1e-12 * np.max(rho)
    bad = live & (dlnrhoq_dlnr > RISE_TOLERANCE)
    if np.any(bad):
        r_bad = float(r[np.argmax(bad)])
        name = what.split(" ")[0]
        change = (
            "raise anisotropy_radius" if name == "anisotropy_radius" else "lower anisotropy_beta"
        )
        raise NoIsotropicDFError(
            f"{what} is impossible for this density: the augmented density "
            f"(rho (1 + r^2/r_a^2) or r^(2 beta) rho) rises outwards at r = {r_bad:.3g} pc, "
            f"so the DF would be negative (Merritt 1985; Cuddeford 1991); {change}"
        )
