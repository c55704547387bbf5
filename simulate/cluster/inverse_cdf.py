"""Tabulated inverse cumulative distributions for fast vectorised sampling.

A :class:`QuantileTable` holds, for each value of a conditioning variable
``c`` (rows), the quantile function ``y(u)`` of a 1-D density ``p(y | c)`` at
fixed probability levels ``u``. Sampling interpolates bilinearly in
``(c, u)``; given the same uniforms two models map to "corresponding" draws
(common random numbers), which keeps IMBH and no-IMBH catalogues coupled.

The probability levels are ``u_k = (1 - cos(pi w_k)) / 2`` with ``w`` uniform,
dense near 0 and 1 where quantile functions are steep; the level index of a
uniform number is found analytically (no search).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import cumulative_trapezoid

__all__ = [
    "QuantileTable",
    "probability_levels",
    "quantiles_from_pdf",
]


def probability_levels(n: int) -> np.ndarray:
    """The ``n`` probability levels ``(1 - cos(pi w)) / 2``, ``w = 0..1``.

    Spaced densest near 0 and 1.

    Parameters
    ----------
    n : int
        Number of levels.

    Returns
    -------
    ndarray
        Levels from 0 to 1, ascending.
    """
    w = np.linspace(0.0, 1.0, n)
    return 0.5 * (1.0 - np.cos(np.pi * w))


def quantiles_from_pdf(y: np.ndarray, pdf: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Quantile function of a tabulated density at the given probability levels.

    Parameters
    ----------
    y : ndarray, shape (n_y,) or (n_rows, n_y)
        Ascending abscissae (per row if 2-D).
    pdf : ndarray, shape (n_rows, n_y)
        Non-negative density values (unnormalised).
    levels : ndarray, shape (n_u,)
        Probability levels in [0, 1].

    Returns
    -------
    ndarray, shape (n_rows, n_u)
    """
    pdf = np.atleast_2d(np.maximum(np.nan_to_num(pdf, nan=0.0, posinf=0.0), 0.0))
    y2 = np.broadcast_to(np.atleast_2d(y), pdf.shape)
    cdf = cumulative_trapezoid(pdf, y2, axis=1, initial=0.0)
    total = cdf[:, -1:]
    empty = total[:, 0] <= 0
    cdf = np.where(total > 0, cdf / np.where(total > 0, total, 1.0), np.linspace(0, 1, y2.shape[1]))
    # strictly increasing for interpolation (flat stretches carry no probability)
    cdf = cdf + np.linspace(0.0, 1e-12, cdf.shape[1])
    cdf /= cdf[:, -1:]
    out = np.empty((pdf.shape[0], levels.size))
    for i in range(pdf.shape[0]):
        out[i] = np.interp(levels, cdf[i], y2[i])
    out[empty] = np.nan
    return out


@dataclass(frozen=True)
class QuantileTable:
    """Quantiles ``y(c, u)`` of a conditional density on a grid of ``c``.

    Parameters
    ----------
    cond : ndarray, shape (n_rows,)
        Ascending conditioning values (often a logarithm).
    values : ndarray, shape (n_rows, n_u)
        Quantiles at :func:`probability_levels` ``(n_u)``.
    """

    cond: np.ndarray
    values: np.ndarray

    def __call__(self, cond: np.ndarray, uniform: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of the quantiles at ``(cond, uniform)``.

        ``cond`` outside the table is clamped to its ends.
        """
        n_rows, n_u = self.values.shape
        c = np.asarray(cond, float)
        if n_rows == 1:
            i0 = np.zeros(c.shape, dtype=np.intp)
            fc = np.zeros(c.shape)
        else:
            pos = np.interp(c, self.cond, np.arange(n_rows, dtype=float))
            i0 = np.minimum(pos.astype(np.intp), n_rows - 2)
            fc = pos - i0
        w = np.arccos(np.clip(1.0 - 2.0 * np.asarray(uniform, float), -1.0, 1.0)) / np.pi
        posu = w * (n_u - 1)
        k0 = np.minimum(posu.astype(np.intp), n_u - 2)
        fu = posu - k0
        v = self.values
        i1 = np.minimum(i0 + 1, n_rows - 1)
        lo = v[i0, k0] * (1.0 - fu) + v[i0, k0 + 1] * fu
        hi = v[i1, k0] * (1.0 - fu) + v[i1, k0 + 1] * fu
        return lo * (1.0 - fc) + hi * fc
