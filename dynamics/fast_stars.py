"""The fast-star test: stars faster than the escape velocity without an IMBH.

A star whose velocity exceeds the escape velocity of every no-IMBH mass model
cannot be a bound member of a cluster without a central dark mass (Häberle et
al. 2024, Nature 631, 285: seven such stars within 3" of omega Cen's centre).
The test is model-light: it needs only the no-IMBH models' potential, not a
dispersion profile or an anisotropy.

Steps (all on the observer's footing: measured proper motions, their errors,
the distance prior and the fitted no-IMBH models):

1. **Velocities**: ``v_2D = 4.74 |mu| d`` [km/s] with the error
   ``sqrt((4.74 d sigma_par)^2 + (v sigma_d / d)^2)``, ``sigma_par`` the PM error
   along the motion from the full covariance (``pm_x_err, pm_y_err, pm_xy_corr``).
2. **Escape velocity** ``v_esc(R)``: at ``r = R`` and the ``escape_quantile`` of the
   no-IMBH posterior models (:mod:`mavispm.dynamics.escape_velocity`).
3. **Significance**: the p-value of ``|mu_obs|`` under the null hypothesis that the
   true speed equals the escape speed (the least favourable null): the observed
   modulus then follows a Rice distribution with the largest error eigenvalue
   (conservative for unequal errors), averaged over the distance prior
   (Gauss-Hermite nodes). ``fast`` when ``p < alpha``.
4. **Expected false fast stars** under the no-IMBH model: (a) measurement errors,
   Gaussian and with the tails measured from the pulls (a Student t fitted to the
   fraction of pulls beyond 3 robust sigma), the true speeds drawn from the model's
   local dispersion truncated at the escape speed; (b) unresolved binaries, whose
   photocentre moves over the baseline (circular orbits, log-normal periods,
   flat mass ratios, L ~ M^3.5); (c) field stars with a given surface density and
   PM distribution relative to the cluster.
5. **Lower mass limit**: a star at projected radius ``R`` moving at ``v_2D`` is bound
   only if ``v^2 / 2 + Phi_*(r) - G M_bh / r < 0``; with ``r >= R``, ``v_3D >= v_2D``
   and the deepest stellar potential (the ``escape_quantile`` over the no-IMBH
   models and over the stellar parts of the IMBH models, whose cusp can be deeper),
   the minimal central mass is ``M_i = R (v_2D^2 - v_esc(R)^2) / (2 G)``. The full
   no-IMBH potential is used (not just the enclosed mass ``M_*(<R)``: the mass
   outside ``R`` deepens the potential too), so the limit is lower, i.e. safer. As
   in Häberle et al. (2024) the stars are combined by requiring all of them to be
   bound: in each Monte Carlo draw (PMs from their error ellipses, the distance
   from its prior) the combined limit is ``max_i M_i``; the lower limit at
   ``confidence`` is the ``1 - confidence`` quantile of that maximum.
6. **Count probabilities**: Poisson probabilities of the observed number of fast
   stars given the expected numbers under the no-IMBH model (false fast stars)
   and under the IMBH model (Gaussian velocities with its dispersion, truncated at
   its own escape speed, plus the same false-star terms).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import astropy.units as u
import numpy as np
from astropy.table import QTable
from numpy.typing import ArrayLike
from scipy import stats

from mavispm.core.config import unit_field
from mavispm.core.errors import InputError
from mavispm.dynamics.jeans import G_PC_KMS2_MSUN, KMS_PER_MASYR_KPC

__all__ = [
    "FastStarResult",
    "FastStarSettings",
    "KMS_PER_AU_YR",
    "PC_PER_ARCSEC_KPC",
    "PMStars",
    "PullTails",
    "about_fitted_centre",
    "binary_kicks",
    "distance_nodes",
    "expected_flags",
    "fast_star_test",
    "largest_error",
    "lower_mass_limit",
    "measure_tails",
    "model_dispersion",
    "no_test",
    "p_value",
    "poisson_probabilities",
    "pulls_of",
    "read_pm_stars",
    "rice_sf",
    "run_on_fits",
    "stars_from_sample",
    "threshold",
    "usable_stars",
    "velocity_2d",
]

#: parsec per (arcsec * kpc)
PC_PER_ARCSEC_KPC = 1e3 * np.pi / (180.0 * 3600.0)
#: km/s per (AU / yr)
KMS_PER_AU_YR = 4.740470463533348
#: Gauss-Hermite nodes for the distance prior
_N_DISTANCE_NODES = 9


@dataclass(frozen=True)
class FastStarSettings:
    """Settings of the fast-star test (``[dynamics.fast_stars]`` table).

    Significance: ``alpha`` (one-sided p-value threshold; 0.00135 = 3 sigma),
    ``escape_quantile`` (quantile of the no-IMBH escape velocity over the
    posterior), ``n_models`` (posterior samples used). Distance prior:
    ``distance_error`` [kpc] (Gaussian sd; the dynamics ``distance_error`` is used
    when this is 0 and that is set). Lower limit: ``confidence``,
    ``n_monte_carlo``. Errors: ``rescale_errors`` (multiply the PM errors by the
    robust width of the truth pulls when it exceeds 1), ``min_stars`` (fewer usable
    stars: no test). Binaries: ``binary_fraction``, ``binary_log_period`` (mean and
    sd of log10 P/day), ``binary_primary_mass`` [solMass], ``binary_max_separation``
    [AU] (wider binaries are disrupted in a cluster core), ``baseline`` [yr] (default:
    the span of the product's epochs). Field stars: ``field_density`` [1/arcsec^2],
    ``field_pm_mean`` (x, y) and ``field_pm_sigma`` [mas/yr] relative to the cluster.
    """

    alpha: float = 0.00135
    escape_quantile: float = 0.99
    n_models: int = 100
    distance_error: float = unit_field(0.0, "kpc", "Gaussian distance prior sd")
    confidence: float = 0.95
    n_monte_carlo: int = 4000
    rescale_errors: bool = True
    min_stars: int = 10
    binary_fraction: float = 0.1
    binary_log_period: tuple[float, float] = (4.8, 2.3)
    binary_primary_mass: float = unit_field(0.8, "solMass", "primary mass of binaries")
    binary_max_separation: float = unit_field(50.0, "AU", "widest surviving binary")
    baseline: float | None = unit_field(None, "yr", "epoch baseline (default: product)")
    field_density: float = unit_field(0.0, "arcsec-2", "surface density of field stars")
    field_pm_mean: tuple[float, float] = (0.0, 0.0)
    field_pm_sigma: float = unit_field(3.0, "mas/yr", "field-star PM dispersion per axis")

    def __post_init__(self):
        checks = {
            "alpha": 0.0 < self.alpha < 0.5,
            "escape_quantile": 0.5 <= self.escape_quantile <= 1.0,
            "n_models": self.n_models >= 1,
            "distance_error": self.distance_error >= 0,
            "confidence": 0.5 <= self.confidence < 1.0,
            "n_monte_carlo": self.n_monte_carlo >= 100,
            "min_stars": self.min_stars >= 1,
            "binary_fraction": 0.0 <= self.binary_fraction <= 1.0,
            "binary_log_period": self.binary_log_period[1] > 0,
            "binary_primary_mass": self.binary_primary_mass > 0,
            "binary_max_separation": self.binary_max_separation > 0,
            "baseline": self.baseline is None or self.baseline > 0,
            "field_density": self.field_density >= 0,
            "field_pm_sigma": self.field_pm_sigma > 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"{name} out of range: {getattr(self, name)!r}")


@dataclass(frozen=True)
class PMStars:
    """Proper motions for the test (plain floats; relative to the cluster mean motion).

    Parameters
    ----------
    id : ndarray of int
    R : ndarray
        Projected radius [arcsec].
    pm_x, pm_y, pm_x_err, pm_y_err : ndarray
        [mas/yr].
    pm_xy_corr : ndarray
        Correlation coefficient of the x/y errors.
    pm_x_true, pm_y_true : ndarray or None
        True PMs (simulations; the analogue of artificial-star tests), used only to
        measure the error distribution (pulls).
    x, y : ndarray or None
        Positions about the field centre [arcsec] (to move to a fitted centre).
    """

    id: np.ndarray
    R: np.ndarray
    pm_x: np.ndarray
    pm_y: np.ndarray
    pm_x_err: np.ndarray
    pm_y_err: np.ndarray
    pm_xy_corr: np.ndarray
    pm_x_true: np.ndarray | None = None
    pm_y_true: np.ndarray | None = None
    x: np.ndarray | None = None
    y: np.ndarray | None = None

    def __len__(self):
        return len(self.R)

    def select(self, keep: np.ndarray) -> PMStars:
        """The stars where ``keep`` is true.

        Parameters
        ----------
        keep : ndarray of bool or int
            Mask or indices.

        Returns
        -------
        PMStars
            The selected rows (optional columns stay None).
        """
        out = {}
        for name in self.__dataclass_fields__:
            val = getattr(self, name)
            out[name] = None if val is None else np.asarray(val)[keep]
        return PMStars(**out)


def usable_stars(stars: PMStars) -> tuple[PMStars, int]:
    """Stars with finite motions, positive finite errors and |corr| < 1; number dropped.

    Parameters
    ----------
    stars : PMStars
        The stars.

    Returns
    -------
    stars : PMStars
        The usable ones.
    n_dropped : int
        How many were dropped.
    """
    ok = np.ones(len(stars), bool)
    for name in ("R", "pm_x", "pm_y", "pm_x_err", "pm_y_err", "pm_xy_corr"):
        ok &= np.isfinite(np.asarray(getattr(stars, name), float))
    ok &= (stars.pm_x_err > 0) & (stars.pm_y_err > 0) & (np.abs(stars.pm_xy_corr) < 1)
    return stars.select(ok), int((~ok).sum())


def velocity_2d(stars: PMStars, distance: float, distance_error: float = 0.0):
    """2-D speed and its error [km/s] from PMs with covariance and a distance prior.

    Parameters
    ----------
    stars : PMStars
    distance, distance_error : float
        Distance and its Gaussian sd [kpc].

    Returns
    -------
    v, v_err : ndarray
        ``4.74 |mu| d`` and ``sqrt((4.74 d sigma_par)^2 + (v sigma_d / d)^2)``,
        ``sigma_par^2 = u^T C u`` along the motion ``u``.
    """
    mu = np.hypot(stars.pm_x, stars.pm_y)
    sig_par = np.sqrt(_error_along(stars, stars.pm_x, stars.pm_y))
    v = KMS_PER_MASYR_KPC * distance * mu
    v_err = np.hypot(KMS_PER_MASYR_KPC * distance * sig_par, v * distance_error / distance)
    return v, v_err


def _error_along(stars: PMStars, dx, dy):
    """Variance of the PM error along the direction (dx, dy) [(mas/yr)^2]."""
    n = np.hypot(dx, dy)
    safe = np.where(n > 0, n, 1.0)
    cx, cy = np.where(n > 0, dx / safe, 1.0), np.where(n > 0, dy / safe, 0.0)
    ex, ey, rho = stars.pm_x_err, stars.pm_y_err, stars.pm_xy_corr
    return (cx * ex) ** 2 + (cy * ey) ** 2 + 2.0 * cx * cy * rho * ex * ey


def largest_error(stars: PMStars):
    """Square root of the largest eigenvalue of the PM error covariance [mas/yr].

    Parameters
    ----------
    stars : PMStars
        The stars (errors [mas/yr] and their correlation).

    Returns
    -------
    ndarray
        Largest 1-sigma error per star [mas/yr].
    """
    a, c = stars.pm_x_err**2, stars.pm_y_err**2
    b = stars.pm_xy_corr * stars.pm_x_err * stars.pm_y_err
    return np.sqrt(0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b))


def rice_sf(t: ArrayLike, nu: ArrayLike, sigma: ArrayLike):
    """``P(|X| > t)`` for a 2-D isotropic Gaussian ``X`` with mean modulus ``nu``, sd ``sigma``.

    Computed as the non-central chi-square survival function (accurate far in the
    tail, unlike ``scipy.stats.rice.sf``).

    Parameters
    ----------
    t : array_like
        Threshold modulus.
    nu : array_like
        Modulus of the mean, same unit.
    sigma : array_like
        1-D standard deviation, same unit.

    Returns
    -------
    ndarray
        Tail probability.
    """
    return stats.ncx2.sf((t / sigma) ** 2, 2, (nu / sigma) ** 2)


def distance_nodes(distance: float, distance_error: float):
    """Gauss-Hermite nodes [kpc] and weights (sum 1) of the Gaussian distance prior.

    Parameters
    ----------
    distance : float
        Prior mean [kpc].
    distance_error : float
        Prior sd [kpc]; <= 0: the distance alone, weight 1.

    Returns
    -------
    nodes : ndarray
        Distances [kpc] (at least 5 % of ``distance``).
    weights : ndarray
        Weights, sum 1.
    """
    if distance_error <= 0:
        return np.array([distance]), np.array([1.0])
    z, w = np.polynomial.hermite_e.hermegauss(_N_DISTANCE_NODES)
    d = np.maximum(distance + distance_error * z, 0.05 * distance)
    return d, w / w.sum()


def p_value(
    mu: np.ndarray, sigma: np.ndarray, v_esc: np.ndarray, d_nodes: np.ndarray, d_weights: np.ndarray
):
    """p-value of an observed PM modulus ``mu`` if the true speed were the escape speed.

    Parameters
    ----------
    mu, sigma : ndarray
        Observed PM modulus and the (largest) error [mas/yr].
    v_esc : ndarray
        Escape speed [km/s].
    d_nodes, d_weights : ndarray
        Distance prior nodes [kpc] and weights.
    """
    p = np.zeros(np.shape(mu))
    for d, w in zip(d_nodes, d_weights):
        p += w * rice_sf(mu, v_esc / (KMS_PER_MASYR_KPC * d), sigma)
    return p


def threshold(
    sigma: np.ndarray,
    v_esc: np.ndarray,
    d_nodes: np.ndarray,
    d_weights: np.ndarray,
    alpha: float,
    iterations: int = 60,
):
    """PM modulus [mas/yr] above which a star is fast at level ``alpha`` (bisection).

    Parameters
    ----------
    sigma : ndarray
        Largest PM error of each star [mas/yr].
    v_esc : ndarray
        Escape speed at each star [km/s].
    d_nodes, d_weights : ndarray
        Distance prior nodes [kpc] and weights.
    alpha : float
        One-sided p-value threshold.
    iterations : int
        Bisection steps.

    Returns
    -------
    ndarray
        Threshold modulus per star [mas/yr].
    """
    mu_esc = v_esc / (KMS_PER_MASYR_KPC * np.min(d_nodes))
    lo = v_esc / (KMS_PER_MASYR_KPC * np.max(d_nodes))
    hi = mu_esc + 50.0 * sigma
    lo = np.broadcast_to(lo, np.shape(hi)).astype(float)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = p_value(mid, sigma, v_esc, d_nodes, d_weights) < alpha
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return hi


# ---------------------------------------------------------------- error distribution


@dataclass(frozen=True)
class PullTails:
    """Width and tails of the PM error distribution measured from pulls.

    Parameters
    ----------
    source : str
        ``"truth"`` (measured minus true PM over the error: an artificial-star test),
        ``"kinematic"`` (PM over sqrt(model dispersion^2 + error^2)) or ``"none"``.
    n : int
        Pulls used.
    robust_sigma : float
        1.4826 x median absolute pull.
    frac_3, frac_5 : float
        Fraction of pulls beyond 3 and 5 robust sigma (Gaussian: 2.7e-3, 5.7e-7).
    dof : float
        Degrees of freedom of the Student t (robust width 1) with the same fraction
        beyond 3 sigma; inf when the tails are not heavier than Gaussian.
    """

    source: str = "none"
    n: int = 0
    robust_sigma: float = 1.0
    frac_3: float = math.nan
    frac_5: float = math.nan
    dof: float = math.inf

    @property
    def t_scale(self) -> float:
        """Scale of the Student t whose robust sigma (1.4826 MAD) is 1."""
        if not math.isfinite(self.dof):
            return 1.0
        return stats.norm.ppf(0.75) / stats.t.ppf(0.75, self.dof)

    def sf(self, z: ArrayLike):
        """One-sided tail probability beyond ``z`` robust sigma.

        Parameters
        ----------
        z : array_like
            Threshold [robust sigma].

        Returns
        -------
        ndarray
            Gaussian tail, or the fitted Student t's when ``dof`` is finite.
        """
        if not math.isfinite(self.dof):
            return stats.norm.sf(z)
        return stats.t.sf(z / self.t_scale, self.dof)


def measure_tails(pulls: ArrayLike, source: str) -> PullTails:
    """Robust width, tail fractions and a Student-t fit of a pull sample.

    Parameters
    ----------
    pulls : array_like
        Pulls (dimensionless); non-finite values are dropped.
    source : str
        Where the pulls come from (``"truth"`` or ``"kinematic"``), recorded.

    Returns
    -------
    PullTails
        The measured tails; Gaussian defaults with fewer than 20 pulls or zero width.
    """
    pulls = np.asarray(pulls, dtype=float)
    pulls = pulls[np.isfinite(pulls)]
    if pulls.size < 20:
        return PullTails()
    med = np.median(pulls)
    s = 1.4826 * np.median(np.abs(pulls - med))
    if not s > 0:
        return PullTails()
    z = np.abs(pulls - med) / s
    f3, f5 = float(np.mean(z > 3)), float(np.mean(z > 5))
    dof = math.inf
    gauss3 = 2.0 * stats.norm.sf(3.0)
    if f3 > gauss3 * (1.0 + 3.0 / math.sqrt(max(gauss3 * pulls.size, 1e-9))):
        tails = PullTails(dof=1.0)

        def excess(log_nu):
            object.__setattr__(tails, "dof", float(np.exp(log_nu)))
            return 2.0 * tails.sf(3.0) - f3

        lo, hi = np.log(0.5), np.log(1e4)
        if excess(lo) > 0 > excess(hi):
            from scipy.optimize import brentq

            dof = float(np.exp(brentq(excess, lo, hi, xtol=1e-4)))
        elif excess(lo) <= 0:
            dof = 0.5
    return PullTails(source, int(pulls.size), float(s), f3, f5, dof)


def pulls_of(stars: PMStars, dispersion=None) -> tuple[np.ndarray, str]:
    """Pulls for the error model: against the truth when known, else kinematic.

    Parameters
    ----------
    stars : PMStars
    dispersion : callable, optional
        ``R [arcsec] -> 1-D dispersion [mas/yr]`` of the no-IMBH model, for
        kinematic pulls.
    """
    if stars.pm_x_true is not None and stars.pm_y_true is not None:
        px = (stars.pm_x - stars.pm_x_true) / stars.pm_x_err
        py = (stars.pm_y - stars.pm_y_true) / stars.pm_y_err
        pulls = np.concatenate([px, py])
        if np.isfinite(pulls).sum() >= 20:
            return pulls, "truth"
    if dispersion is not None:
        s = np.asarray(dispersion(stars.R), float)
        px = stars.pm_x / np.hypot(s, stars.pm_x_err)
        py = stars.pm_y / np.hypot(s, stars.pm_y_err)
        return np.concatenate([px, py]), "kinematic"
    return np.array([]), "none"


# ---------------------------------------------------------------- binaries


def binary_kicks(n: int, rng: np.random.Generator, baseline: float, settings: FastStarSettings):
    """Apparent 2-D velocity [km/s] of unresolved binaries' photocentres over a baseline.

    Circular orbits, periods log-normal in days (``binary_log_period``), mass ratio
    uniform in [0.1, 1], luminosity ~ M^3.5 (main sequence), random orientation and
    phase; binaries wider than ``binary_max_separation`` are dropped (redrawn as
    ``0``-kick singles would bias; they are simply absent). The photocentre
    semi-major axis is ``a (q / (1 + q) - L2 / (L1 + L2))``; its displacement
    between two epochs ``baseline`` apart over the baseline is the apparent extra
    velocity (what a two-epoch proper motion measures).

    Parameters
    ----------
    n : int
        Number of binaries.
    rng : numpy.random.Generator
        Random numbers.
    baseline : float
        Epoch baseline [yr].
    settings : FastStarSettings
        The binary population (period distribution, primary mass [solMass], widest
        separation [AU]).

    Returns
    -------
    ndarray
        Apparent speed [km/s] per binary; 0 for binaries wider than
        ``binary_max_separation``.
    """
    m1 = settings.binary_primary_mass
    mean, sd = settings.binary_log_period
    q = rng.uniform(0.1, 1.0, n)
    period_yr = 10.0 ** rng.normal(mean, sd, n) / 365.25
    a_au = (m1 * (1.0 + q) * period_yr**2) ** (1.0 / 3.0)
    lum = q**3.5
    alpha = a_au * np.abs(q / (1.0 + q) - lum / (1.0 + lum))
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    cos_i = rng.uniform(-1.0, 1.0, n)
    half = np.pi * baseline / period_yr
    chord = 2.0 * alpha * np.abs(np.sin(half))
    # chord direction in the orbital plane at the mid phase; its sky projection
    dx, dy = -np.sin(phase) * chord, np.cos(phase) * chord * cos_i
    kick = KMS_PER_AU_YR * np.hypot(dx, dy) / baseline
    return np.where(a_au <= settings.binary_max_separation, kick, 0.0)


# ---------------------------------------------------------------- expected counts


def _truncated_rayleigh(s, v_max, k):
    """Stratified draws ``(n, k)`` of a 2-D isotropic Gaussian's modulus truncated at v_max."""
    u_ = (np.arange(k) + 0.5) / k
    s = np.maximum(np.asarray(s, float), 1e-12)[:, None]
    f_max = -np.expm1(-0.5 * (np.asarray(v_max, float)[:, None] / s) ** 2)
    return s * np.sqrt(-2.0 * np.log1p(-u_[None, :] * f_max))


def expected_flags(
    t: np.ndarray,
    sigma: np.ndarray,
    s: np.ndarray,
    v_max: np.ndarray,
    tails: PullTails | None,
    kicks: np.ndarray | None = None,
    k: int = 64,
):
    """Per-star probability of exceeding the threshold ``t`` [mas/yr].

    True speeds: modulus of a 2-D Gaussian of 1-D dispersion ``s`` truncated at
    ``v_max`` (stratified, ``k`` per star); errors: isotropic Gaussian ``sigma``
    (Rice), or the pulls' Student t along the motion when ``tails`` is given;
    ``kicks`` (n, k) [mas/yr] are added as vectors at random angles.

    Parameters
    ----------
    t : ndarray
        Threshold per star [mas/yr].
    sigma : ndarray
        PM error per star [mas/yr].
    s : ndarray
        1-D model dispersion per star [mas/yr].
    v_max : ndarray
        Truncation of the true speeds per star [mas/yr].
    tails : PullTails or None
        Measured error tails (None: Gaussian errors).
    kicks : ndarray, shape (n, k), optional
        Binary kicks [mas/yr].
    k : int
        Stratified draws per star.

    Returns
    -------
    ndarray
        Probability per star.
    """
    nu = _truncated_rayleigh(s, v_max, k)
    if kicks is not None:
        ang = np.random.default_rng(12345).uniform(0, 2 * np.pi, nu.shape)
        nu = np.hypot(nu + kicks * np.cos(ang), kicks * np.sin(ang))
    tt, sg = np.asarray(t)[:, None], np.asarray(sigma)[:, None]
    if tails is None or not math.isfinite(tails.dof):
        prob = rice_sf(tt, nu, sg)
    else:
        prob = np.maximum(tails.sf((tt - nu) / sg), rice_sf(tt, nu, sg))
    return prob.mean(axis=1)


# ---------------------------------------------------------------- lower mass limit


def lower_mass_limit(
    R, pm, cov, v_esc, distance, distance_error, confidence=0.95, n_draws=4000, seed=0
):
    """Lower limit on the central mass binding every given star (solMass).

    Parameters
    ----------
    R : ndarray (n,)
        Projected radii [arcsec].
    pm : ndarray (n, 2)
        Measured PMs [mas/yr].
    cov : ndarray (n, 2, 2)
        Their error covariances [(mas/yr)^2].
    v_esc : ndarray (n,)
        Conservative no-IMBH escape speed at ``r = R`` [km/s].
    distance, distance_error : float
        [kpc].
    confidence : float
    n_draws : int
    seed : int

    Returns
    -------
    limit : float
        ``1 - confidence`` quantile of ``max_i M_i`` over the draws (0 for no stars).
    per_star : ndarray (n,)
        Each star's own limit at the same confidence.
    """
    n = len(R)
    if n == 0:
        return 0.0, np.zeros(0)
    rng = np.random.default_rng(seed)
    d = distance + distance_error * rng.standard_normal(n_draws)
    d = np.maximum(d, 0.05 * distance)
    chol = np.linalg.cholesky(cov)
    z = rng.standard_normal((n_draws, n, 2))
    mu = pm[None, :, :] + np.einsum("nij,knj->kni", chol, z)
    v2 = (KMS_PER_MASYR_KPC * d[:, None]) ** 2 * np.sum(mu * mu, axis=2)
    r_pc = np.asarray(R)[None, :] * d[:, None] * PC_PER_ARCSEC_KPC
    m = np.maximum(r_pc * (v2 - np.asarray(v_esc)[None, :] ** 2) / (2.0 * G_PC_KMS2_MSUN), 0.0)
    q = 1.0 - confidence
    return float(np.quantile(m.max(axis=1), q)), np.quantile(m, q, axis=0)


def poisson_probabilities(n_obs: int, expected: float) -> tuple[float, float]:
    """``P(N = n_obs)`` and ``P(N >= n_obs)`` for a Poisson mean ``expected``.

    Parameters
    ----------
    n_obs : int
        Observed count.
    expected : float
        Poisson mean (negative values are taken as 0).

    Returns
    -------
    p_equal, p_at_least : float
        The two probabilities.
    """
    lam = max(float(expected), 0.0)
    if lam == 0.0:
        return float(n_obs == 0), float(n_obs == 0)
    return float(stats.poisson.pmf(n_obs, lam)), float(stats.poisson.sf(n_obs - 1, lam))


# ---------------------------------------------------------------- the test


@dataclass
class FastStarResult:
    """Outcome of :func:`fast_star_test`.

    Parameters
    ----------
    possible : bool
        False when no test could be made (``note`` says why); then nothing is fast.
    table : QTable
        Candidates (``v_2D > v_esc`` or fast): ``id``, ``R`` [arcsec], ``v_2d``,
        ``v_2d_err``, ``v_esc``, ``v_esc_imbh`` [km/s], ``p_value``, ``significance``
        (Gaussian sigma), ``fast``, ``m_min`` [solMass] (own lower limit).
    attrs : dict
        Scalars for the dynamics product (see docs/dynamics.md).
    curves : dict
        ``R`` [arcsec] grid and escape-velocity curves [km/s] for the plot, plus
        ``R_all``, ``v_all`` (every usable star).
    """

    possible: bool
    table: QTable
    attrs: dict
    curves: dict = field(default_factory=dict)
    note: str = ""


_TABLE_UNITS = {
    "id": None,
    "R": u.arcsec,
    "v_2d": u.km / u.s,
    "v_2d_err": u.km / u.s,
    "v_esc": u.km / u.s,
    "v_esc_imbh": u.km / u.s,
    "p_value": None,
    "significance": None,
    "fast": None,
    "m_min": u.Msun,
}


def _table(cols: dict) -> QTable:
    t = QTable()
    for name, unit in _TABLE_UNITS.items():
        val = np.asarray(cols[name])
        t[name] = val if unit is None else val * unit
    return t


def _escape(models, R_arcsec, distance):
    """Escape speeds [km/s] of every model at ``r = R``: shape (n_models, n_radii)."""
    from mavispm.dynamics.escape_velocity import escape_speed_at_projected

    return np.stack([escape_speed_at_projected(m, R_arcsec, distance) for m in models])


def no_test(reason: str, settings: FastStarSettings, n_dropped: int = 0) -> FastStarResult:
    """An explicit "no test possible" result: no fast star, no limit, the reason.

    Parameters
    ----------
    reason : str
        Why no test was possible (stored as the note).
    settings : FastStarSettings
        The settings (``alpha`` and ``confidence`` are recorded in the attributes).
    n_dropped : int
        Stars dropped as unusable.

    Returns
    -------
    FastStarResult
        An empty result with ``possible`` False.
    """
    empty = {k: np.zeros(0, dtype=np.int64 if k == "id" else float) for k in _TABLE_UNITS}
    empty["fast"] = np.zeros(0, bool)
    attrs = {
        "fast_test_possible": False,
        "fast_test_note": reason,
        "fast_n_stars": 0,
        "fast_n_dropped": int(n_dropped),
        "fast_n_candidates": 0,
        "fast_n_significant": 0,
        "fast_alpha": settings.alpha,
        "bh_mass_lower_limit": 0.0 * u.Msun,
        "bh_mass_lower_limit_confidence": settings.confidence,
    }
    return FastStarResult(False, _table(empty), attrs, {}, reason)


def fast_star_test(
    stars: PMStars,
    distance: float,
    no_imbh_models,
    settings: FastStarSettings | None = None,
    distance_error: float = 0.0,
    dispersion=None,
    imbh_models=None,
    imbh_dispersion=None,
    baseline: float | None = None,
    field_radius: float | None = None,
    seed: int = 0,
    stellar_models=None,
) -> FastStarResult:
    """Run the fast-star test on measured proper motions.

    Parameters
    ----------
    stars : PMStars
        PMs relative to the cluster mean motion.
    distance : float
        [kpc] (> 0).
    no_imbh_models : sequence of mass models
        Posterior samples of every mass model without a central point mass
        (cluster alone; cluster + extended dark component): PosteriorMassModel, or
        any object with ``potential(r)`` (length Quantity -> (km/s)^2, e.g.
        :class:`mavispm.dynamics.mass_models.MassModel`).
    settings : FastStarSettings
    distance_error : float
        Gaussian distance prior sd [kpc] (``settings.distance_error`` wins if > 0).
    dispersion : callable, optional
        ``R [arcsec] -> 1-D PM dispersion [mas/yr]`` of the no-IMBH model (false-star
        budget from errors and binaries; without it those terms use the worst case,
        every star at the escape speed).
    imbh_models, imbh_dispersion : optional
        The same for the IMBH model (escape curve, expected number of fast stars).
    baseline : float, optional
        Epoch baseline [yr] (``settings.baseline`` wins); without one the binary term is NaN.
    field_radius : float, optional
        Radius [arcsec] of the area where field stars count (default: the largest R).
    seed : int
    stellar_models : sequence of mass models, optional
        Further potentials without a point mass for the lower limit: the stellar (and
        dark) parts of the IMBH models, whose cusp can make the stars' potential deeper
        than any no-IMBH model's. The limit subtracts the deepest (the
        ``escape_quantile`` of each set, the larger of the two).

    Returns
    -------
    FastStarResult

    Raises
    ------
    InputError
        Non-positive distance or no mass models.
    """
    s = settings or FastStarSettings()
    if not (np.isfinite(distance) and distance > 0):
        raise InputError(f"fast-star test needs a distance > 0 kpc, got {distance}")
    if len(no_imbh_models) == 0:
        raise InputError("fast-star test needs posterior samples of the no-IMBH models")
    d_err = s.distance_error if s.distance_error > 0 else float(distance_error)
    baseline = s.baseline if s.baseline is not None else baseline
    n_in = len(stars)
    stars, n_drop = usable_stars(stars)
    if len(stars) < s.min_stars:
        return no_test(
            f"no test possible: {len(stars)} usable stars (finite PMs, errors > 0) of {n_in}, "
            f"fewer than min_stars = {s.min_stars}",
            s,
            n_drop,
        )
    # error model from the pulls; rescale the errors when the truth pulls are wider
    pulls, source = pulls_of(stars, dispersion)
    tails = measure_tails(pulls, source)
    err_scale = 1.0
    if s.rescale_errors and tails.source == "truth" and tails.robust_sigma > 1.0:
        err_scale = tails.robust_sigma
        stars = PMStars(
            **{
                **{k: getattr(stars, k) for k in stars.__dataclass_fields__},
                "pm_x_err": stars.pm_x_err * err_scale,
                "pm_y_err": stars.pm_y_err * err_scale,
            }
        )
    d_nodes, d_w = distance_nodes(distance, d_err)
    kms = KMS_PER_MASYR_KPC * distance
    # escape velocity: r = R, high quantile over the posterior
    esc = _escape(no_imbh_models, stars.R, distance)
    v_esc = np.quantile(esc, s.escape_quantile, axis=0)
    mu = np.hypot(stars.pm_x, stars.pm_y)
    sigma = largest_error(stars)
    v, v_err = velocity_2d(stars, distance, d_err)
    p = p_value(mu, sigma, v_esc, d_nodes, d_w)
    fast = p < s.alpha
    t = threshold(sigma, v_esc, d_nodes, d_w, s.alpha)
    # expected false fast stars under the no-IMBH model
    mu_esc = v_esc / kms
    s_loc = np.asarray(dispersion(stars.R), float) if dispersion is not None else None  # mas/yr
    rng = np.random.default_rng([seed, 20])
    k = 64
    if s_loc is not None:
        p_gauss = expected_flags(t, sigma, s_loc, mu_esc, None, k=k)
        p_tails = expected_flags(t, sigma, s_loc, mu_esc, tails, k=k)
    else:  # worst case: every star at the escape speed
        p_gauss = rice_sf(t, mu_esc, sigma)
        p_tails = np.maximum(p_gauss, tails.sf((t - mu_esc) / sigma))
    n_err_gauss, n_err_tails = float(p_gauss.sum()), float(p_tails.sum())
    if baseline is not None and s.binary_fraction > 0:
        # excess flag probability of a binary over a single star with the same true speed
        kicks = binary_kicks(len(stars) * k, rng, baseline, s).reshape(len(stars), k) / kms
        if s_loc is not None:
            p_bin = expected_flags(t, sigma, s_loc, mu_esc, None, kicks=kicks, k=k)
        else:  # worst case: at the escape speed, kick along the motion
            p_bin = rice_sf(t[:, None], mu_esc[:, None] + kicks, sigma[:, None]).mean(axis=1)
        n_binary = float(s.binary_fraction * np.maximum(p_bin - p_gauss, 0.0).sum())
    else:
        n_binary = 0.0 if s.binary_fraction == 0 else math.nan
    # field stars: uniform density inside the field radius
    r_field = float(field_radius if field_radius is not None else stars.R.max())
    R_grid = np.linspace(0.0, r_field, 65)[1:] - 0.5 * r_field / 64
    esc_grid = np.quantile(_escape(no_imbh_models, R_grid, distance), s.escape_quantile, axis=0)
    sig_med = float(np.median(sigma))
    t_grid = threshold(np.full(R_grid.size, sig_med), esc_grid, d_nodes, d_w, s.alpha)
    if s.field_density > 0:
        sf = np.hypot(s.field_pm_sigma, sig_med)
        p_field = rice_sf(t_grid, np.hypot(*s.field_pm_mean), sf)
        n_field = float(s.field_density * np.sum(2.0 * np.pi * R_grid * (r_field / 64) * p_field))
    else:
        n_field = 0.0
    n_false = n_err_tails + (0.0 if math.isnan(n_binary) else n_binary) + n_field
    # IMBH model: escape curve and expected number of fast stars
    v_esc_imbh = np.full(len(stars), np.nan)
    esc_imbh_grid = np.full(R_grid.size, np.nan)
    n_exp_imbh = math.nan
    if imbh_models:
        v_esc_imbh = np.median(_escape(imbh_models, stars.R, distance), 0)
        esc_imbh_grid = np.median(_escape(imbh_models, R_grid, distance), 0)
        if imbh_dispersion is not None:
            s1 = np.asarray(imbh_dispersion(stars.R), float)
            p1 = expected_flags(t, sigma, s1, v_esc_imbh / kms, tails, k=k)
            n_exp_imbh = float(p1.sum()) + n_false - n_err_tails
    # lower mass limit from the significant fast stars
    cov = np.empty((len(stars), 2, 2))
    cov[:, 0, 0] = stars.pm_x_err**2
    cov[:, 1, 1] = stars.pm_y_err**2
    cov[:, 0, 1] = cov[:, 1, 0] = stars.pm_xy_corr * stars.pm_x_err * stars.pm_y_err
    m_min = np.zeros(len(stars))
    limit = 0.0
    v_esc_limit = v_esc
    if stellar_models:
        esc_st = np.quantile(_escape(stellar_models, stars.R, distance), s.escape_quantile, 0)
        v_esc_limit = np.maximum(v_esc, esc_st)
    if fast.any():
        limit, per = lower_mass_limit(
            stars.R[fast],
            np.stack([stars.pm_x[fast], stars.pm_y[fast]], axis=1),
            cov[fast],
            v_esc_limit[fast],
            distance,
            d_err,
            s.confidence,
            s.n_monte_carlo,
            seed,
        )
        m_min[fast] = per
    n_fast = int(fast.sum())
    p0 = poisson_probabilities(n_fast, n_false)
    p1 = poisson_probabilities(n_fast, n_exp_imbh) if math.isfinite(n_exp_imbh) else (np.nan,) * 2
    cand = fast | (v > v_esc)
    table = _table(
        {
            "id": np.asarray(stars.id)[cand],
            "R": stars.R[cand],
            "v_2d": v[cand],
            "v_2d_err": v_err[cand],
            "v_esc": v_esc[cand],
            "v_esc_imbh": v_esc_imbh[cand],
            "p_value": p[cand],
            "significance": stats.norm.isf(np.maximum(p[cand], 1e-300)),
            "fast": fast[cand],
            "m_min": m_min[cand],
        }
    )
    table.sort("p_value")
    note = "" if n_fast else "no significant fast star"
    attrs = {
        "fast_test_possible": True,
        "fast_test_note": note,
        "fast_n_stars": int(len(stars)),
        "fast_n_dropped": n_drop,
        "fast_n_candidates": int(cand.sum()),
        "fast_n_significant": n_fast,
        "fast_alpha": s.alpha,
        "fast_escape_quantile": s.escape_quantile,
        "fast_n_models": len(no_imbh_models),
        "fast_distance_error": d_err * u.kpc,
        "fast_error_scale": err_scale,
        "fast_pull_source": tails.source,
        "fast_pull_robust_sigma": tails.robust_sigma,
        "fast_pull_frac_3": tails.frac_3,
        "fast_pull_frac_5": tails.frac_5,
        "fast_pull_dof": tails.dof if math.isfinite(tails.dof) else -1.0,
        "fast_expected_false_errors_gaussian": n_err_gauss,
        "fast_expected_false_errors": n_err_tails,
        "fast_expected_false_binaries": n_binary,
        "fast_expected_false_field": n_field,
        "fast_expected_false": n_false,
        "fast_expected_imbh": n_exp_imbh,
        "fast_p_count_no_imbh": p0[0],
        "fast_p_count_ge_no_imbh": p0[1],
        "fast_p_count_imbh": p1[0],
        "fast_p_count_ge_imbh": p1[1],
        "fast_baseline": (math.nan if baseline is None else baseline) * u.yr,
        "bh_mass_lower_limit": limit * u.Msun,
        "bh_mass_lower_limit_confidence": s.confidence,
        "v_esc_center_no_imbh": float(esc_grid[0]) * u.km / u.s,
    }
    curves = {
        "R": R_grid,
        "v_esc_no_imbh": esc_grid,
        "v_esc_no_imbh_median": np.median(_escape(no_imbh_models, R_grid, distance), 0),
        "v_esc_imbh": esc_imbh_grid,
        "R_all": stars.R,
        "v_all": v,
        "v_err_all": v_err,
        "fast_all": fast,
    }
    return FastStarResult(True, table, attrs, curves, note)


# ---------------------------------------------------------------- products and fits


def _pm_xy_spec():
    from mavispm.core.products import TableSpec

    return TableSpec(
        required={
            "id": "",
            "x": "arcsec",
            "y": "arcsec",
            "R": "arcsec",
            "pm_x": "mas/yr",
            "pm_y": "mas/yr",
            "pm_x_err": "mas/yr",
            "pm_y_err": "mas/yr",
        },
        optional={"pm_xy_corr": "", "flag": "", "pm_x_true": "mas/yr", "pm_y_true": "mas/yr"},
        allow_nan=("pm_x", "pm_y", "pm_x_err", "pm_y_err", "pm_xy_corr", "pm_x_true", "pm_y_true"),
    )


def read_pm_stars(
    path: str | os.PathLike, field_radius: float | None = None, use_flagged: bool = False
):
    """Stars of a propermotions product for the fast-star test, and the epoch baseline.

    Flagged stars are dropped unless ``use_flagged``; stars beyond ``field_radius``
    [arcsec] are dropped. NaN motions or errors are kept here (the test drops and
    counts them).

    Parameters
    ----------
    path : str or os.PathLike
        The ``propermotions`` product.
    field_radius : float, optional
        Largest projected radius kept [arcsec].
    use_flagged : bool
        Keep flagged stars.

    Returns
    -------
    stars : PMStars
    baseline : float or None
        Span of the product's ``epochs`` [yr].

    Raises
    ------
    InputError
        Missing columns (named), negative errors.
    """
    from mavispm.core.products import read_product

    prod = read_product(path, "propermotions", specs={"stars": _pm_xy_spec()}, load_arrays=False)
    t = prod.tables["stars"]

    def col(name, unit=None):
        c = t[name]
        return np.asarray(c.to_value(unit) if unit else c, dtype=float)

    mas = u.mas / u.yr
    for name in ("pm_x_err", "pm_y_err"):
        if np.any(col(name, mas) < 0):
            raise InputError("negative errors", path=path, column=name)
    keep = np.ones(len(t), bool)
    if "flag" in t.colnames and not use_flagged:
        keep &= np.asarray(t["flag"]) == 0
    R = col("R", u.arcsec)
    if field_radius is not None:
        keep &= R <= field_radius
    has_truth = "pm_x_true" in t.colnames and "pm_y_true" in t.colnames
    stars = PMStars(
        id=np.asarray(t["id"])[keep],
        R=R[keep],
        pm_x=col("pm_x", mas)[keep],
        pm_y=col("pm_y", mas)[keep],
        pm_x_err=col("pm_x_err", mas)[keep],
        pm_y_err=col("pm_y_err", mas)[keep],
        pm_xy_corr=(col("pm_xy_corr") if "pm_xy_corr" in t.colnames else np.zeros(len(t)))[keep],
        pm_x_true=col("pm_x_true", mas)[keep] if has_truth else None,
        pm_y_true=col("pm_y_true", mas)[keep] if has_truth else None,
        x=col("x", u.arcsec)[keep],
        y=col("y", u.arcsec)[keep],
    )
    epochs = prod.attrs.get("epochs")
    baseline = None
    if epochs is not None:
        ep = np.atleast_1d(
            u.Quantity(epochs, u.yr).to_value(u.yr)
            if hasattr(epochs, "unit")
            else np.asarray(epochs, float)
        )
        if ep.size >= 2 and np.ptp(ep) > 0:
            baseline = float(np.ptp(ep))
    return stars, baseline


def model_dispersion(likelihood, theta: ArrayLike):
    """``R [arcsec] -> 1-D PM dispersion [mas/yr]`` (rms of radial and tangential) of a model.

    Parameters
    ----------
    likelihood : DiscreteLikelihood
        The model's likelihood (its ``dispersion_at``).
    theta : array_like
        Physical parameter vector.

    Returns
    -------
    callable
        ``dispersion(R)`` of projected radii [arcsec] (at least 1e-3), in [mas/yr].
    """
    theta = np.asarray(theta, dtype=float)

    def dispersion(R):
        R = np.maximum(np.asarray(R, dtype=float), 1e-3)
        return np.sqrt(np.mean(likelihood.dispersion_at(theta, R) ** 2, axis=0))

    return dispersion


def stars_from_sample(sample) -> PMStars:
    """PMStars from the dynamics stage's StarSample (radial/tangential frame, no truth).

    The modulus of the motion and its errors are frame invariant; the sample's
    radial/tangential errors are independent (no x/y correlation).

    Parameters
    ----------
    sample : StarSample
        The dynamics stage's stars.

    Returns
    -------
    PMStars
        The same stars (ids are row numbers).
    """
    n = len(sample.R)
    return PMStars(
        id=np.arange(n),
        R=np.asarray(sample.R, float),
        pm_x=np.asarray(sample.v_r, float),
        pm_y=np.asarray(sample.v_t, float),
        pm_x_err=np.asarray(sample.e_r, float),
        pm_y_err=np.asarray(sample.e_t, float),
        pm_xy_corr=np.zeros(n),
        x=None if sample.x is None else np.asarray(sample.x, float),
        y=None if sample.y is None else np.asarray(sample.y, float),
    )


def about_fitted_centre(
    stars: PMStars, samples: ArrayLike, names: Sequence[str], n_sigma: float = 2.0
):
    """Stars about a fit's centre and systemic motion (posterior medians), conservatively.

    ``x0, y0`` [arcsec] and ``pm_x0, pm_y0`` [mas/yr] are the fitted centre and mean
    motion (when the fit has them). Motions become relative to the median systemic
    motion, whose posterior sd is added to the PM errors; radii are measured from the
    median centre and reduced by ``n_sigma`` times its larger posterior sd (clipped
    at 0): a smaller radius means a higher escape velocity and a lower mass limit.

    Parameters
    ----------
    stars : PMStars
        Stars with positions about the field centre.
    samples : array_like, shape (n_samples, n_params)
        Posterior samples.
    names : sequence of str
        Parameter names of the sample columns.
    n_sigma : float
        Radii are reduced by this many posterior sd of the centre.

    Returns
    -------
    PMStars
    """
    samples = np.asarray(samples, float)
    names = list(names)

    def stat(name):
        if name not in names:
            return 0.0, 0.0
        col = samples[:, names.index(name)]
        return float(np.median(col)), float(np.std(col))

    (x0, sx), (y0, sy) = stat("x0"), stat("y0")
    (px, spx), (py, spy) = stat("pm_x0"), stat("pm_y0")
    fields = {k: getattr(stars, k) for k in stars.__dataclass_fields__}
    if stars.x is not None and (x0 or y0 or sx or sy):
        R = np.hypot(stars.x - x0, stars.y - y0)
        fields.update(x=stars.x - x0, y=stars.y - y0, R=np.maximum(R - n_sigma * max(sx, sy), 0))
    if px or py or spx or spy:
        fields.update(
            pm_x=stars.pm_x - px,
            pm_y=stars.pm_y - py,
            pm_x_err=np.hypot(stars.pm_x_err, spx),
            pm_y_err=np.hypot(stars.pm_y_err, spy),
        )
        if stars.pm_x_true is not None:
            fields.update(pm_x_true=stars.pm_x_true - px, pm_y_true=stars.pm_y_true - py)
    return PMStars(**fields)


def run_on_fits(
    propermotions, settings, fits, distance, field_radius, seed=0, stars=None
) -> FastStarResult:
    """The fast-star test of a dynamics run (the stage calls this with its fits).

    Parameters
    ----------
    propermotions : path or None
        The propermotions product of the fit (full PM covariance, truth pulls);
        None: the fit's own star sample ``stars`` is used.
    settings : DynamicsSettings
        With ``fast_stars`` set (FastStarSettings).
    fits : sequence of ModelFit
        The fits of the comparison (:func:`mavispm.dynamics.fit.fit_model`). Those
        without a ``bh_mass`` parameter (``none``, and the cluster + extended dark
        component model ``dark``) form the no-IMBH set; the first with one is the
        IMBH model (escape curve, expected fast-star count). Stars are taken about
        the no-IMBH fit's centre and systemic motion when fitted
        (:func:`about_fitted_centre`).
    distance, field_radius : float
        [kpc], [arcsec].
    seed : int
    stars : StarSample, optional
        The fit's stars (used without a propermotions product).
    """
    from mavispm.dynamics.escape_velocity import posterior_mass_models

    fs = settings.fast_stars or FastStarSettings()
    with_bh = [f for f in fits if "bh_mass" in f.space.names]
    without = [f for f in fits if "bh_mass" not in f.space.names]
    if not without:
        raise InputError("fast-star test needs a fit without a central point mass")
    baseline = None
    if propermotions is not None:
        pm, baseline = read_pm_stars(propermotions, field_radius, settings.use_flagged)
    elif stars is not None:
        pm = stars_from_sample(stars)
    else:
        raise InputError("fast-star test needs the proper motions (product or star sample)")
    no_imbh = without[0]
    pm = about_fitted_centre(pm, no_imbh.chain.samples, no_imbh.space.names)
    # the no-IMBH set: every model without a point mass, n_models samples in all
    per = max(1, fs.n_models // len(without))
    models0 = [
        m for f in without for m in posterior_mass_models(f.likelihood, f.chain.samples, per, seed)
    ]
    imbh = with_bh[0] if with_bh else None
    models1 = None
    imbh_disp = None
    if imbh is not None:
        models1 = posterior_mass_models(imbh.likelihood, imbh.chain.samples, fs.n_models, seed)
        imbh_disp = model_dispersion(imbh.likelihood, imbh.chain.map_params)
    # stellar (+ dark) parts of the IMBH models: their cusp may be deeper (lower limit)
    per1 = max(1, fs.n_models // max(len(with_bh), 1))
    stellar = [
        m
        for f in with_bh
        for m in posterior_mass_models(f.likelihood, f.chain.samples, per1, seed, True)
    ]
    return fast_star_test(
        pm,
        distance,
        models0,
        fs,
        distance_error=settings.distance_sd(distance),
        dispersion=model_dispersion(no_imbh.likelihood, no_imbh.chain.map_params),
        imbh_models=models1,
        imbh_dispersion=imbh_disp,
        baseline=baseline,
        field_radius=field_radius,
        seed=seed,
        stellar_models=stellar or None,
    )
