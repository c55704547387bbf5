"""Free-kurtosis velocity law: the projected dispersions with a fitted symmetric shape.

Each sky proper-motion component ``v`` (radial, tangential) of a star at projected radius
``R`` has the model's projected variance ``s^2 = sigma_c^2(R)`` and an excess kurtosis
``kappa`` (kurtosis ``3 + kappa``), drawn from a two-Gaussian family:

* ``kappa >= 0`` (heavier tails than a Gaussian, as the line-of-sight mixture of
  Gaussian 3-D velocities): the scale mixture
  ``f = N(0, (1 - k) s^2) / 2 + N(0, (1 + k) s^2) / 2`` with ``k = sqrt(kappa / 3)``;
* ``kappa < 0`` (flatter, as near an IMBH where the distribution function ends at the
  escape speed): the displaced pair ``f = N(+mu, w^2) / 2 + N(-mu, w^2) / 2`` with
  ``mu^2 = m s^2``, ``w^2 = (1 - m) s^2``, ``m = sqrt(-kappa / 2)``.

Both have variance ``s^2`` exactly, kurtosis ``3(1 + k^2)`` and ``3 - 2 m^2`` (so
``3 + kappa``), are positive everywhere, and to first order in ``kappa`` are the same
Gauss-Hermite perturbation ``N(0, s^2) [1 + kappa He4(v / s) / 24]``, so ``kappa`` is a
shape parameter passing continuously through 0 (the Gaussian law; the next term is
``O(kappa^2)`` for ``kappa > 0`` and ``O(|kappa|^(3/2))`` for ``kappa < 0``). Convolved with a star's Gaussian
error ``e`` each Gaussian's variance grows by ``e^2`` (closed form): with ``A, B = (1 -+
k) s^2 + e^2`` and ``W = w^2 + e^2``

    -2 ln p - ln 2 pi = ln B + v^2 / B - 2 ln[(1 + sqrt(B / A) exp(-v^2 (1/A - 1/B) / 2)) / 2]
                      = ln W + (v^2 + mu^2) / W - 2 ln cosh(|v| mu / W)          (kappa < 0),

a density of variance ``s^2 + e^2`` and excess kurtosis ``kappa (s^2 / (s^2 + e^2))^2``.
``kappa`` lies in (-2, 3) (the limits are a pair of points and a zero-width component).

(A Gauss-Hermite series ``N(0, s^2)[1 + h4 He4(v / s) / sqrt(24)]`` has the same
closed-form convolution but goes negative in the tails for ``h4 < 0``; flooring it
there and renormalising adds variance, 1.2 % at ``h4 = -0.1`` and 6.6 % at -0.25, and
stops the kurtosis at ~2.4, so it was not used; docs/dynamics.md.)

Radial dependence (``kappa_inner``, ``kappa_outer``): ``kappa`` is linear in ``ln R``
between two anchor radii and constant outside them (one global ``kappa``: equal values).

:func:`shape_star_sums` is the compiled sum over the stars (the counterpart of
:func:`mavispm.dynamics.star_sums.star_sums`, with its ``chi`` convention:
``ln L_kin = -chi / 2 - N ln 2 pi``), branch-free so that it runs on the vector units (the
pair's ``-2 ln cosh`` as ``-2 |v| mu / W - 2 ln[(1 + exp(-2 |v| mu / W)) / 2]``, which
cannot overflow); :func:`shape_star_sums_numpy` its numpy reference; :func:`shape_density`
the density of one component.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.star_sums import cubic_point_weights, stars_about, sum4
from mavispm.dynamics.vector_exp import exp_bounded, exp_nonpositive, log_positive

__all__ = [
    "KAPPA_LIMITS",
    "kappa_at",
    "shape_density",
    "shape_star_sums",
    "shape_star_sums_about",
    "shape_star_sums_numpy",
]

#: Open interval of the excess kurtosis the family reaches.
KAPPA_LIMITS = (-2.0, 3.0)


def kappa_at(ln_r, kappa_inner, kappa_outer, ln_r_lo, ln_r_hi):
    """``kappa`` at ``ln R``: linear in ``ln R`` between the anchors, constant outside."""
    t = np.clip((np.asarray(ln_r, dtype=float) - ln_r_lo) / (ln_r_hi - ln_r_lo), 0.0, 1.0)
    return kappa_inner + (kappa_outer - kappa_inner) * t


def shape_density(v, s2, e2, kappa):
    """Density of one proper-motion component (numpy reference; the module's mixtures).

    Parameters
    ----------
    v : array_like
        Proper-motion component [mas/yr].
    s2, e2 : array_like
        Model dispersion squared and error squared [(mas/yr)^2].
    kappa : array_like
        Intrinsic excess kurtosis, in ``KAPPA_LIMITS``.

    Returns
    -------
    ndarray
        The two-Gaussian mixture convolved with the error.
    """
    v, s2, e2, kappa = np.broadcast_arrays(
        *(np.asarray(a, dtype=float) for a in (v, s2, e2, kappa))
    )

    def gauss(x, mean, var):
        return np.exp(-0.5 * (x - mean) ** 2 / var) / np.sqrt(2.0 * np.pi * var)

    k = np.sqrt(np.maximum(kappa, 0.0) / 3.0)
    scale = 0.5 * (gauss(v, 0.0, (1 - k) * s2 + e2) + gauss(v, 0.0, (1 + k) * s2 + e2))
    m = np.sqrt(np.maximum(-kappa, 0.0) / 2.0)
    mu, w2 = np.sqrt(m * s2), (1.0 - m) * s2 + e2
    pair = 0.5 * (gauss(v, mu, w2) + gauss(v, -mu, w2))
    return np.where(kappa >= 0, scale, pair)


def shape_star_sums_numpy(u, ln_a, x0, step, ln_s2, ln_sig, v2, e2, kappa_par):
    """Reference implementation of :func:`shape_star_sums` (numpy).

    Parameters
    ----------
    u : ndarray (N,)
        ``ln(R / a)`` of the stars.
    ln_a : float
        ln scale radius [ln arcsec] (``ln R = u + ln a`` sets ``kappa``).
    x0, step : float
        Start and step of the uniform ``ln X`` grid.
    ln_s2 : ndarray (2, n)
        ln model dispersion squared (radial, tangential) on the grid.
    ln_sig : ndarray (n,)
        ln surface density on the grid.
    v2, e2 : ndarray (2, N)
        Squared proper-motion components and squared errors.
    kappa_par : ndarray (4,)
        ``kappa_inner, kappa_outer, ln R_lo, ln R_hi`` (equal kappas: one global value).

    Returns
    -------
    chi, lsig : float
        ``-sum(2 ln p + ln 2 pi)`` over stars and components, and the sum of the
        interpolated ln surface density.
    """
    idx, w = cubic_weights(x0, step, ln_sig.size, u)
    s2 = np.exp(interpolate(ln_s2, idx, w))
    kappa = kappa_at(u + ln_a, *kappa_par)
    p = shape_density(np.sqrt(v2), s2, e2, kappa)
    chi = -np.sum(2.0 * np.log(p) + np.log(2.0 * np.pi))
    return float(chi), float(np.sum(interpolate(ln_sig, idx, w)))


#: Floor of a component's variance factor ``q`` [(mas/yr)^2] before two are multiplied
#: (as the line-of-sight law's ``_LEAST_VARIANCE``): their product stays a normal double.
_LEAST_FACTOR = 1e-150


@numba.njit(nogil=True, cache=True, inline="always", fastmath={"contract"}, error_model="numpy")
def _scale_factor(v2, s2, e2, k):  # pragma: no cover - compiled
    """``(q, x)`` of one component of the scale mixture (``kappa >= 0``, ``k = sqrt(kappa
    / 3)``): ``-2 ln p - ln 2 pi = ln q + x`` with ``q = B / Q^2``, ``x = v^2 / B``,
    ``Q = (1 + sqrt(B / A) exp(-v^2 (1/A - 1/B) / 2)) / 2``; branch-free (vectorises)."""
    a = (1.0 - k) * s2 + e2
    b = (1.0 + k) * s2 + e2
    ia = 1.0 / a
    ib = 1.0 / b
    q = 0.5 * (1.0 + np.sqrt(b * ia) * exp_nonpositive(-0.5 * v2 * (ia - ib)))
    f = b / (q * q)
    return (_LEAST_FACTOR if f < _LEAST_FACTOR else f), v2 * ib  # NaN propagates


@numba.njit(nogil=True, cache=True, inline="always", fastmath={"contract"}, error_model="numpy")
def _pair_factor(v2, s2, e2, m):  # pragma: no cover - compiled
    """``(q, x)`` of one component of the displaced pair (``kappa < 0``, ``m = sqrt(-kappa
    / 2)``): ``-2 ln p - ln 2 pi = ln q + x`` with ``q = 4 W / (1 + exp(-2 |v| mu / W))^2``
    and ``x = (|v| - mu)^2 / W`` (``-2 ln cosh`` written without overflow); branch-free."""
    mu = np.sqrt(m * s2)
    w = (1.0 - m) * s2 + e2
    iw = 1.0 / w
    av = np.sqrt(v2)
    d = av - mu
    h = 1.0 + exp_nonpositive(-2.0 * av * mu * iw)
    f = 4.0 * w / (h * h)
    return (_LEAST_FACTOR if f < _LEAST_FACTOR else f), d * d * iw


@numba.njit(nogil=True, cache=True, inline="always")
def _component(v2, s2, e2, kappa):  # pragma: no cover - compiled
    """``(q, x)`` of one component at ``kappa`` of either sign (one branch; the scalar
    counterpart of the term loops below): ``-2 ln p - ln 2 pi = ln q + x``."""
    if kappa >= 0.0:
        return _scale_factor(v2, s2, e2, math.sqrt(kappa / 3.0))
    return _pair_factor(v2, s2, e2, math.sqrt(-0.5 * kappa))


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _star_values(
    u, ln_a, x0, step, ln_s2, ln_sig, kappa_par, ln_s2r, ln_s2t, kappa, lsig
):  # pragma: no cover - compiled
    """Each star's interpolated ``ln s^2`` (radial, tangential), ``kappa`` and ln surface
    density (cubic weights of :func:`~mavispm.dynamics.star_sums.cubic_point_weights`)."""
    n = ln_sig.size
    k_in, k_out, t_lo, t_hi = kappa_par[0], kappa_par[1], kappa_par[2], kappa_par[3]
    dk = k_out - k_in
    inv = 1.0 / (t_hi - t_lo)
    row_r = ln_s2[0]
    row_t = ln_s2[1]
    for i in range(u.size):
        j, w0, w1, w2, w3 = cubic_point_weights(u[i], x0, step, n)
        # unsigned indices (j >= 1): no negative-index wraparound checks in the loads
        k0 = np.uint64(j - 1)
        k1, k2, k3 = k0 + np.uint64(1), k0 + np.uint64(2), k0 + np.uint64(3)
        ln_s2r[i] = w0 * row_r[k0] + w1 * row_r[k1] + w2 * row_r[k2] + w3 * row_r[k3]
        ln_s2t[i] = w0 * row_t[k0] + w1 * row_t[k1] + w2 * row_t[k2] + w3 * row_t[k3]
        lsig[i] = w0 * ln_sig[k0] + w1 * ln_sig[k1] + w2 * ln_sig[k2] + w3 * ln_sig[k3]
        kappa[i] = k_in + dk * min(max((u[i] + ln_a - t_lo) * inv, 0.0), 1.0)


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def _scale_terms(v2r, v2t, e2r, e2t, ln_s2r, ln_s2t, kappa, out):  # pragma: no cover
    """Each star's ``-2 ln p - 2 ln 2 pi`` (both components) where every ``kappa >= 0``."""
    for i in range(out.size):
        k = np.sqrt(kappa[i] * (1.0 / 3.0))
        qr, xr = _scale_factor(v2r[i], exp_bounded(ln_s2r[i]), e2r[i], k)
        qt, xt = _scale_factor(v2t[i], exp_bounded(ln_s2t[i]), e2t[i], k)
        out[i] = log_positive(qr * qt) + xr + xt


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def _pair_terms(v2r, v2t, e2r, e2t, ln_s2r, ln_s2t, kappa, out):  # pragma: no cover
    """Each star's ``-2 ln p - 2 ln 2 pi`` (both components) where every ``kappa < 0``."""
    for i in range(out.size):
        m = np.sqrt(-0.5 * kappa[i])
        qr, xr = _pair_factor(v2r[i], exp_bounded(ln_s2r[i]), e2r[i], m)
        qt, xt = _pair_factor(v2t[i], exp_bounded(ln_s2t[i]), e2t[i], m)
        out[i] = log_positive(qr * qt) + xr + xt


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def _mixed_terms(v2r, v2t, e2r, e2t, ln_s2r, ln_s2t, kappa, out):  # pragma: no cover
    """As :func:`_scale_terms` for ``kappa`` of either sign: both forms, one selected per
    star (twice the arithmetic, still branch-free)."""
    for i in range(out.size):
        kp = kappa[i]
        k = np.sqrt(max(kp, 0.0) * (1.0 / 3.0))
        m = np.sqrt(max(-kp, 0.0) * 0.5)
        s2r = exp_bounded(ln_s2r[i])
        s2t = exp_bounded(ln_s2t[i])
        qr, xr = _scale_factor(v2r[i], s2r, e2r[i], k)
        qt, xt = _scale_factor(v2t[i], s2t, e2t[i], k)
        pr, yr = _pair_factor(v2r[i], s2r, e2r[i], m)
        pt, yt = _pair_factor(v2t[i], s2t, e2t[i], m)
        neg = kp < 0.0
        out[i] = log_positive(pr * pt if neg else qr * qt) + (yr + yt if neg else xr + xt)


@numba.njit(nogil=True, cache=True)
def shape_star_sums(u, ln_a, x0, step, ln_s2, ln_sig, v2, e2, kappa_par):  # pragma: no cover
    """Compiled :func:`shape_star_sums_numpy` (same arguments and results to rounding).

    Two passes over the stars: their interpolated values (:func:`_star_values`), then
    their terms in a branch-free loop (:func:`_scale_terms`, :func:`_pair_terms` or, where
    ``kappa`` changes sign over the stars, :func:`_mixed_terms`) that runs on the vector
    units, with the two components' ``ln q`` in one logarithm; each ``q`` is floored at
    ``_LEAST_FACTOR`` (1e-150 (mas/yr)^2, far below any dispersion).
    """
    n = ln_sig.size
    if n < 4 or ln_s2.shape[1] != n:
        raise ValueError("shape_star_sums needs ln_s2 (2, n) and ln_sig (n,) with n >= 4")
    size = u.size
    ln_s2r = np.empty(size)
    ln_s2t = np.empty(size)
    kappa = np.empty(size)
    lsig = np.empty(size)
    out = np.empty(size)
    _star_values(u, ln_a, x0, step, ln_s2, ln_sig, kappa_par, ln_s2r, ln_s2t, kappa, lsig)
    terms = (v2[0], v2[1], e2[0], e2[1], ln_s2r, ln_s2t, kappa, out)
    if kappa_par[0] >= 0.0 and kappa_par[1] >= 0.0:
        _scale_terms(*terms)
    elif kappa_par[0] < 0.0 and kappa_par[1] < 0.0:
        _pair_terms(*terms)
    elif kappa_par[0] == kappa_par[0] and kappa_par[1] == kappa_par[1]:
        _mixed_terms(*terms)
    else:  # NaN kappa: NaN, as every other NaN parameter
        return np.nan, sum4(lsig, size)
    return sum4(out, size), sum4(lsig, size)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def shape_star_sums_about(
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
    ln_s2,
    ln_sig,
    kappa_par,
):  # pragma: no cover - compiled
    """:func:`mavispm.dynamics.star_sums.stars_about` then :func:`shape_star_sums`.

    Arguments as :func:`mavispm.dynamics.star_sums.star_sums_about` plus ``kappa_par``
    (:func:`shape_star_sums`); ``kappa`` follows each star's radius about the fitted centre.
    """
    ln_r, v2, e2 = stars_about(x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r)
    return shape_star_sums(ln_r - ln_a, ln_a, grid_x0, step, ln_s2, ln_sig, v2, e2, kappa_par)
