"""Per-star sums of the discrete likelihood: interpolate the model to the stars and add up.

For stars at ``u_i = ln(R_i / a)`` the model quantities tabulated on a uniform
grid in ``ln X`` (``ln sigma_R^2``, ``ln sigma_T^2`` [(mas/yr)^2] and the ln
surface density) are interpolated with 4-point (cubic) Lagrange weights, and

    chi = sum_i sum_c [ v_c,i^2 / (sigma_c(R_i)^2 + e_c,i^2) + ln(sigma_c(R_i)^2 + e_c,i^2) ]
    lsig = sum_i ln Sigma(R_i)

are returned. :func:`star_sums` is a fused numba loop (one pass over the stars,
no temporaries; the hot path of every likelihood call); :func:`star_sums_numpy`
is the vectorised reference it is tested against. :func:`star_sums_about` moves
the stars to a fitted centre and systemic motion first (:func:`stars_about`).

The ``ln(sigma^2 + e^2)`` terms are summed as the logarithm of running products
(one ``log`` per ~20 stars instead of one per star): a product is logged and
restarted when it leaves [1e-150, 1e150], and a factor outside [1e-100, 1e100]
is logged on its own, so nothing overflows or underflows; the result differs from
the sum of logarithms by rounding only (relative ~1e-15).
"""

from __future__ import annotations

import numba
import numpy as np

from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.vector_exp import log_positive

_SIXTH = 1.0 / 6.0

__all__ = [
    "cubic_point_weights",
    "fold_log",
    "star_sums",
    "star_sums_about",
    "star_sums_numpy",
    "stars_about",
    "sum4",
]


def star_sums_numpy(u, x0, step, ln_s2, ln_sig, v2, e2):
    """Reference implementation of :func:`star_sums` (numpy).

    Parameters
    ----------
    u : ndarray (N,)
        ``ln(R / a)`` of the stars.
    x0, step : float
        Start and step of the uniform ``ln X`` grid.
    ln_s2 : ndarray (2, n)
        ln model dispersion squared (radial, tangential) on the grid.
    ln_sig : ndarray (n,)
        ln surface density on the grid.
    v2, e2 : ndarray (2, N)
        Squared proper-motion components and squared errors.

    Returns
    -------
    chi, lsig : float
    """
    idx, w = cubic_weights(x0, step, ln_sig.size, u)
    var = np.exp(interpolate(ln_s2, idx, w)) + e2
    return float(np.sum(v2 / var + np.log(var))), float(np.sum(interpolate(ln_sig, idx, w)))


@numba.njit(nogil=True, cache=True, inline="always")
def fold_log(q, prod, ln_acc):  # pragma: no cover - compiled
    """Fold ``ln q`` into the running product ``prod`` and the logged part ``ln_acc``.

    A factor outside [1e-100, 1e100] is logged on its own; the product is logged and
    restarted when it leaves [1e-150, 1e150] (also NaN: logged, and it propagates).
    ``ln_acc + ln(prod)`` is the sum of the logarithms folded so far (module notes).

    Returns
    -------
    prod, ln_acc : float
    """
    if q > 1e100 or q < 1e-100:
        return prod, ln_acc + np.log(q)
    prod *= q
    if not (1e-150 < prod < 1e150):
        return 1.0, ln_acc + np.log(prod)
    return prod, ln_acc


@numba.njit(nogil=True, cache=True, inline="always")
def cubic_point_weights(q, x0, step, n):  # pragma: no cover - compiled
    """Index ``j`` and 4-point Lagrange weights of grid points ``j-1 .. j+2`` at ``q``.

    The compiled one-point form of :func:`mavispm.dynamics.interpolation.cubic_weights`
    (same clamping at the ends of the uniform grid ``x0 + step * arange(n)``).
    """
    pos = min(max((q - x0) / step, 0.0), n - 1.0)
    j = min(max(int(np.floor(pos)), 1), n - 3)
    s = pos - j
    sm1, sm2, sp1 = s - 1.0, s - 2.0, s + 1.0
    # products with the constants (not divisions): the same weights to rounding, cheaper
    return (
        j,
        -s * sm1 * sm2 * _SIXTH,
        sp1 * sm1 * sm2 * 0.5,
        -sp1 * s * sm2 * 0.5,
        sp1 * s * sm1 * _SIXTH,
    )


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def sum4(x, n):  # pragma: no cover - compiled
    """Sum of ``x[:n]`` in four interleaved partial sums (four independent addition chains
    instead of one: the same sum to rounding, a quarter of the latency)."""
    t0 = t1 = t2 = t3 = 0.0
    k = 0
    while k + 4 <= n:
        t0 += x[k]
        t1 += x[k + 1]
        t2 += x[k + 2]
        t3 += x[k + 3]
        k += 4
    while k < n:
        t0 += x[k]
        k += 1
    return (t0 + t1) + (t2 + t3)


@numba.njit(nogil=True, cache=True)
def star_sums(u, x0, step, ln_s2, ln_sig, v2, e2):  # pragma: no cover - compiled
    """Fused :func:`star_sums_numpy` (same arguments, same clamping at the grid ends).

    Parameters
    ----------
    u : ndarray (N,)
        ``ln(R / a)`` of the stars.
    x0, step : float
        Start and step of the uniform ``ln X`` grid.
    ln_s2 : ndarray (2, n)
        ln model dispersion squared (radial, tangential) on the grid.
    ln_sig : ndarray (n,)
        ln surface density on the grid.
    v2, e2 : ndarray (2, N)
        Squared proper-motion components and squared errors.

    Returns
    -------
    chi, lsig : float
        ``sum(v2 / var + ln var)`` over stars and components (``var`` = model dispersion
        squared plus error squared), and the sum of the interpolated ln surface density.
    """
    n = ln_sig.size
    if n < 4 or ln_s2.shape[1] != n:
        raise ValueError("star_sums needs ln_s2 (2, n) and ln_sig (n,) with n >= 4")
    chi = 0.0
    lsig = 0.0
    prod = 1.0
    ln_acc = 0.0
    for i in range(u.size):
        j, w0, w1, w2, w3 = cubic_point_weights(u[i], x0, step, n)
        # unsigned indices (j >= 1): no negative-index wraparound checks in the loads
        k0 = np.uint64(j - 1)
        k1, k2, k3 = k0 + np.uint64(1), k0 + np.uint64(2), k0 + np.uint64(3)
        for c in range(2):
            row = ln_s2[c]
            ln_v = w0 * row[k0] + w1 * row[k1] + w2 * row[k2] + w3 * row[k3]
            var = np.exp(ln_v) + e2[c, i]
            chi += v2[c, i] / var
            prod, ln_acc = fold_log(var, prod, ln_acc)  # ln var (module notes)
        lsig += w0 * ln_sig[k0] + w1 * ln_sig[k1] + w2 * ln_sig[k2] + w3 * ln_sig[k3]
    return chi + ln_acc + np.log(prod), lsig


@numba.njit(nogil=True, cache=True, error_model="numpy")
def star_sums_about(
    x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r, ln_a, grid_x0, step, ln_s2, ln_sig
):  # pragma: no cover - compiled
    """:func:`stars_about` then :func:`star_sums`, in one compiled call.

    Parameters
    ----------
    x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r
        As :func:`stars_about`.
    ln_a : float
        ln scale radius [ln arcsec]: ``u = ln R - ln a``.
    grid_x0, step, ln_s2, ln_sig
        As ``x0, step, ln_s2, ln_sig`` of :func:`star_sums`.

    Returns
    -------
    chi, lsig : float
        As :func:`star_sums`.
    """
    n = x.size
    u = np.empty(n)
    v2 = np.empty((2, n))
    e2 = np.empty((2, n))
    for i in range(n):
        ln_r, v2[0, i], v2[1, i], e2[0, i], e2[1, i] = _star_about(
            x[i], y[i], pm_x[i], pm_y[i], cx[i], sy[i], er2[i], et2[i], x0, y0, mx0, my0, min_r
        )
        u[i] = ln_r - ln_a
    return star_sums(u, grid_x0, step, ln_s2, ln_sig, v2, e2)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _star_about(x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r):  # pragma: no cover
    """One star of :func:`stars_about`: ln R, squared R/T motions, rotated squared errors
    (ln R with the vectorising :func:`~mavispm.dynamics.vector_exp.log_positive`, so the
    callers' loops over the stars run on the vector units)."""
    dx = x - x0
    dy = y - y0
    r = max(np.sqrt(dx * dx + dy * dy), 1e-12)
    c = dx / r
    s = dy / r
    px = pm_x - mx0
    py = pm_y - my0
    vr = px * c + py * s
    vt = -px * s + py * c
    cd = cx * c + sy * s
    c2 = cd * cd
    s2 = 1.0 - c2
    return (
        log_positive(max(r, min_r)),
        vr * vr,
        vt * vt,
        er2 * c2 + et2 * s2,
        er2 * s2 + et2 * c2,
    )


@numba.njit(nogil=True, cache=True, error_model="numpy")
def stars_about(x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r):  # pragma: no cover
    """ln R, squared R/T motions and rotated squared errors about centre ``(x0, y0)``.

    Motions are taken relative to ``(mx0, my0)``; the errors ``er2, et2`` (about the
    field centre, directions ``cx, sy``) are rotated by the angle ``d`` between the
    old and new radial directions: ``e_R'^2 = e_R^2 cos^2 d + e_T^2 sin^2 d``.
    Reference: :meth:`mavispm.dynamics.likelihood.DiscreteLikelihood._stars_about_numpy`.

    Parameters
    ----------
    x, y : ndarray (N,)
        Positions about the field centre [arcsec].
    pm_x, pm_y : ndarray (N,)
        Proper motions [mas/yr].
    cx, sy : ndarray (N,)
        Cosine and sine of each star's radial direction about the field centre.
    er2, et2 : ndarray (N,)
        Squared radial and tangential errors about the field centre [(mas/yr)^2].
    x0, y0 : float
        New centre [arcsec].
    mx0, my0 : float
        Mean motion subtracted [mas/yr].
    min_r : float
        Smallest radius used [arcsec] (stars closer are put at it).

    Returns
    -------
    ln_r : ndarray (N,)
        ln of the radius about the new centre.
    v2 : ndarray (2, N)
        Squared radial and tangential motions [(mas/yr)^2].
    e2 : ndarray (2, N)
        Rotated squared errors [(mas/yr)^2].
    """
    n = x.size
    ln_r = np.empty(n)
    v2 = np.empty((2, n))
    e2 = np.empty((2, n))
    for i in range(n):
        ln_r[i], v2[0, i], v2[1, i], e2[0, i], e2[1, i] = _star_about(
            x[i], y[i], pm_x[i], pm_y[i], cx[i], sy[i], er2[i], et2[i], x0, y0, mx0, my0, min_r
        )
    return ln_r, v2, e2
