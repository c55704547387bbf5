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

The points are taken in runs of one regime (the panels' nodes and the density points
are in order of radius: three runs), each run one branch-free loop with the vectorising
:func:`~mavispm.dynamics.vector_exp.log_positive` and
:func:`~mavispm.dynamics.vector_exp.exp_bounded` (numba calls the C library's scalar
functions otherwise), so LLVM runs it on the vector units; the interpolated ln masses are
collected first and exponentiated in one vector pass.
The multiplier differs from the reference by rounding only (relative <~1e-14, the
largest from ``ln q`` of order 50 times the double precision).
"""

from __future__ import annotations

import numba
import numpy as np

from mavispm.dynamics.vector_exp import exp_bounded, log_positive

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
    factor = np.empty((n_p, n_k))
    _multipliers(
        c2, ln_c2, inv_x2_nodes.ravel(), ln_inv_x2_nodes.ravel(), half_g, coef, factor.ravel()
    )
    cum = np.empty(n_p + 1)
    cum[0] = m_in
    run = 0.0
    for p in range(n_p):
        s = 0.0
        for k in range(n_k):
            s += f_base[p, k] * factor[p, k]
        run += s
        cum[p + 1] = run + m_in
    total = cum[n_p] + m_out
    ln_cum = np.empty(n_p + 1)
    _logs(cum, ln_cum)
    n_m = indptr.size - 1
    m = np.empty(n_m)
    for i in range(n_m):  # the exponent of each mass point (CSR rows: not vectorised)
        acc = 0.0
        for q in range(indptr[i], indptr[i + 1]):
            acc += data[q] * ln_cum[indices[q]]
        m[i] = (3.0 - gamma) * dln_below[i] if below[i] else acc
    _masses(m, below, above, outer, cum[0], cum[n_p], total)
    nu = np.empty(base_nu.size)
    _multipliers(c2, ln_c2, inv_x2_points, ln_inv_x2_points, half_g, coef, nu)
    _scaled(nu, base_nu, total)
    return nu, m


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _multipliers(c2, ln_c2, inv_x2, ln_inv_x2, h, coef, out):  # pragma: no cover - compiled
    """``out[i] = (1 + q_i)^h`` with ``q_i = c2 inv_x2[i]`` and ``ln q_i = ln_c2 +
    ln_inv_x2[i]`` (the three regimes of the module notes).

    The points are taken in runs of one regime (three runs for monotonic radii, as the
    panels' nodes and the density points are; any order works), and each run is one
    branch-free loop that vectorises (the series alone outside the cusp, ``exp`` and
    ``log`` only where needed)."""
    n = out.size
    i = 0
    while i < n:
        regime = _regime(c2 * inv_x2[i])
        j = i + 1
        while j < n and _regime(c2 * inv_x2[j]) == regime:
            j += 1
        _run(regime, c2, ln_c2, inv_x2[i:j], ln_inv_x2[i:j], h, coef, out[i:j])
        i = j


@numba.njit(nogil=True, cache=True, error_model="numpy", fastmath={"contract"})
def _run(regime, c2, ln_c2, inv_x2, ln_inv_x2, h, coef, out):  # pragma: no cover - compiled
    """One run of :func:`_multipliers`, all in ``regime`` (:func:`_regime`)."""
    if regime == 0:
        for k in range(out.size):
            out[k] = _binomial(c2 * inv_x2[k], coef)
    elif regime == 2:
        for k in range(out.size):
            q = c2 * inv_x2[k]
            out[k] = exp_bounded(h * (ln_c2 + ln_inv_x2[k])) * _binomial(1.0 / q, coef)
    else:
        for k in range(out.size):
            out[k] = exp_bounded(h * log_positive(1.0 + c2 * inv_x2[k]))


@numba.njit(nogil=True, cache=True, inline="always")
def _regime(q):  # pragma: no cover - compiled
    """0: ``q <= 0.01`` (series), 2: ``q >= 100`` (power times series), 1: between (and
    NaN)."""
    return 0 if q <= 0.01 else (2 if q >= 100.0 else 1)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _logs(x, out):  # pragma: no cover - compiled
    """``out = ln x`` (vectorised)."""
    for i in range(x.size):
        out[i] = log_positive(x[i])


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _masses(m, below, above, outer, cum_in, cum_out, total):  # pragma: no cover - compiled
    """Enclosed mass fractions from the exponents ``m`` (in place): ``cum_in exp(m)``
    inside the first edge, ``cum_out + outer`` beyond the last, ``exp(m)`` between,
    divided by ``total`` and capped at 1."""
    for i in range(m.size):
        e = exp_bounded(m[i])
        v = cum_in * e if below[i] else e
        v = cum_out + outer[i] if above[i] else v
        v = v / total
        m[i] = 1.0 if v > 1.0 else v


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _scaled(nu, base_nu, total):  # pragma: no cover - compiled
    """``nu = base_nu nu / total`` (in place)."""
    for i in range(nu.size):
        nu[i] = base_nu[i] * nu[i] / total


@numba.njit(nogil=True, cache=True)
def _binomial_coefficients(h):  # pragma: no cover - compiled
    """``C(h, k)`` for ``k = 0 .. 8``."""
    coef = np.empty(9)
    coef[0] = 1.0
    for k in range(1, 9):
        coef[k] = coef[k - 1] * (h - (k - 1)) / k
    return coef


@numba.njit(nogil=True, cache=True, inline="always")
def _binomial(z, coef):  # pragma: no cover - compiled
    """``sum_k coef[k] z^k`` (Horner, written out: loops that call it vectorise)."""
    acc = coef[8]
    acc = acc * z + coef[7]
    acc = acc * z + coef[6]
    acc = acc * z + coef[5]
    acc = acc * z + coef[4]
    acc = acc * z + coef[3]
    acc = acc * z + coef[2]
    acc = acc * z + coef[1]
    return acc * z + coef[0]
