"""Position errors shared between epochs: the registration to a common reference list.

A frame-built ePSF is registered node by node to a reference list (the first
epoch's input list); the error of that registration (the node centring's, a smooth
field over the frame) is part of every star's position error. An observer-mode
later epoch is centred on the earlier ePSF's convention and carries the *same*
realisation of that field (docs/measure.md, "Observer mode"). The measured
products store it apart, ``x_err_registration``, ``y_err_registration``, and name
the list in the root attribute ``registration_reference``.

In a difference of two epochs registered to the same list the shared part cancels.
Per star and axis the epochs' positions are ``X_k = x(t_k) + e_k + r_k xi`` with
independent ``e_k`` (variance ``sigma_k^2 - r_k^2``, ``sigma_k`` the total error)
and one shared ``xi`` (unit variance) per reference list. The motion fit weighs
each epoch by its independent variance, and the shared part enters the motion as
``(sum_k c_k J_k r_k)^2`` (``c_k = d mu / d X_k``, ``J_k`` the epoch's alignment
Jacobian): for two epochs ``((r_1 - r_0) / dt)^2``, ~0 where both interpolate the
same field. Epochs naming different lists (or none: products written before the
columns, truth-forced epochs, which each have their own list) keep their totals.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = [
    "MIN_INDEPENDENT_FRACTION",
    "independent_errors",
    "shared_mask",
    "shared_motion_covariance",
]

#: Floor of the independent error as a fraction of the total (a guard against a
#: zero variance; the products' totals hold the Fisher error beyond the registration).
MIN_INDEPENDENT_FRACTION = 1e-3


def shared_mask(references: Sequence[str | None], valid: np.ndarray) -> np.ndarray:
    """Where a star's epoch shares its registration with another of its valid epochs.

    Parameters
    ----------
    references : sequence of str or None
        Each epoch's ``registration_reference`` (None or empty: unknown, never shared).
    valid : ndarray of bool, shape (n, n_epochs)
        Where a star has a usable position.

    Returns
    -------
    ndarray of bool, shape (n, n_epochs)
    """
    valid = np.asarray(valid, bool)
    out = np.zeros_like(valid)
    names = [r if r else None for r in references]
    for name in {r for r in names if r is not None}:
        cols = np.array([r == name for r in names])
        if cols.sum() < 2:
            continue
        members = valid & cols[None, :]
        out |= members & (np.count_nonzero(members, axis=1) >= 2)[:, None]
    return out


def independent_errors(total: np.ndarray, shared: np.ndarray, is_shared: np.ndarray) -> np.ndarray:
    """Total errors less the shared part in quadrature where it is shared.

    Parameters
    ----------
    total : ndarray
        Total position errors (any unit).
    shared : ndarray
        Their shared (registration) part, same unit (NaN counts as 0).
    is_shared : ndarray of bool
        Where the part is shared (:func:`shared_mask`).

    Returns
    -------
    ndarray
        ``sqrt(total^2 - shared^2)`` where shared (at least
        :data:`MIN_INDEPENDENT_FRACTION` of the total), else ``total``.
    """
    shared = np.nan_to_num(np.asarray(shared, float))
    with np.errstate(invalid="ignore"):
        reduced = np.sqrt(np.maximum(total**2 - shared**2, (MIN_INDEPENDENT_FRACTION * total) ** 2))
    return np.where(is_shared, reduced, total)


def shared_motion_covariance(
    references: Sequence[str | None],
    is_shared: np.ndarray,
    coef_x: np.ndarray,
    coef_y: np.ndarray,
    jac: np.ndarray,
    rx: np.ndarray,
    ry: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the shared registration leaves in the proper motions (to add to their covariance).

    Parameters
    ----------
    references : sequence of str or None
        Each epoch's ``registration_reference``.
    is_shared : ndarray of bool, shape (n, n_epochs)
        :func:`shared_mask`.
    coef_x, coef_y : ndarray, shape (n, n_epochs)
        ``d mu / d X_k`` of the motion fit
        (:attr:`~mavispm.measure.propermotions.motion_fit.LinearMotion.coef_x`).
    jac : ndarray, shape (n, n_epochs, 2, 2)
        Each epoch's alignment Jacobian at the star (identity for the reference epoch).
    rx, ry : ndarray, shape (n, n_epochs)
        The shared parts (NaN counts as 0), the unit of the positions.

    Returns
    -------
    var_x, var_y, cov_xy : ndarray, shape (n,)
        [position unit^2 / time^2]; zeros where no epoch is shared.
    """
    rx = np.where(is_shared, np.nan_to_num(rx), 0.0)
    ry = np.where(is_shared, np.nan_to_num(ry), 0.0)
    n = is_shared.shape[0]
    var_x, var_y, cov = np.zeros(n), np.zeros(n), np.zeros(n)
    names = [r if r else None for r in references]
    for name in {r for r in names if r is not None}:
        cols = np.array([r == name for r in names])
        # one shared x and one shared y error per list: its response in mu_x and mu_y
        ax = np.sum(cols * coef_x * jac[..., 0, 0] * rx, axis=1)  # mu_x per unit x error
        bx = np.sum(cols * coef_x * jac[..., 0, 1] * ry, axis=1)  # mu_x per unit y error
        ay = np.sum(cols * coef_y * jac[..., 1, 0] * rx, axis=1)
        by = np.sum(cols * coef_y * jac[..., 1, 1] * ry, axis=1)
        var_x += ax**2 + bx**2
        var_y += ay**2 + by**2
        cov += ax * ay + bx * by
    return var_x, var_y, cov
