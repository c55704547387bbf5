"""Per-exposure image motion and dynamic distortion of a stack of sub-exposures.

Each sub-exposure k of a stack sees a displacement field ``d_k(x)`` (mas) made of

* residual low-order image motion: common tilt (2 modes) and the linear
  anisoplanatic plate-scale modes (scale, rotation, two shears; Cameron et al.
  2009) of the NGS tip-tilt residual averaged over the sub-exposure;
* dynamic distortion: the quadratic and cubic terms of
  ``simulate.optics.distortion`` redrawn per sub-exposure.

Amplitudes. By default the low-order motion comes from the AO error budget of
the scene: the covariance of the atmospheric TT residual between field points
(``tiptilt.atmospheric_cross_covariance`` without the NGS noise, which averages
out within a sub-exposure) is projected by least squares on the six modes over
a 7 x 7 grid of the 15" science field, and scaled to one sub-exposure of length
T by the average of an exponentially correlated signal,
``f = 2 (tau / T)^2 (T / tau - 1 + exp(-T / tau))`` (~ 2 tau / T), with the
tilt correlation time ``tau = D / v_eff`` (the wind crossing the pupil,
``v_eff = (sum c_l |v_l|^(5/3))^(3/5)``). ``tilt``, ``plate_scale`` and
``distortion_rms`` override the budget with isotropic per-mode amplitudes.

Between sub-exposures each mode is an AR(1) sequence with
``rho = exp(-exptime / correlation_time)`` (independent draws for 0), so the
stack's mean displacement has variance ``sigma^2 / N`` for independent draws and
more when correlated. Draws are seeded by (``seed``, epoch).

The stack is their sum computed without rendering each sub-exposure: a star at
x gets the mean of its N displacements as a shift and their covariance (about
that mean) as an extra Gaussian blur, i.e. the stacked PSF is the PSF convolved
with the Gaussian of the same first two moments as the empirical distribution
of the N displacements (exact centroid and second moments).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from mavispm.core.config import unit_field
from mavispm.simulate.optics.distortion import _BASIS, SCIENCE_RADIUS, _basis_rms

if TYPE_CHECKING:
    from mavispm.simulate.optics.atmosphere import Layers
    from mavispm.simulate.optics.tiptilt import TipTiltField

__all__ = [
    "DISTORTION_TERMS",
    "ImageMotion",
    "ImageMotionSettings",
    "MOTION_MODES",
    "StackMotion",
    "budget_mode_covariance",
    "build_image_motion",
    "distortion_basis",
    "effective_wind_speed",
    "exposure_average_factor",
    "mode_basis",
    "noise_free_covariance",
]

#: low-order motion modes: common tilt and the linear plate-scale modes
MOTION_MODES = ("tilt_x", "tilt_y", "scale", "rotation", "shear1", "shear2")
#: per-exposure dynamic-distortion terms (unit RMS over the science field)
DISTORTION_TERMS = ("quadratic_x", "quadratic_y", "cubic")

_MODE_BASIS = {
    "tilt_x": lambda u, v: (np.ones_like(u), np.zeros_like(u)),
    "tilt_y": lambda u, v: (np.zeros_like(u), np.ones_like(u)),
    **{k: _BASIS[k] for k in ("scale", "rotation", "shear1", "shear2")},
}


@dataclass(frozen=True)
class ImageMotionSettings:
    """Per-exposure image motion (TOML table ``[scene.optics.image_motion]``).

    Parameters
    ----------
    enabled : bool
        Off (default): a stack is N identical sub-exposures.
    tilt : float or None
        RMS common tilt per axis per sub-exposure (mas); None: from the AO budget.
    plate_scale : float or None
        RMS displacement at r = 15" of each linear mode (scale, rotation, shears)
        per sub-exposure (mas); None: from the AO budget.
    tilt_correlation_time : float or None
        Correlation time of the TT residual within a sub-exposure (s); None: D / v_eff.
    correlation_time : float
        Correlation time of the motion modes between sub-exposures (s); 0 draws them
        independently.
    distortion_rms : float
        RMS over the science field of each dynamic-distortion term per sub-exposure (mas).
    distortion_correlation_time : float
        Correlation time of the dynamic distortion between sub-exposures (s).
    seed : int
        Seed of the draws (combined with the epoch).
    """

    enabled: bool = False
    tilt: float | None = unit_field(None, "mas", "RMS common tilt per axis per sub-exposure")
    plate_scale: float | None = unit_field(None, "mas", "RMS plate-scale mode at r = 15 arcsec")
    tilt_correlation_time: float | None = unit_field(None, "s", "TT residual correlation time")
    correlation_time: float = unit_field(0.0, "s", "mode correlation between sub-exposures")
    distortion_rms: float = unit_field(0.05, "mas", "RMS of each dynamic-distortion term")
    distortion_correlation_time: float = unit_field(
        300.0, "s", "dynamic-distortion correlation between sub-exposures"
    )
    seed: int = 0

    def __post_init__(self):
        for name in ("tilt", "plate_scale", "tilt_correlation_time"):
            v = getattr(self, name)
            if v is not None and not v >= 0:
                raise ValueError(f"{name} must be >= 0, got {v}")
        for name in ("correlation_time", "distortion_rms", "distortion_correlation_time"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


def mode_basis(x: ArrayLike, y: ArrayLike) -> np.ndarray:
    """Displacements (mas) per unit coefficient, shape (N, 2, 6), at positions (arcsec).

    Parameters
    ----------
    x, y : array_like
        Field positions [arcsec].

    Returns
    -------
    ndarray, shape (N, 2, 6)
        Displacement [mas] along x and y of each of :data:`MOTION_MODES` for a coefficient of
        1 mas.
    """
    u = np.asarray(x, float) / SCIENCE_RADIUS
    v = np.asarray(y, float) / SCIENCE_RADIUS
    cols = [np.stack(_MODE_BASIS[m](u, v), -1) for m in MOTION_MODES]
    return np.stack(cols, -1)


def distortion_basis(x: ArrayLike, y: ArrayLike) -> np.ndarray:
    """Unit-RMS dynamic-distortion terms (mas per unit coefficient), shape (N, 2, 3).

    Parameters
    ----------
    x, y : array_like
        Field positions [arcsec].

    Returns
    -------
    ndarray, shape (N, 2, 3)
        Displacement [mas] of each of :data:`DISTORTION_TERMS` for a coefficient of 1 mas RMS.
    """
    u = np.asarray(x, float) / SCIENCE_RADIUS
    v = np.asarray(y, float) / SCIENCE_RADIUS
    cols = [np.stack(_BASIS[t](u, v), -1) / _basis_rms(t) for t in DISTORTION_TERMS]
    return np.stack(cols, -1)


def exposure_average_factor(tau: float, exptime: float) -> float:
    """Variance of the T-average of a unit-variance signal with autocorrelation exp(-|t|/tau).

    Parameters
    ----------
    tau : float
        Correlation time [s]; <= 0 gives 0 (white signal).
    exptime : float
        Averaging time T [s].

    Returns
    -------
    float
        ``2 (tau/T)^2 (T/tau - 1 + exp(-T/tau))`` (dimensionless, in [0, 1]).
    """
    if tau <= 0:
        return 0.0
    r = exptime / tau
    if r < 1e-6:
        return 1.0
    return float(2.0 / r**2 * (r - 1.0 + np.exp(-r)))


def effective_wind_speed(weights: ArrayLike, velocities: ArrayLike) -> float:
    """``(sum c_l |v_l|^(5/3))^(3/5)`` (m/s) of layers with Cn^2 fractions ``weights``.

    Parameters
    ----------
    weights : array_like
        Cn^2 fractions (normalised here).
    velocities : array_like, shape (L, 2)
        Wind vectors [m/s].

    Returns
    -------
    float
        Effective wind speed [m/s].
    """
    w = np.asarray(weights, float)
    speed = np.hypot(*np.asarray(velocities, float).T)
    return float((np.sum(w / w.sum() * speed ** (5 / 3))) ** 0.6)


def budget_mode_covariance(tiptilt: TipTiltField, n_grid: int = 7) -> np.ndarray:
    """Covariance (6, 6) in mas^2 of the low-order modes of the atmospheric TT residual.

    Least-squares projection of the residual's cross-covariance on
    :data:`MOTION_MODES` over an ``n_grid`` x ``n_grid`` grid cut to the science
    circle; the NGS noise (white at the loop rate) is left out.

    Parameters
    ----------
    tiptilt : TipTiltField
        The tip-tilt residual model.
    n_grid : int
        Grid points per side.

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance [mas^2].
    """
    g = np.linspace(-SCIENCE_RADIUS, SCIENCE_RADIUS, n_grid)
    gx, gy = np.meshgrid(g, g)
    keep = np.hypot(gx, gy) <= SCIENCE_RADIUS * (1 + 1e-9)
    xy = np.stack([gx[keep], gy[keep]], -1)
    cov = noise_free_covariance(tiptilt, xy) if tiptilt.settings.enabled else None
    if cov is None:
        return np.zeros((6, 6))
    p = xy.shape[0]
    sigma = cov.transpose(0, 2, 1, 3).reshape(2 * p, 2 * p)
    b = mode_basis(xy[:, 0], xy[:, 1]).reshape(2 * p, 6)
    proj = np.linalg.solve(b.T @ b, b.T)  # (6, 2P)
    out = proj @ sigma @ proj.T
    # clip round-off negatives (the rotation mode of a tilt field, a gradient, is ~0)
    vals, vecs = np.linalg.eigh(0.5 * (out + out.T))
    out = (vecs * np.clip(vals, 0.0, None)) @ vecs.T
    return out * tiptilt.settings.scale_factor**2


def noise_free_covariance(tiptilt: TipTiltField, xy: ArrayLike) -> np.ndarray:
    """Atmospheric TT residual cross-covariance (P, P, 2, 2) mas^2 without the NGS noise.

    ``r = t - W s_meas`` with ``W = K_as C_ss^-1`` (the loop's MMSE weights,
    noise included); the noise term ``W C_n W^T`` is removed, leaving
    ``K_ab - W_a K_sb - K_as W_b^T + W_a K_ss W_b^T``.

    Parameters
    ----------
    tiptilt : TipTiltField
        The tip-tilt residual model.
    xy : array_like, shape (P, 2)
        Field positions [arcsec].

    Returns
    -------
    ndarray, shape (P, P, 2, 2)
        Cross-covariance [mas^2].
    """
    from mavispm.simulate.optics.atmosphere import MAS_PER_RAD

    a = np.asarray(xy, float) * 1000 / MAS_PER_RAD
    th = tiptilt._theta
    kab = tiptilt._cov(a[:, None, :] - a[None, :, :])
    kas = np.concatenate(list(np.moveaxis(tiptilt._cov(a[:, None, :] - th[None]), 1, 0)), -1)
    n = th.shape[0]
    kss = np.zeros((2 * n, 2 * n))
    for i in range(n):
        for j in range(n):
            kss[2 * i : 2 * i + 2, 2 * j : 2 * j + 2] = tiptilt._cov(th[i] - th[j])
    w = np.einsum("pij,jk->pik", kas, tiptilt._css_inv)  # (P, 2, 2n)
    term = (
        kab
        - np.einsum("pij,qkj->pqik", w, kas)
        - np.einsum("pij,qkj->pqik", kas, w)
        + np.einsum("pij,jk,qlk->pqil", w, kss, w)
    )
    return term * MAS_PER_RAD**2


def _ar1(rng: np.random.Generator, n: int, cov: np.ndarray, rho: float) -> np.ndarray:
    """n draws (n, K) of a stationary AR(1) vector sequence with covariance ``cov``."""
    k = cov.shape[0]
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    root = vecs * np.sqrt(np.clip(vals, 0.0, None))
    z = rng.standard_normal((n, k))
    out = np.empty((n, k))
    out[0] = z[0]
    c = np.sqrt(max(1.0 - rho**2, 0.0))
    for i in range(1, n):
        out[i] = rho * out[i - 1] + c * z[i]
    return out @ root.T


def _rng(seed: int, epoch: float) -> np.random.Generator:
    token = hashlib.sha256(f"image_motion:{int(seed)}:{float(epoch):.9f}".encode()).digest()
    return np.random.default_rng(int.from_bytes(token[:8], "little"))


@dataclass(frozen=True)
class StackMotion:
    """The drawn per-exposure coefficients of one stack.

    Parameters
    ----------
    modes : ndarray, shape (N, 6)
        Coefficients of :data:`MOTION_MODES` per sub-exposure (mas).
    distortion : ndarray, shape (N, 3)
        Coefficients of :data:`DISTORTION_TERMS` per sub-exposure (mas RMS units).
    """

    modes: np.ndarray
    distortion: np.ndarray

    def displacements(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Per-exposure displacements (N_exp, N_star, 2) in mas at positions (arcsec).

        Parameters
        ----------
        x, y : array_like
            Field positions of the stars [arcsec].

        Returns
        -------
        ndarray, shape (N_exp, N_star, 2)
            Displacements [mas].
        """
        d = np.einsum("sjm,km->ksj", mode_basis(x, y), self.modes)
        return d + np.einsum("sjt,kt->ksj", distortion_basis(x, y), self.distortion)

    def stack_moments(self, x: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Mean displacement (N_star, 2) and its covariance over the exposures (N_star, 2, 2),
        both in mas, computed from the coefficient moments (no per-exposure loop).

        Parameters
        ----------
        x, y : array_like
            Field positions of the stars [arcsec].

        Returns
        -------
        mean : ndarray, shape (N_star, 2)
            Mean displacement [mas].
        cov : ndarray, shape (N_star, 2, 2)
            Covariance over the exposures [mas^2].
        """
        bm = mode_basis(x, y)
        bd = distortion_basis(x, y)
        basis = np.concatenate([bm, bd], -1)  # (S, 2, 9)
        coef = np.concatenate([self.modes, self.distortion], -1)  # (N, 9)
        mean_c = coef.mean(axis=0)
        dev = coef - mean_c
        cov_c = dev.T @ dev / coef.shape[0]
        mean = basis @ mean_c
        cov = np.einsum("sim,mn,sjn->sij", basis, cov_c, basis)
        return mean, cov


class ImageMotion:
    """Per-exposure image motion model of a scene.

    Parameters
    ----------
    settings : ImageMotionSettings
    budget_covariance : ndarray (6, 6)
        Covariance of the motion modes of the TT residual (mas^2), before averaging
        over a sub-exposure.
    tau : float
        Correlation time of that residual (s).
    """

    def __init__(self, settings: ImageMotionSettings, budget_covariance: np.ndarray, tau: float):
        self.settings = settings
        self.budget_covariance = np.asarray(budget_covariance, float)
        self.tau = float(tau)

    @property
    def enabled(self) -> bool:
        """Whether stacks get per-exposure motion."""
        return bool(self.settings.enabled)

    def exposure_covariance(self, exptime: float) -> np.ndarray:
        """Covariance (6, 6) of the motion modes averaged over one sub-exposure (mas^2).

        Fixed ``tilt`` / ``plate_scale`` settings replace the budget's blocks.

        Parameters
        ----------
        exptime : float
            Sub-exposure time [s].

        Returns
        -------
        ndarray, shape (6, 6)
            Covariance [mas^2].
        """
        s = self.settings
        cov = self.budget_covariance * exposure_average_factor(self.tau, exptime)
        if s.tilt is not None:
            cov[:2, :] = 0.0
            cov[:, :2] = 0.0
            cov[0, 0] = cov[1, 1] = s.tilt**2
        if s.plate_scale is not None:
            cov[2:, :] = 0.0
            cov[:, 2:] = 0.0
            cov[2:, 2:] = s.plate_scale**2 * np.eye(4)  # the bases are 1 mas at r = 15"
        return cov

    def draw(self, nexp: int, exptime: float, epoch: float = 0.0) -> StackMotion:
        """Coefficients of ``nexp`` sub-exposures of ``exptime`` s at ``epoch`` (yr).

        Successive sub-exposures are AR(1)-correlated with the settings' correlation times.

        Parameters
        ----------
        nexp : int
            Number of sub-exposures.
        exptime : float
            Sub-exposure time [s].
        epoch : float
            Epoch [yr] (seeds the draw).

        Returns
        -------
        StackMotion
            The drawn coefficients.
        """
        s = self.settings
        rng = _rng(s.seed, epoch)
        rho = np.exp(-exptime / s.correlation_time) if s.correlation_time > 0 else 0.0
        modes = _ar1(rng, nexp, self.exposure_covariance(exptime), rho)
        rho_d = (
            np.exp(-exptime / s.distortion_correlation_time)
            if s.distortion_correlation_time > 0
            else 0.0
        )
        dist = _ar1(rng, nexp, s.distortion_rms**2 * np.eye(len(DISTORTION_TERMS)), rho_d)
        return StackMotion(modes, dist)

    def stack(self, x: ArrayLike, y: ArrayLike, nexp: int, exptime: float, epoch: float = 0.0):
        """Mean displacement (N, 2) and blur covariance (N, 2, 2), mas, of a stack's stars.

        Parameters
        ----------
        x, y : array_like
            Field positions [arcsec].
        nexp : int
            Number of sub-exposures.
        exptime : float
            Sub-exposure time [s].
        epoch : float
            Epoch [yr].

        Returns
        -------
        mean : ndarray, shape (N, 2)
            Mean displacement [mas].
        cov : ndarray, shape (N, 2, 2)
            Covariance over the sub-exposures [mas^2].
        """
        return self.draw(nexp, exptime, epoch).stack_moments(x, y)


def build_image_motion(
    settings: ImageMotionSettings, tiptilt: TipTiltField, layers_: Layers, diameter: float
) -> ImageMotion:
    """The :class:`ImageMotion` of a scene, with the budget from its TT field.

    Parameters
    ----------
    settings : ImageMotionSettings
        The ``[scene.optics.image_motion]`` table.
    tiptilt : TipTiltField
        The tip-tilt residual model (sets the mode budget).
    layers_ : Layers
        Turbulent layers (for the tilt correlation time D / v_eff).
    diameter : float
        Telescope diameter (m).
    """
    tau = settings.tilt_correlation_time
    if tau is None:
        tau = diameter / max(effective_wind_speed(layers_.weights, layers_.velocities), 1e-6)
    needs_budget = settings.enabled and (settings.tilt is None or settings.plate_scale is None)
    cov = budget_mode_covariance(tiptilt) if needs_budget else np.zeros((6, 6))
    return ImageMotion(settings, cov, tau)
