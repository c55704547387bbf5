"""Line-of-sight velocity mixture: the proper-motion distribution a star really has.

A star seen at projected radius ``R`` lies at an unknown depth ``z`` on the line of
sight, at 3-D radius ``r = sqrt(R^2 + z^2)``. With a Gaussian 3-D velocity
distribution at each radius (dispersions ``sigma_r``, ``sigma_t``; anisotropy
``beta = 1 - sigma_t^2 / sigma_r^2``), its sky-radial and sky-tangential proper motions
are Gaussian *at that depth*, with variances

    s_R^2(r) = sigma_r^2 [(1 - beta) + beta R^2 / r^2],      s_T^2(r) = (1 - beta) sigma_r^2,

and the distribution of the star's motion is the mixture over depth, weighted by the
tracer density along the line of sight:

    p(v_R, v_T | R) = int nu(r) N(v_R | 0, s_R^2 + e_R^2) N(v_T | 0, s_T^2 + e_T^2) dz
                      / int nu(r) dz.

Its second moments are the projected dispersions of :mod:`mavispm.dynamics.jeans`, but
its shape is not Gaussian: where the dispersion changes along the line of sight (a
central black hole, a cusp, the fall-off beyond the core) it has heavier tails and a
narrower core, and the two components are correlated through the shared depth. A
Gaussian with the projected dispersions gives calibrated posteriors only for data drawn
from that Gaussian (the simulation-based calibration of docs/dynamics.md shows the
intervals too narrow on 3-D Gaussian velocities); this mixture is the model's own law.

Numerics. With ``r = X cosh t`` (``X = R / a``), ``dz = X cosh t dt`` and the integrand
is regular at ``z = 0``. ``K`` Gauss-Legendre nodes in ``t`` on
``[0, arccosh(r_end / X)]`` with ``r_end = max(100, 10 X)`` scale radii (the tracer
beyond holds < 1e-6 of any line of sight of the profiles offered), or the tidal radius of
a truncated (King 1962) tracer, give the mixture's
components on the likelihood's output grid ``X_j``: weights ``W_jk`` (normalised to
one per ``j``) and variances ``s_R^2``, ``s_T^2``. The tracer density and the Jeans
columns at the nodes come from the projector's radial grid by cubic interpolation.
Each star's components are the cubic interpolation of the grid's in ``ln X`` (the same
weights as the Gaussian model's dispersions). On a model with a 3000 solMass black
hole, 16 nodes give ln p within ~1e-3 of a dense integral at ``R = 0.05"`` and
within ~2e-5 at 15" (mean absolute error over Gaussian draws).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.special import logsumexp

from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.jeans_kernel import _floor, _project_row, jeans_columns
from mavispm.dynamics.star_sums import cubic_point_weights, stars_about, sum4
from mavispm.dynamics.vector_exp import exp_nonpositive

__all__ = [
    "LineOfSightNodes",
    "line_of_sight_model",
    "line_of_sight_nodes",
    "mixture_ln_densities",
    "mixture_star_sums",
    "mixture_star_sums_about",
    "mixture_star_sums_numpy",
]

_LN_2PI = np.log(2.0 * np.pi)
#: Least 3-D radius where every line of sight ends [scale radii]: beyond it < 1e-6 of an
#: untruncated tracer.
R_END = 100.0


@dataclass(frozen=True)
class LineOfSightNodes:
    """Fixed line-of-sight nodes of every output radius on the projector's radial grid.

    Parameters
    ----------
    index : ndarray of int64 (M, K, 4)
        Radial-grid indices of the 4-point cubic interpolation at each node.
    weight : ndarray (M, K, 4)
        Their Lagrange weights.
    dz : ndarray (M, K)
        Quadrature weight of each node in ``z`` [scale radii] (``X cosh t`` times the
        Gauss-Legendre weight in ``t``).
    inv_cosh2 : ndarray (M, K)
        ``R^2 / r^2 = 1 / cosh^2 t`` at each node.
    """

    index: np.ndarray
    weight: np.ndarray
    dz: np.ndarray
    inv_cosh2: np.ndarray


def line_of_sight_nodes(
    X, ln_r0: float, step: float, n_r: int, n_nodes: int, x_max: float, r_end: float | None = None
):
    """Build :class:`LineOfSightNodes` for output radii ``X`` on a uniform ``ln r`` grid.

    Parameters
    ----------
    X : ndarray (M,)
        Output projected radii [scale radii].
    ln_r0, step, n_r : float, float, int
        The radial grid ``ln_r0 + step * arange(n_r)``.
    n_nodes : int
        Gauss-Legendre nodes per line of sight (>= 2).
    x_max : float
        End of the radial grid [scale radii]; nodes stay inside it.
    r_end : float, optional
        3-D radius where the tracer ends [scale radii] (a tidal radius; None: untruncated,
        the lines of sight end at ``max(100, 10 X)``).

    Returns
    -------
    LineOfSightNodes
    """
    if n_nodes < 2:
        raise ValueError(f"line_of_sight_nodes must be >= 2, got {n_nodes}")
    X = np.asarray(X, dtype=float)
    end = np.maximum(R_END, 10.0 * X) if r_end is None else np.full(X.shape, float(r_end))
    end = np.minimum(end, 0.999 * x_max)
    t_max = np.arccosh(np.maximum(end / X, 1.0 + 1e-12))
    g, gw = np.polynomial.legendre.leggauss(n_nodes)
    t = 0.5 * t_max[:, None] * (g[None, :] + 1.0)
    cosh_t = np.cosh(t)
    dz = 0.5 * t_max[:, None] * gw[None, :] * X[:, None] * cosh_t
    idx, w = cubic_weights(ln_r0, step, n_r, np.log(X[:, None] * cosh_t))
    return LineOfSightNodes(
        index=np.ascontiguousarray(np.moveaxis(idx, 0, -1), dtype=np.int64),
        weight=np.ascontiguousarray(np.moveaxis(w, 0, -1)),
        dz=np.ascontiguousarray(dz),
        inv_cosh2=np.ascontiguousarray(1.0 / cosh_t**2),
    )


@numba.njit(nogil=True, cache=True)
def _at_node(f, idx, w):  # pragma: no cover - compiled
    """Cubic interpolation of grid values ``f`` at one node."""
    return w[0] * f[idx[0]] + w[1] * f[idx[1]] + w[2] * f[idx[2]] + w[3] * f[idx[3]]


@numba.njit(nogil=True, cache=True)
def line_of_sight_model(
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
    index,
    weight,
    dz,
    inv_cosh2,
):  # pragma: no cover - compiled
    """Mixture components, ln surface density and ln projected mass on the output radii.

    The Jeans model of :func:`mavispm.dynamics.jeans_kernel.log_dispersions` (same
    arguments up to ``hi``), evaluated at the line-of-sight nodes
    (``index, weight, dz, inv_cosh2`` of :class:`LineOfSightNodes`) instead of projected.

    Returns
    -------
    mix_w : ndarray (M, K)
        Mixture weights (``nu dz``, normalised to one per output radius).
    s2_r, s2_t : ndarray (M, K)
        Sky-radial and sky-tangential variances of the components [unit of ``weights``].
    ln_sigma, ln_proj : ndarray (M,)
        ln surface density and ln projected mass fraction (floored at the smallest
        normal double).
    """
    col_t, col_r = jeans_columns(
        r, ln_r, step, x_max, nu, m, m_end, tail_nu, beta_0, beta_inf, r_a, dark_radius, weights
    )
    n_out, n_k = dz.shape
    mix_w = np.zeros((n_out, n_k))
    s2_r = np.zeros((n_out, n_k))
    s2_t = np.zeros((n_out, n_k))
    ln_sigma = np.empty(n_out)
    ln_proj = np.empty(n_out)
    for i in range(n_out):
        s_nu, _, _, s_c = _project_row(k0[i], k2[i], kc[i], lo[i], hi[i], nu, col_t, col_r)
        ln_sigma[i] = np.log(_floor(s_nu))
        ln_proj[i] = np.log(_floor(m_out[i] + s_c))
        total = 0.0
        for k in range(n_k):
            idx = index[i, k]
            w = weight[i, k]
            dens = _at_node(nu, idx, w)
            if dens <= 0.0:  # beyond a truncated tracer (or interpolation below zero)
                continue
            ct = max(_at_node(col_t, idx, w), 0.0)
            cr = _at_node(col_r, idx, w)
            mix_w[i, k] = dens * dz[i, k]
            s2_t[i, k] = ct / dens
            s2_r[i, k] = max((ct + cr * inv_cosh2[i, k]) / dens, 0.0)
            total += mix_w[i, k]
        if total > 0.0:
            for k in range(n_k):
                mix_w[i, k] /= total
    return mix_w, s2_r, s2_t, ln_sigma, ln_proj


@numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract", "arcp"})
def _interpolate_rows(w0, w1, w2, w3, j, grid, out):  # pragma: no cover - compiled
    """Cubic interpolation of every column of ``grid`` between rows ``j-1 .. j+2``
    (contiguous rows: the loop over columns vectorises)."""
    r0, r1, r2, r3 = grid[j - 1], grid[j], grid[j + 1], grid[j + 2]
    for k in range(out.size):
        out[k] = w0 * r0[k] + w1 * r1[k] + w2 * r2[k] + w3 * r3[k]


@numba.njit(nogil=True, cache=True)
def _component_table(mix_w, s2_r, s2_t):  # pragma: no cover - compiled
    """The three (M, K) component tables side by side in one contiguous (M, 3K) table, so
    that a star's components are one interpolation over ``3K`` columns (ValueError
    unless the three share one shape (M, K) with M >= 4)."""
    n, n_k = mix_w.shape
    if n < 4 or s2_r.shape != mix_w.shape or s2_t.shape != mix_w.shape:
        raise ValueError("the mixture needs components of one shape (M, K), M >= 4")
    table = np.empty((n, 3 * n_k))
    for i in range(n):
        for k in range(n_k):
            table[i, k] = mix_w[i, k]
            table[i, n_k + k] = s2_r[i, k]
            table[i, 2 * n_k + k] = s2_t[i, k]
    return table


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def _star_terms(buf, n_k, tk, v2r, v2t, e2r, e2t):  # pragma: no cover - compiled
    """One star's mixture terms from its interpolated components ``buf`` (weights,
    ``s_R^2``, ``s_T^2`` side by side; errors added here).

    On return ``buf`` holds the weights clipped at zero, the exponents
    ``-(v_R^2 / V_R + v_T^2 / V_T) / 2`` and the amplitudes ``w / sqrt(V_R V_T)``, and
    ``tk`` the terms ``amplitude * exp(exponent)`` (the caller sums ``tk`` and the
    weights with :func:`~mavispm.dynamics.star_sums.sum4`: with the sums in the caller the star
    loop ran ~10% faster).

    The loops are branch-free and free of reductions, with one division per component
    (``1 / (V_R V_T)``, each variance floored at ``_LEAST_VARIANCE`` so that the
    product stays a normal double) and the vectorising
    :func:`~mavispm.dynamics.vector_exp.exp_nonpositive` (``numpy.exp`` in numba is a
    scalar library call), so they run on the CPU's vector units.
    """
    for k in range(n_k):
        vr = max(buf[n_k + k], 0.0) + e2r
        vt = max(buf[2 * n_k + k], 0.0) + e2t
        vr = _LEAST_VARIANCE if vr < _LEAST_VARIANCE else vr  # NaN propagates
        vt = _LEAST_VARIANCE if vt < _LEAST_VARIANCE else vt
        inv = 1.0 / (vr * vt)
        w = max(buf[k], 0.0)
        buf[k] = w
        buf[n_k + k] = -0.5 * (v2r * vt + v2t * vr) * inv
        buf[2 * n_k + k] = w * np.sqrt(inv)
    for k in range(n_k):
        tk[k] = buf[2 * n_k + k] * exp_nonpositive(buf[n_k + k])


@numba.njit(nogil=True, cache=True)
def _ln_underflowed(buf, n_k):  # pragma: no cover - compiled
    """ln of the summed terms in logarithms (log-sum-exp), for a star whose direct sum
    underflows (far in the tails); ``buf`` as :func:`_star_terms` leaves it."""
    best = -np.inf
    for k in range(n_k):
        if buf[2 * n_k + k] > 0.0:
            buf[n_k + k] += np.log(buf[2 * n_k + k])
            best = max(best, buf[n_k + k])
    acc = 0.0
    for k in range(n_k):
        if buf[2 * n_k + k] > 0.0:
            acc += np.exp(buf[n_k + k] - best)
    return best + np.log(acc)


#: Least variance of a component [(mas/yr)^2]: physically zero, and the product of two
#: stays a normal double.
_LEAST_VARIANCE = 1e-150

#: Summed terms below this are treated as underflowed (terms of ``exp(-708)`` and less).
_UNDERFLOW = 1e-280


@numba.njit(nogil=True, cache=True)
def mixture_ln_densities(u, x0, step, mix_w, s2_r, s2_t, v2, e2):  # pragma: no cover
    """ln mixture density of each star's proper motion [ln (mas/yr)^-2].

    Parameters
    ----------
    u : ndarray (N,)
        ``ln(R / a)`` of the stars.
    x0, step : float
        Start and step of the uniform ``ln X`` output grid.
    mix_w, s2_r, s2_t : ndarray (M, K)
        Mixture components on the grid (:func:`line_of_sight_model`), M >= 4.
    v2, e2 : ndarray (2, N)
        Squared radial / tangential proper motions and squared errors.

    Returns
    -------
    ndarray (N,)
        ``ln p(v_R,i, v_T,i | R_i)`` (components interpolated cubically in ``ln X``,
        clamped at the grid ends).
    """
    n, n_k = mix_w.shape
    table = _component_table(mix_w, s2_r, s2_t)
    buf = np.empty(3 * n_k)
    tk = np.empty(n_k)
    out = np.empty(u.size)
    for i in range(u.size):
        j, w0, w1, w2, w3 = cubic_point_weights(u[i], x0, step, n)
        _interpolate_rows(w0, w1, w2, w3, j, table, buf)
        _star_terms(buf, n_k, tk, v2[0, i], v2[1, i], e2[0, i], e2[1, i])
        total, wsum = sum4(tk, n_k), sum4(buf, n_k)
        if not wsum > 0.0:
            out[i] = -np.inf
        elif total > _UNDERFLOW:
            out[i] = np.log(total / wsum) - _LN_2PI
        else:
            out[i] = _ln_underflowed(buf, n_k) - np.log(wsum) - _LN_2PI
    return out


@numba.njit(nogil=True, cache=True)
def mixture_star_sums(u, x0, step, mix_w, s2_r, s2_t, ln_sig, v2, e2):  # pragma: no cover
    """Summed ln mixture density of the stars and their summed ln surface density.

    The sum of :func:`mixture_ln_densities`, computed across stars instead of star by
    star: the stars are grouped by interval of the output grid (a counting sort; any
    order works), the stars of one interval share the four table rows of their cubic
    interpolation, so each component is evaluated for all of them in one loop over the
    stars that vectorises (:func:`_run_terms`). The logarithms of
    the stars' densities are taken as the logarithm of running products (one ``log`` per
    many stars instead of one per star; a product is logged and restarted when it leaves
    [1e-150, 1e150], a density outside [1e-100, 1e100] is logged on its own); a star whose
    summed terms underflow is summed again in logarithms. The same sum to rounding.

    Parameters
    ----------
    u, x0, step, mix_w, s2_r, s2_t, v2, e2
        As :func:`mixture_ln_densities`.
    ln_sig : ndarray (M,)
        ln surface density on the grid.

    Returns
    -------
    ln_kin, lsig : float
        ``sum_i ln p(v_R,i, v_T,i | R_i)`` (including ``-ln 2 pi`` per star) and
        ``sum_i ln Sigma(R_i)``.
    """
    n, n_k = mix_w.shape
    if ln_sig.size != n:
        raise ValueError("ln_sig and the mixture components need one grid")
    table = _component_table(mix_w, s2_r, s2_t)
    n_s = u.size
    # the stars sorted by grid interval (a counting sort), with their cubic weights
    rows = np.empty(n_s, dtype=np.int64)
    lw_in = np.empty((4, n_s))
    _grid_weights(u, x0, step, n, rows, lw_in[0], lw_in[1], lw_in[2], lw_in[3])
    first = np.zeros(n + 1, dtype=np.int64)
    for i in range(n_s):
        first[rows[i] + 1] += 1
    for j in range(n):
        first[j + 1] += first[j]
    slot = first[:n].copy()
    lw = np.empty((4, n_s))
    v2s = np.empty((2, n_s))
    e2s = np.empty((2, n_s))
    rows_s = np.empty(n_s, dtype=np.int64)
    for i in range(n_s):
        j = rows[i]
        k = slot[j]
        slot[j] = k + 1
        rows_s[k] = j
        lw[0, k] = lw_in[0, i]
        lw[1, k] = lw_in[1, i]
        lw[2, k] = lw_in[2, i]
        lw[3, k] = lw_in[3, i]
        v2s[0, k] = v2[0, i]
        v2s[1, k] = v2[1, i]
        e2s[0, k] = e2[0, i]
        e2s[1, k] = e2[1, i]
    total = np.zeros(n_s)
    wsum = np.zeros(n_s)
    lsig = 0.0
    for j in range(1, n - 2):
        a, b = first[j], first[j + 1]
        if b > a:
            lsig += _dot4(
                ln_sig[j - 1], ln_sig[j], ln_sig[j + 1], ln_sig[j + 2],
                lw[0, a:b], lw[1, a:b], lw[2, a:b], lw[3, a:b],
            )  # fmt: skip
            _run_terms(
                table[j - 1], table[j], table[j + 1], table[j + 2], n_k,
                lw[0, a:b], lw[1, a:b], lw[2, a:b], lw[3, a:b],
                v2s[0, a:b], v2s[1, a:b], e2s[0, a:b], e2s[1, a:b], total[a:b], wsum[a:b],
            )  # fmt: skip
    prod = 1.0
    ln_acc = 0.0
    buf = np.empty(3 * n_k)
    tk = np.empty(n_k)
    for i in range(n_s):
        if not wsum[i] > 0.0:
            return -np.inf, lsig
        if not total[i] > _UNDERFLOW:
            j = rows_s[i]
            _interpolate_rows(lw[0, i], lw[1, i], lw[2, i], lw[3, i], j, table, buf)
            _star_terms(buf, n_k, tk, v2s[0, i], v2s[1, i], e2s[0, i], e2s[1, i])
            ln_acc += _ln_underflowed(buf, n_k) - np.log(sum4(buf, n_k))
            continue
        f = total[i] / wsum[i]
        if not 1e-100 <= f <= 1e100:  # also NaN: logged, and it propagates
            ln_acc += np.log(f)
            continue
        prod *= f
        if not 1e-150 < prod < 1e150:
            ln_acc += np.log(prod)
            prod = 1.0
    return ln_acc + np.log(prod) - n_s * _LN_2PI, lsig


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _grid_weights(u, x0, step, n, rows, w0, w1, w2, w3):  # pragma: no cover - compiled
    """Grid interval ``rows`` and cubic weights ``w0 .. w3`` of every star
    (:func:`~mavispm.dynamics.star_sums.cubic_point_weights`, inlined, in one loop)."""
    for i in range(u.size):
        rows[i], w0[i], w1[i], w2[i], w3[i] = cubic_point_weights(u[i], x0, step, n)


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def _dot4(f0, f1, f2, f3, w0, w1, w2, w3):  # pragma: no cover - compiled
    """``sum_i (w0_i f0 + w1_i f1 + w2_i f2 + w3_i f3)``: the interpolated grid values
    ``f0 .. f3`` summed over a run of stars (in order: no reassociation)."""
    acc = 0.0
    for i in range(w0.size):
        acc += w0[i] * f0 + w1[i] * f1 + w2[i] * f2 + w3[i] * f3
    return acc


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def _run_terms(
    r0, r1, r2, r3, n_k, w0, w1, w2, w3, v2r, v2t, e2r, e2t, total, wsum
):  # pragma: no cover - compiled
    """Add every component's term and weight to ``total`` and ``wsum`` for a run of stars
    that share the table rows ``r0 .. r3`` (cubic weights ``w0 .. w3`` per star).

    The terms of :func:`_star_terms` (weights clipped at zero, each variance floored at
    ``_LEAST_VARIANCE``, ``w exp(-(v_R^2 / V_R + v_T^2 / V_T) / 2) / sqrt(V_R V_T)``),
    with the loop over the run's stars innermost: branch-free, contiguous, so it runs on
    the vector units.
    """
    m = total.size
    for k in range(n_k):
        a0, a1, a2, a3 = r0[k], r1[k], r2[k], r3[k]
        kr = n_k + k
        b0, b1, b2, b3 = r0[kr], r1[kr], r2[kr], r3[kr]
        kt = 2 * n_k + k
        c0, c1, c2, c3 = r0[kt], r1[kt], r2[kt], r3[kt]
        for i in range(m):
            x0, x1, x2, x3 = w0[i], w1[i], w2[i], w3[i]
            w = max(x0 * a0 + x1 * a1 + x2 * a2 + x3 * a3, 0.0)
            vr = max(x0 * b0 + x1 * b1 + x2 * b2 + x3 * b3, 0.0) + e2r[i]
            vt = max(x0 * c0 + x1 * c1 + x2 * c2 + x3 * c3, 0.0) + e2t[i]
            vr = _LEAST_VARIANCE if vr < _LEAST_VARIANCE else vr  # NaN propagates
            vt = _LEAST_VARIANCE if vt < _LEAST_VARIANCE else vt
            inv = 1.0 / (vr * vt)
            ex = -0.5 * (v2r[i] * vt + v2t[i] * vr) * inv
            wsum[i] += w
            total[i] += w * np.sqrt(inv) * exp_nonpositive(ex)


@numba.njit(nogil=True, cache=True)
def mixture_star_sums_about(
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
):  # pragma: no cover - compiled
    """:func:`~mavispm.dynamics.star_sums.stars_about` then :func:`mixture_star_sums`."""
    ln_r, v2, e2 = stars_about(x, y, pm_x, pm_y, cx, sy, er2, et2, x0, y0, mx0, my0, min_r)
    return mixture_star_sums(ln_r - ln_a, grid_x0, step, mix_w, s2_r, s2_t, ln_sig, v2, e2)


def mixture_star_sums_numpy(u, x0, step, mix_w, s2_r, s2_t, ln_sig, v2, e2):
    """Reference implementation of :func:`mixture_star_sums` (numpy, log-sum-exp).

    Parameters and returns as :func:`mixture_star_sums`.
    """
    idx, w = cubic_weights(x0, step, ln_sig.size, u)
    wk = np.maximum(interpolate(mix_w.T, idx, w), 0.0)  # (K, N)
    vr = np.maximum(np.maximum(interpolate(s2_r.T, idx, w), 0.0) + e2[0], np.finfo(float).tiny)
    vt = np.maximum(np.maximum(interpolate(s2_t.T, idx, w), 0.0) + e2[1], np.finfo(float).tiny)
    with np.errstate(divide="ignore"):
        terms = np.log(wk) - 0.5 * (v2[0] / vr + v2[1] / vt + np.log(vr * vt))
    ln_p = logsumexp(terms, axis=0) - np.log(wk.sum(axis=0)) - _LN_2PI
    return float(np.sum(ln_p)), float(np.sum(interpolate(ln_sig, idx, w)))
