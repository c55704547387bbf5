"""Compiled density and enclosed mass of a cusped profile at fixed points.

:func:`cusped_at_points` is one numba pass of
:meth:`mavispm.dynamics.tracers.CuspedAtPoints.call_numpy` (its reference): the
cumulative Gauss-Legendre mass of ``nu_base(x) (1 + (x_c / x)^2)^(gamma / 2)`` on the
fixed ``ln x`` panels (with the analytic power law inside the first edge), its cubic
interpolation in ``ln m`` to the mass points (a sparse matrix in CSR form), and the
density at the density points, both normalised to unit mass.

The cusp multiplier ``(1 + q)^h``, ``q = x_c^2 / x^2``, ``h = gamma / 2``, is
evaluated without ``log1p`` (the reference's form, ``exp(h log1p(q))``), and mostly
without any transcendental function, by where ``q`` lies:

* ``q <= 0.01`` (outside the cusp): the binomial series ``sum_k C(h, k) q^k`` to
  ``k = 8`` (truncation ``<= q^9 <= 1e-18``);
* ``q >= 100`` (deep in the cusp): ``exp(h ln q) (1 + 1/q)^h``, ``ln q = ln x_c^2 +
  ln(1/x^2)`` from the cached ``ln(1 / x^2)``, and the same series in ``1 / q``;
* otherwise ``exp(h ln(1 + q))``.

The multiplier differs from the reference by rounding only (relative <~1e-14, the
largest from ``ln q`` of order 50 times the double precision).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "cusped_at_points",
]

_FOUR_PI = 4.0 * np.pi


@numba.njit(nogil=True, cache=True)
def cusped_at_points(
    gamma,
    cusp_radius,
    ln_x_in,
    nu0,
    m_out,
    f_base,
    inv_x2_nodes,
    ln_inv_x2_nodes,
    indptr,
    indices,
    data,
    below,
    dln_below,
    above,
    outer,
    base_nu,
    inv_x2_points,
    ln_inv_x2_points,
):  # pragma: no cover - compiled
    """Density and enclosed mass fraction of a cusped profile.

    Parameters
    ----------
    gamma, cusp_radius : float
        Cusp slope and radius [scale radii].
    ln_x_in : float
        ln of the first panel edge.
    nu0 : float
        Central density of the base profile.
    m_out : float
        Base mass beyond the last edge (0 for a truncated profile).
    f_base, inv_x2_nodes, ln_inv_x2_nodes : ndarray (P, K)
        ``4 pi x^3 nu_base`` times the Gauss-Legendre weight, ``1 / x^2`` and its
        logarithm at the nodes of each panel.
    indptr, indices, data : ndarray
        CSR matrix (mass points x panel edges) of the cubic interpolation in ``ln x``.
    below, above : ndarray of bool
        Mass points inside the first / beyond the last edge.
    dln_below : ndarray
        ``ln x - ln x_in`` (<= 0) of the mass points.
    outer : ndarray
        Base mass between the last edge and each mass point beyond it.
    base_nu, inv_x2_points, ln_inv_x2_points : ndarray
        Base density, ``1 / x^2`` and its logarithm at the density points.

    Returns
    -------
    nu : ndarray
        Density at the density points (unit total mass).
    m : ndarray
        Enclosed mass fraction at the mass points (at most 1).
    """
    half_g = 0.5 * gamma
    c2 = cusp_radius * cusp_radius
    ln_c2 = np.log(c2)
    coef = _binomial_coefficients(half_g)
    x_in = np.exp(ln_x_in)
    m_in = _FOUR_PI * nu0 * cusp_radius**gamma * x_in ** (3.0 - gamma) / (3.0 - gamma)
    n_p, n_k = f_base.shape
    cum = np.empty(n_p + 1)
    cum[0] = m_in
    run = 0.0
    for p in range(n_p):
        s = 0.0
        for k in range(n_k):
            factor = _multiplier(
                c2 * inv_x2_nodes[p, k], ln_c2 + ln_inv_x2_nodes[p, k], half_g, coef
            )
            s += f_base[p, k] * factor
        run += s
        cum[p + 1] = run + m_in
    total = cum[n_p] + m_out
    ln_cum = np.log(cum)
    n_m = indptr.size - 1
    m = np.empty(n_m)
    for i in range(n_m):
        if below[i]:
            v = cum[0] * np.exp((3.0 - gamma) * dln_below[i])
        elif above[i]:
            v = cum[n_p] + outer[i]
        else:
            acc = 0.0
            for q in range(indptr[i], indptr[i + 1]):
                acc += data[q] * ln_cum[indices[q]]
            v = np.exp(acc)
        v = v / total
        m[i] = 1.0 if v > 1.0 else v
    nu = np.empty(base_nu.size)
    for i in range(base_nu.size):
        factor = _multiplier(c2 * inv_x2_points[i], ln_c2 + ln_inv_x2_points[i], half_g, coef)
        nu[i] = base_nu[i] * factor / total
    return nu, m


@numba.njit(nogil=True, cache=True)
def _binomial_coefficients(h):  # pragma: no cover - compiled
    """``C(h, k)`` for ``k = 0 .. 8``."""
    coef = np.empty(9)
    coef[0] = 1.0
    for k in range(1, 9):
        coef[k] = coef[k - 1] * (h - (k - 1)) / k
    return coef


@numba.njit(nogil=True, cache=True)
def _binomial(z, coef):  # pragma: no cover - compiled
    """``sum_k coef[k] z^k`` (Horner)."""
    acc = coef[8]
    for k in range(7, -1, -1):
        acc = acc * z + coef[k]
    return acc


@numba.njit(nogil=True, cache=True)
def _multiplier(q, ln_q, h, coef):  # pragma: no cover - compiled
    """``(1 + q)^h`` given ``q`` and ``ln q`` (see the module notes)."""
    if q <= 0.01:
        return _binomial(q, coef)
    if q >= 100.0:
        return np.exp(h * ln_q) * _binomial(1.0 / q, coef)
    return np.exp(h * np.log(1.0 + q))
