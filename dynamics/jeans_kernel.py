"""Compiled Jeans model on the likelihood's grid: the hot path of every likelihood call.

:func:`log_dispersions` does in one numba pass what
:meth:`mavispm.dynamics.jeans.JeansProjector.moments` (numpy, the reference) and the
likelihood's weighting of its components do together. On the projector's uniform
``ln r`` grid it forms the integrating factor ``g(r)`` of the anisotropy
``beta(r) = beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2)`` and the radial Jeans
integral of the whole mass model,

    nu sigma_r^2 (r) = g(r)^-1 [ int_r^x_max g nu (w_cl m + w_bh + w_dark m_P(r'/b)) / r'^2 dr'
                                 + tail ],

(4th-order outside-in sums in ``ln r``; ``w`` the masses times ``G / a``), and
projects ``(1 - beta) nu sigma_r^2``, ``beta nu sigma_r^2`` and ``nu`` with the
projector's fixed operators. Because the projection is linear and every term is
positive, weighting the components before projecting (one column instead of three)
changes the result only by rounding (relative ~1e-15). The operator rows are
visited only between their first and last non-zero column (:func:`row_ranges`), and
their dot products may be vectorised (reassociated sums, again rounding only).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "jeans_columns",
    "log_dispersions",
    "row_ranges",
]

_TINY = np.finfo(float).tiny


def row_ranges(*operators):
    """First and one-past-last column with a non-zero entry, per row, over ``operators``.

    Parameters
    ----------
    *operators : ndarray (M, n)
        Dense operators of one shape.

    Returns
    -------
    lo, hi : ndarray of int64 (M,)
        Column range of each row (``lo == hi`` for an all-zero row).
    """
    nz = np.zeros(operators[0].shape, dtype=bool)
    for op in operators:
        nz |= op != 0.0
    cols = np.arange(nz.shape[1])[None, :]
    any_nz = nz.any(axis=1)
    lo = np.where(any_nz, np.where(nz, cols, nz.shape[1]).min(axis=1), 0)
    hi = np.where(any_nz, np.where(nz, cols, -1).max(axis=1) + 1, 0)
    return lo.astype(np.int64), hi.astype(np.int64)


@numba.njit(nogil=True, cache=True)
def _floor(v):  # pragma: no cover - compiled
    """``max(v, tiny)`` that keeps NaN (as ``np.maximum``)."""
    return _TINY if v < _TINY else v


@numba.njit(nogil=True, cache=True)
def _plummer_mass(x):  # pragma: no cover - compiled
    """Plummer mass fraction ``x^3 (1 + x^2)^(-3/2)``, as ``t^(3/2)`` with ``t = x^2 / (1 + x^2)``
    (a square root instead of a power: the same value to rounding)."""
    t = x * x / (1.0 + x * x)
    return t * np.sqrt(t)


@numba.njit(nogil=True, cache=True)
def _outside_in(f, h, out):  # pragma: no cover - compiled
    """``int_{r_j}^{x_max} f d ln r`` on the uniform grid (the 4th-order scheme of
    :meth:`mavispm.dynamics.jeans.JeansProjector._outside_in`), written into ``out``."""
    n = f.size
    h24 = h / 24.0
    out[n - 1] = 0.0
    acc = h24 * (9.0 * f[n - 1] + 19.0 * f[n - 2] - 5.0 * f[n - 3] + f[n - 4])
    out[n - 2] = acc
    for k in range(n - 3, 0, -1):
        acc += h24 * (13.0 * (f[k] + f[k + 1]) - f[k - 1] - f[k + 2])
        out[k] = acc
    acc += h24 * (9.0 * f[0] + 19.0 * f[1] - 5.0 * f[2] + f[3])
    out[0] = acc


@numba.njit(nogil=True, cache=True)
def jeans_columns(
    r, ln_r, step, x_max, nu, m, m_end, tail_nu, beta_0, beta_inf, r_a, dark_radius, weights
):  # pragma: no cover - compiled
    """``(1 - beta) nu sigma_r^2`` and ``beta nu sigma_r^2`` of the whole mass model on the
    radial grid (the arguments as :func:`log_dispersions`).

    Returns
    -------
    col_t, col_r : ndarray (n_r,)
        The tangential-type and radial-excess columns; ``nu sigma_r^2 = col_t + col_r``,
        ``nu sigma_t^2 = col_t``.
    """
    n = r.size
    const = beta_0 == beta_inf
    ln_ra2 = 2.0 * np.log(r_a)
    ra2 = r_a * r_a
    ln_fac = np.empty(n)
    beta = np.empty(n)
    for j in range(n):
        if const:
            ln_fac[j] = 2.0 * beta_0 * ln_r[j]
            beta[j] = beta_0
        else:
            ln_fac[j] = 2.0 * beta_0 * ln_r[j] + (beta_inf - beta_0) * np.logaddexp(
                2.0 * ln_r[j], ln_ra2
            )
            r2 = r[j] * r[j]
            beta[j] = beta_0 + (beta_inf - beta_0) * r2 / (r2 + ra2)
    lf_end = ln_fac[n - 1]
    tail = tail_nu / np.exp(lf_end)
    w_cl, w_bh, w_dk = weights[0], weights[1], weights[2]
    dark = dark_radius > 0.0
    end = w_cl * m_end + w_bh
    if dark:
        end += w_dk * _plummer_mass(x_max / dark_radius)
    fac = np.empty(n)
    f = np.empty(n)
    for j in range(n):
        fac[j] = np.exp(ln_fac[j] - lf_end)
        mass = w_cl * m[j] + w_bh
        if dark:
            mass += w_dk * _plummer_mass(r[j] / dark_radius)
        f[j] = fac[j] * nu[j] / r[j] * mass
    acc = np.empty(n)
    _outside_in(f, step, acc)
    col_t = np.empty(n)
    col_r = np.empty(n)
    for j in range(n):
        p = (acc[j] + tail * end) / fac[j]
        col_t[j] = (1.0 - beta[j]) * p
        col_r[j] = beta[j] * p
    return col_t, col_r


@numba.njit(nogil=True, cache=True)
def log_dispersions(
    r,
    ln_r,
    step,
    x_max,
    nu,
    m,
    m_end,
    m_out,
    tail_nu,
    beta_0,
    beta_inf,
    r_a,
    dark_radius,
    weights,
    k0,
    k2,
    kc,
    lo,
    hi,
):  # pragma: no cover - compiled
    """ln model dispersions, ln surface density and ln projected mass on the output radii.

    Parameters
    ----------
    r, ln_r : ndarray (n_r,)
        The projector's radial grid (uniform in ``ln r``, last point ``x_max``).
    step : float
        Its step in ``ln r``.
    x_max : float
        Outer truncation [scale radii].
    nu, m : ndarray (n_r,)
        Tracer density and enclosed cluster mass fraction on the grid.
    m_end : float
        Enclosed cluster mass fraction at ``x_max``.
    m_out : ndarray (M,)
        Tracer mass fraction inside the sphere of each output radius.
    tail_nu : float
        :meth:`mavispm.dynamics.anisotropy.Anisotropy.tail` times the density at
        ``x_max`` (the analytic Jeans integral beyond ``x_max`` per unit enclosed mass,
        times ``g(x_max)``; 0 for a truncated profile).
    beta_0, beta_inf, r_a : float
        Anisotropy profile (constant when ``beta_0 == beta_inf``).
    dark_radius : float
        Scale radius of the dark Plummer sphere (<= 0: none).
    weights : ndarray (3,)
        ``sigma^2`` per unit moment of the cluster, point mass and dark sphere
        (their masses times ``G / a`` in the output unit).
    k0, k2, kc : ndarray (M, n_r)
        Projection operators: ``Sigma``-type, ``R^2 / r^2``-weighted and cylinder mass.
    lo, hi : ndarray of int (M,)
        Non-zero column range of each operator row (:func:`row_ranges`).

    Returns
    -------
    ln_s2 : ndarray (2, M)
        ln of the radial and tangential dispersion squared (floored at the smallest
        normal double).
    ln_sigma, ln_proj : ndarray (M,)
        ln surface density and ln projected mass fraction (floored likewise).
    """
    col_t, col_r = jeans_columns(
        r, ln_r, step, x_max, nu, m, m_end, tail_nu, beta_0, beta_inf, r_a, dark_radius, weights
    )
    n_out = k0.shape[0]
    ln_s2 = np.empty((2, n_out))
    ln_sigma = np.empty(n_out)
    ln_proj = np.empty(n_out)
    for i in range(n_out):
        s_nu, s_t, s_r, s_c = _project_row(k0[i], k2[i], kc[i], lo[i], hi[i], nu, col_t, col_r)
        sigma = _floor(s_nu)
        ln_s2[0, i] = np.log(_floor((s_t + s_r) * (1.0 / sigma)))
        ln_s2[1, i] = np.log(_floor(s_t * (1.0 / sigma)))
        ln_sigma[i] = np.log(sigma)
        ln_proj[i] = np.log(_floor(m_out[i] + s_c))
    return ln_s2, ln_sigma, ln_proj


@numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def _project_row(k0, k2, kc, lo, hi, nu, col_t, col_r):  # pragma: no cover - compiled
    """One row of the projections: ``k0 . nu``, ``k0 . col_t``, ``k2 . col_r``, ``kc . nu``
    over the row's non-zero columns ``lo:hi``. The sums may be reordered (vectorised);
    slices make the indices provably non-negative, so no wraparound checks remain."""
    a_, b_, c_ = k0[lo:hi], k2[lo:hi], kc[lo:hi]
    nu_, t_, r_ = nu[lo:hi], col_t[lo:hi], col_r[lo:hi]
    s_nu = 0.0
    s_t = 0.0
    s_r = 0.0
    s_c = 0.0
    for j in range(a_.size):
        a = a_[j]
        s_nu += a * nu_[j]
        s_t += a * t_[j]
        s_r += b_[j] * r_[j]
        s_c += c_[j] * nu_[j]
    return s_nu, s_t, s_r, s_c
