"""Per-star sums of the discrete likelihood: interpolate the model to the stars and add up.

For stars at ``u_i = ln(R_i / a)`` the model quantities tabulated on a uniform
grid in ``ln X`` (``ln sigma_R^2``, ``ln sigma_T^2`` [(mas/yr)^2] and the ln
surface density) are interpolated with 4-point (cubic) Lagrange weights, and

    chi = sum_i sum_c [ v_c,i^2 / (sigma_c(R_i)^2 + e_c,i^2) + ln(sigma_c(R_i)^2 + e_c,i^2) ]
    lsig = sum_i ln Sigma(R_i)

are returned. :func:`star_sums` is a fused numba loop (one pass over the stars,
no temporaries; the hot path of every likelihood call); :func:`star_sums_numpy`
is the vectorised reference it is tested against.
"""

from __future__ import annotations

import numba
import numpy as np

from mavispm.dynamics.interpolation import cubic_weights, interpolate

__all__ = [
    "cubic_point_weights",
    "star_sums",
    "star_sums_numpy",
    "stars_about",
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


@numba.njit(nogil=True, cache=True)
def cubic_point_weights(q, x0, step, n):  # pragma: no cover - compiled
    """Index ``j`` and 4-point Lagrange weights of grid points ``j-1 .. j+2`` at ``q``.

    The compiled one-point form of :func:`mavispm.dynamics.interpolation.cubic_weights`
    (same clamping at the ends of the uniform grid ``x0 + step * arange(n)``).
    """
    pos = min(max((q - x0) / step, 0.0), n - 1.0)
    j = min(max(int(np.floor(pos)), 1), n - 3)
    s = pos - j
    sm1, sm2, sp1 = s - 1.0, s - 2.0, s + 1.0
    return j, -s * sm1 * sm2 / 6.0, sp1 * sm1 * sm2 / 2.0, -sp1 * s * sm2 / 2.0, sp1 * s * sm1 / 6.0


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
    chi = 0.0
    lsig = 0.0
    for i in range(u.size):
        j, w0, w1, w2, w3 = cubic_point_weights(u[i], x0, step, n)
        for c in range(2):
            ln_v = (
                w0 * ln_s2[c, j - 1]
                + w1 * ln_s2[c, j]
                + w2 * ln_s2[c, j + 1]
                + w3 * ln_s2[c, j + 2]
            )
            var = np.exp(ln_v) + e2[c, i]
            chi += v2[c, i] / var + np.log(var)
        lsig += w0 * ln_sig[j - 1] + w1 * ln_sig[j] + w2 * ln_sig[j + 1] + w3 * ln_sig[j + 2]
    return chi, lsig


@numba.njit(nogil=True, cache=True)
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
        dx = x[i] - x0
        dy = y[i] - y0
        r = max(np.sqrt(dx * dx + dy * dy), 1e-12)
        c = dx / r
        s = dy / r
        px = pm_x[i] - mx0
        py = pm_y[i] - my0
        vr = px * c + py * s
        vt = -px * s + py * c
        cd = cx[i] * c + sy[i] * s
        c2 = cd * cd
        s2 = 1.0 - c2
        ln_r[i] = np.log(max(r, min_r))
        v2[0, i] = vr * vr
        v2[1, i] = vt * vt
        e2[0, i] = er2[i] * c2 + et2[i] * s2
        e2[1, i] = er2[i] * s2 + et2[i] * c2
    return ln_r, v2, e2
