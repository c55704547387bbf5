"""The part of a star's fit residual that is odd about its centre: the misfit that moves it.

A model misfit even about the star (a width or halo error of a centred model) raises its
stamp's chi^2 without moving it; one odd about it (a neighbour's light on one side, an
asymmetric core) pulls the fitted position. The error model inflates the position
errors by the odd part's excess over the star's peers and the flux error by the whole
chi^2 (:mod:`mavispm.measure.stars.error_model`; docs/measure-scale.md, twenty-fifth
pass).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["odd_chi2"]


def odd_chi2(e: np.ndarray, valid: np.ndarray, dx: np.ndarray, dy: np.ndarray, n_odd: int):
    """Reduced chi^2 of the part of each stamp's residual that is odd about the star.

    The normalised residual ``e = sqrt(w) (data - model)`` at each pixel ``p`` is
    compared with its mirror image through the fitted centre, ``e(2 c - p)``, read by
    bilinear interpolation between the four pixels around the mirror point (the
    centre's sub-pixel phase: a reflection through the nearest pixel or half-pixel
    point, up to 0.25 px off, leaks an even misfit into the odd part in proportion to
    that offset over the PSF's width). For white noise ``sum (e_p - e(2 c - p))^2`` has
    the expectation ``sum (1 + sum_k w_k^2 - 2 w_self)`` (``w_k`` the interpolation
    weights, ``w_self`` that of the pixel itself): the statistic is divided by it and by
    the share of pairs the odd parameters (the position, and the sky slopes) absorb, so
    that pure noise gives 1. A misfit even about the star (a width or halo error of a
    centred model) cancels in it; one that moves the star (a neighbour's light on one
    side) does not.

    Parameters
    ----------
    e : ndarray, shape (N, S, S)
        Normalised residuals on the stamps (rows, columns).
    valid : ndarray of bool, shape (N, S, S)
    dx, dy : ndarray, shape (N,)
        Fitted centre less the stamp's central pixel [pixel].
    n_odd : int
        Odd parameters of the fit (2: x, y; 4 with the sky slopes).

    Returns
    -------
    ndarray, shape (N,)
        NaN where at most ``n_odd`` pairs are valid or the centre is not finite.
    """
    e = np.ascontiguousarray(e, dtype=np.float64)
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    dx = np.ascontiguousarray(dx, dtype=np.float64)
    dy = np.ascontiguousarray(dy, dtype=np.float64)
    return _odd_chi2(e, valid, dx, dy, int(n_odd))


@numba.njit(nogil=True, cache=True)
def _odd_chi2(e, valid, dx, dy, n_odd):
    """:func:`odd_chi2`, compiled (star by star, pixel by pixel)."""
    n, size = e.shape[0], e.shape[1]
    out = np.full(n, np.nan)
    for k in range(n):
        if not (np.isfinite(dx[k]) and np.isfinite(dy[k])):
            continue
        # the mirror of pixel index i is 2 d + 2 r - i = (q + 2 r - i) + f, q = floor(2 d)
        qx, qy = np.floor(2.0 * dx[k]), np.floor(2.0 * dy[k])
        fx, fy = 2.0 * dx[k] - qx, 2.0 * dy[k] - qy
        if abs(qx) >= size - 1 or abs(qy) >= size - 1:
            continue
        kx, ky = int(qx), int(qy)
        wx = (1.0 - fx, fx)
        wy = (1.0 - fy, fy)
        total = 0.0
        expect = 0.0
        count = 0
        for j in range(size):
            for i in range(size):
                if not valid[k, j, i] or not np.isfinite(e[k, j, i]):
                    continue
                mirror = 0.0
                wsq = 0.0
                wself = 0.0
                ok = True
                for sy in range(2):
                    for sx in range(2):
                        w = wy[sy] * wx[sx]
                        if w <= 0.0:
                            continue
                        jj = ky + sy + size - 1 - j
                        ii = kx + sx + size - 1 - i
                        if jj < 0 or jj >= size or ii < 0 or ii >= size:
                            ok = False
                        elif not valid[k, jj, ii] or not np.isfinite(e[k, jj, ii]):
                            ok = False
                        else:
                            mirror += w * e[k, jj, ii]
                            wsq += w * w
                            if jj == j and ii == i:
                                wself += w
                if not ok:
                    continue
                d = e[k, j, i] - mirror
                total += d * d
                expect += 1.0 + wsq - 2.0 * wself
                count += 1
        pairs = count / 2.0  # each pair of mirror pixels is counted twice
        if pairs > n_odd:
            absorbed = max(1.0 - n_odd / pairs, 1e-3)
            out[k] = total / max(expect * absorbed, 1e-300)
    return out
