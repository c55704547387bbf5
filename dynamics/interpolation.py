"""Cubic (4-point Lagrange) interpolation on a uniform grid, shared by the profiles,
the Jeans projector and the likelihood."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "cubic_weights",
    "interpolate",
]


def cubic_weights(lnx_grid_start: float, step: float, n: int, lnq: ArrayLike):
    """Indices and 4-point Lagrange weights for cubic interpolation on a uniform grid.

    Queries outside the grid are clamped to its ends.

    Parameters
    ----------
    lnx_grid_start, step, n : float, float, int
        The uniform grid ``lnx_grid_start + step * arange(n)`` (n >= 4).
    lnq : ndarray
        Query points.

    Returns
    -------
    idx : ndarray of int, shape (4, N)
    weights : ndarray, shape (4, N)
    """
    pos = np.clip((np.asarray(lnq, dtype=float) - lnx_grid_start) / step, 0.0, n - 1.0)
    i = np.clip(np.floor(pos).astype(int), 1, n - 3)
    s = pos - i
    sm1, sm2, sp1 = s - 1.0, s - 2.0, s + 1.0
    weights = np.stack(
        [-s * sm1 * sm2 / 6.0, sp1 * sm1 * sm2 / 2.0, -sp1 * s * sm2 / 2.0, sp1 * s * sm1 / 6.0]
    )
    idx = np.stack([i - 1, i, i + 1, i + 2])
    return idx, weights


def interpolate(values: np.ndarray, idx: np.ndarray, weights: np.ndarray):
    """Apply :func:`cubic_weights` to grid ``values`` (..., n) -> (..., N).

    Parameters
    ----------
    values : ndarray, shape (..., n)
        Values on the grid.
    idx : ndarray of int, shape (4, N)
        Grid indices from :func:`cubic_weights`.
    weights : ndarray, shape (4, N)
        Their weights.

    Returns
    -------
    ndarray, shape (..., N)
        Interpolated values.
    """
    return np.sum(values[..., idx] * weights, axis=-2)
