"""Proper motions from aligned multi-epoch positions by weighted least squares.

For each star and axis, the aligned positions ``X_k`` at epochs ``t_k`` with
variances ``var_k`` are fitted by ``X(t) = X_0 + mu (t - t_ref)``. With weights
``w_k = 1 / var_k``, ``tbar = sum(w t) / sum(w)`` and ``S = sum(w (t - tbar)^2)``,

    mu = sum(w (t - tbar) X) / S,      var(mu) = 1 / S,

which for two epochs reduces to ``(X_1 - X_0) / (t_1 - t_0)`` with variance
``(var_0 + var_1) / (t_1 - t_0)^2``. The x-y covariance of ``mu`` follows from
the per-epoch x-y covariances (from the transformation's uncertainty).
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np
from scipy import stats

__all__ = [
    "LinearMotion",
    "MIN_RADIUS",
    "fit_linear_motion",
    "pm_to_velocity",
    "radial_tangential",
]

#: Radii below this [arcsec] have no defined radial direction.
MIN_RADIUS = 1e-9


@dataclass
class LinearMotion:
    """Per-star weighted least-squares linear motion fit (all arrays shape (n,)).

    Parameters
    ----------
    pm_x, pm_y : ndarray
        Proper motion [arcsec/yr].
    var_pm_x, var_pm_y, cov_pm_xy : ndarray
        Its covariance [arcsec^2/yr^2].
    x0, y0 : ndarray
        Fitted position at the reference epoch [arcsec].
    n_epochs : ndarray of int
        Epochs used.
    chi2 : ndarray
        Chi-square of the linear fit (both axes), 0 for two epochs.
    dof : ndarray of int
        Its degrees of freedom, ``2 (n_epochs - 2)``.
    coef_x, coef_y : ndarray, shape (n, n_epochs), optional
        ``d pm / d X_k``: the weights [1/yr] that turn a change of each epoch's aligned
        position into a change of the proper motion (0 where not valid), for
        propagating errors shared between stars.
    """

    pm_x: np.ndarray
    pm_y: np.ndarray
    var_pm_x: np.ndarray
    var_pm_y: np.ndarray
    cov_pm_xy: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    n_epochs: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    coef_x: np.ndarray | None = None
    coef_y: np.ndarray | None = None

    def poor_fit(self, p_min: float = 1e-3) -> np.ndarray:
        """Stars whose motion is inconsistent with a straight line (chi-square p < ``p_min``).

        Parameters
        ----------
        p_min : float
            Chi-square probability below which a track is not straight.

        Returns
        -------
        ndarray of bool
        """
        p = np.ones_like(self.chi2)
        has = self.dof > 0
        p[has] = stats.chi2.sf(self.chi2[has], self.dof[has])
        return p < p_min


def _axis_fit(t, pos, var, valid, t_ref):
    w = np.where(valid, 1.0 / np.where(valid, var, 1.0), 0.0)
    sw = w.sum(axis=1)
    tbar = (w * t).sum(axis=1) / sw
    dt = t - tbar[:, None]
    s = (w * dt**2).sum(axis=1)
    pos0 = np.where(valid, pos, 0.0)
    mu = (w * dt * pos0).sum(axis=1) / s
    mean = (w * pos0).sum(axis=1) / sw
    x0 = mean + mu * (t_ref - tbar)
    resid = np.where(valid, pos0 - (mean[:, None] + mu[:, None] * dt), 0.0)
    chi2 = (w * resid**2).sum(axis=1)
    coef = w * dt / s[:, None]  # d mu / d X_k
    return mu, 1.0 / s, x0, chi2, coef


def fit_linear_motion(
    t: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    var_x: np.ndarray,
    var_y: np.ndarray,
    cov_xy: np.ndarray,
    valid: np.ndarray,
    t_ref: float,
) -> LinearMotion:
    """Weighted least-squares proper motions of many stars at once.

    Parameters
    ----------
    t : ndarray, shape (n_epochs,)
        Epochs [yr].
    x, y : ndarray, shape (n, n_epochs)
        Aligned positions [arcsec] (anything where ``valid`` is False).
    var_x, var_y, cov_xy : ndarray, shape (n, n_epochs)
        Position (co)variances [arcsec^2].
    valid : ndarray of bool, shape (n, n_epochs)
        Where a star has a usable position; each star needs two valid epochs.
    t_ref : float
        Epoch [yr] of the fitted reference position.

    Returns
    -------
    LinearMotion
    """
    t = np.asarray(t, float)[None, :]
    valid = np.asarray(valid, bool)
    n_valid = np.count_nonzero(valid, axis=1)
    if np.any(n_valid < 2):
        raise ValueError("every star needs at least two valid epochs for a proper motion")
    mux, vx, x0, chix, cx = _axis_fit(t, x, var_x, valid, t_ref)
    muy, vy, y0, chiy, cy = _axis_fit(t, y, var_y, valid, t_ref)
    cov = (cx * cy * np.where(valid, cov_xy, 0.0)).sum(axis=1)
    return LinearMotion(
        pm_x=mux,
        pm_y=muy,
        var_pm_x=vx,
        var_pm_y=vy,
        cov_pm_xy=cov,
        x0=x0,
        y0=y0,
        n_epochs=n_valid,
        chi2=chix + chiy,
        dof=2 * (n_valid - 2),
        coef_x=cx,
        coef_y=cy,
    )


def radial_tangential(
    x: np.ndarray,
    y: np.ndarray,
    pm_x: np.ndarray,
    pm_y: np.ndarray,
    var_x: np.ndarray,
    var_y: np.ndarray,
    cov_xy: np.ndarray,
    center: tuple[float, float] = (0.0, 0.0),
):
    """Radial and tangential proper-motion components about a centre.

    ``pm_r = (dx pm_x + dy pm_y) / R`` (positive outwards), ``pm_t = (dx pm_y - dy pm_x) / R``
    (positive counter-clockwise, x towards y). At ``R = 0`` the direction is undefined:
    the x axis is used as radial direction and ``at_centre`` is set.

    Parameters
    ----------
    x, y : ndarray
        Positions [arcsec].
    pm_x, pm_y, var_x, var_y, cov_xy : ndarray
        Proper motion and covariance (any consistent units).
    center : tuple of float
        Centre [arcsec].

    Returns
    -------
    pm_r, pm_t, err_r, err_t, radius, at_centre : ndarray
    """
    dx = np.asarray(x, float) - center[0]
    dy = np.asarray(y, float) - center[1]
    r = np.hypot(dx, dy)
    at_centre = r < MIN_RADIUS
    safe = np.where(at_centre, 1.0, r)
    c = np.where(at_centre, 1.0, dx / safe)
    s = np.where(at_centre, 0.0, dy / safe)
    pm_r = c * pm_x + s * pm_y
    pm_t = c * pm_y - s * pm_x
    var_r = c**2 * var_x + s**2 * var_y + 2 * c * s * cov_xy
    var_t = s**2 * var_x + c**2 * var_y - 2 * c * s * cov_xy
    return pm_r, pm_t, np.sqrt(np.maximum(var_r, 0)), np.sqrt(np.maximum(var_t, 0)), r, at_centre


def pm_to_velocity(pm: u.Quantity, distance: u.Quantity) -> u.Quantity:
    """Tangential velocity [km/s] of a proper motion at a distance (``v = mu d``).

    Parameters
    ----------
    pm : Quantity
        Proper motion (angle/time).
    distance : Quantity
        Distance (length).

    Returns
    -------
    Quantity
        [km/s]
    """
    return (pm * distance).to(u.km / u.s, equivalencies=u.dimensionless_angles())
