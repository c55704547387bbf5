"""Line-of-sight mixture with a fitted local excess kurtosis (``line_of_sight_kurtosis``).

The mixture over depth of :mod:`mavispm.dynamics.line_of_sight` (node weights ``W_k``
from the tracer density along the line of sight, per-node sky variances ``s_R^2``,
``s_T^2`` from the Jeans model), with each node's Gaussian per sky component replaced by
the two-Gaussian family of :mod:`mavispm.dynamics.shape_law` with one fitted excess
kurtosis ``kappa`` of the *local* (3-D) velocity distribution:

    p(v_R, v_T | R) = sum_k W_k f(v_R | s_R,k^2, e_R^2, kappa) f(v_T | s_T,k^2, e_T^2, kappa)
                      / sum_k W_k,

``f`` the error-convolved component density of :func:`mavispm.dynamics.shape_law.shape_density`
(exact variance ``s^2 + e^2``; ``kappa = 0``: the Gaussian, so the law is then the
line-of-sight law). The two sky components of one node share ``kappa`` and are
independent at that depth (the family is a per-component shape, not a 3-D distribution:
a platykurtic local distribution truncated at the escape speed is only approximated).

:func:`kurtosis_mixture_star_sums` is the compiled sum over stars (one ``kappa`` for all
radii), :func:`kurtosis_mixture_star_sums_numpy` its numpy reference.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.special import logsumexp

from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.line_of_sight import _component_table, _interpolate_rows
from mavispm.dynamics.shape_law import _component, shape_density
from mavispm.dynamics.star_sums import cubic_point_weights, stars_about

__all__ = [
    "kurtosis_mixture_ln_densities",
    "kurtosis_mixture_star_sums",
    "kurtosis_mixture_star_sums_about",
    "kurtosis_mixture_star_sums_numpy",
]

_LN_2PI = np.log(2.0 * np.pi)
#: Least variance of a component [(mas/yr)^2] (as the line-of-sight law's).
_LEAST_VARIANCE = 1e-150


@numba.njit(nogil=True, cache=True)
def kurtosis_mixture_ln_densities(
    u, x0, step, mix_w, s2_r, s2_t, v2, e2, kappa
):  # pragma: no cover
    """ln density of each star's proper motion [ln (mas/yr)^-2].

    Parameters
    ----------
    u, x0, step, mix_w, s2_r, s2_t, v2, e2
        As :func:`mavispm.dynamics.line_of_sight.mixture_ln_densities`.
    kappa : float
        Local excess kurtosis, in ``shape_law.KAPPA_LIMITS``.

    Returns
    -------
    ndarray (N,)
        ``ln p(v_R,i, v_T,i | R_i)``.
    """
    n, n_k = mix_w.shape
    table = _component_table(mix_w, s2_r, s2_t)
    buf = np.empty(3 * n_k)
    lt = np.empty(n_k)
    out = np.empty(u.size)
    for i in range(u.size):
        j, w0, w1, w2, w3 = cubic_point_weights(u[i], x0, step, n)
        _interpolate_rows(w0, w1, w2, w3, j, table, buf)
        wsum = 0.0
        best = -np.inf
        for k in range(n_k):
            w = max(buf[k], 0.0)
            wsum += w
            if not w > 0.0:
                lt[k] = -np.inf
                continue
            s2r = max(buf[n_k + k], 0.0)
            s2t = max(buf[2 * n_k + k], 0.0)
            e2r = max(e2[0, i], _LEAST_VARIANCE - s2r)
            e2t = max(e2[1, i], _LEAST_VARIANCE - s2t)
            qr, xr = _component(v2[0, i], s2r, e2r, kappa)
            qt, xt = _component(v2[1, i], s2t, e2t, kappa)
            lt[k] = np.log(w) - 0.5 * (np.log(qr) + np.log(qt) + xr + xt)
            best = max(best, lt[k])
        if not wsum > 0.0 or best == -np.inf:
            out[i] = -np.inf
            continue
        acc = 0.0
        for k in range(n_k):
            acc += np.exp(lt[k] - best)
        out[i] = best + np.log(acc) - np.log(wsum) - _LN_2PI
    return out


@numba.njit(nogil=True, cache=True)
def kurtosis_mixture_star_sums(
    u, x0, step, mix_w, s2_r, s2_t, ln_sig, v2, e2, kappa
):  # pragma: no cover - compiled
    """Summed ln density of the stars (:func:`kurtosis_mixture_ln_densities`) and their
    summed ln surface density (the returns of
    :func:`mavispm.dynamics.line_of_sight.mixture_star_sums`)."""
    n = mix_w.shape[0]
    if ln_sig.size != n:
        raise ValueError("ln_sig and the mixture components need one grid")
    ln_p = kurtosis_mixture_ln_densities(u, x0, step, mix_w, s2_r, s2_t, v2, e2, kappa)
    lsig = 0.0
    for i in range(u.size):
        j, w0, w1, w2, w3 = cubic_point_weights(u[i], x0, step, n)
        lsig += w0 * ln_sig[j - 1] + w1 * ln_sig[j] + w2 * ln_sig[j + 1] + w3 * ln_sig[j + 2]
    return np.sum(ln_p), lsig


@numba.njit(nogil=True, cache=True)
def kurtosis_mixture_star_sums_about(
    x,
    y,
    pm_x,
    pm_y,
    cx,
    sy,
    er2,
    et2,
    x0,
    y0,
    mx0,
    my0,
    min_r,
    ln_a,
    grid_x0,
    step,
    mix_w,
    s2_r,
    s2_t,
    ln_sig,
    kappa,
):  # pragma: no cover - compiled
    """:func:`~mavispm.dynamics.star_sums.stars_about` then
    :func:`kurtosis_mixture_star_sums`."""
    ln_r, v2, e2 = stars_about(x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r)
    return kurtosis_mixture_star_sums(
        ln_r - ln_a, grid_x0, step, mix_w, s2_r, s2_t, ln_sig, v2, e2, kappa
    )


def kurtosis_mixture_star_sums_numpy(u, x0, step, mix_w, s2_r, s2_t, ln_sig, v2, e2, kappa):
    """Reference implementation of :func:`kurtosis_mixture_star_sums` (numpy, with
    :func:`mavispm.dynamics.shape_law.shape_density`)."""
    idx, w = cubic_weights(x0, step, ln_sig.size, u)
    wk = np.maximum(interpolate(mix_w.T, idx, w), 0.0)  # (K, N)
    s2r = np.maximum(interpolate(s2_r.T, idx, w), 0.0)
    s2t = np.maximum(interpolate(s2_t.T, idx, w), 0.0)
    with np.errstate(divide="ignore", under="ignore"):
        pr = shape_density(np.sqrt(v2[0]), s2r, e2[0], kappa)
        pt = shape_density(np.sqrt(v2[1]), s2t, e2[1], kappa)
        terms = np.log(wk) + np.log(pr) + np.log(pt)
    ln_p = logsumexp(terms, axis=0) - np.log(wk.sum(axis=0))
    return float(np.sum(ln_p)), float(np.sum(interpolate(ln_sig, idx, w)))
