"""Compiled evaluation of a field-variable ePSF on pixel stamps (numba).

The same interpolation as :meth:`mavispm.measure.stars.variable_psf.VariableEPSF.evaluate`'s
numpy path: a cubic B-spline through the prefiltered, zero-padded basis ePSFs, mixed per
star by its mixing weights, sampled at the stamp pixel centres, with the derivatives
with respect to the star centre. Each star's mixed spline coefficients are formed
once on the window its stamp's taps cover (``L = os (S - 1) + 4`` samples per axis),
then contracted with the separable tap weights; taps outside the basis grid read
zero (the numpy path's zero padding). Everything is float64 (the numpy path gathers
in float32), so the two agree to float32 rounding and this one is the more exact.

Cost per star: ``L^2 M`` for the mixing (``M`` mixing terms) plus ``48 S^2`` for the
value and both derivatives, with no temporary arrays of ``N x (4 S)^2``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["deposit_radial", "evaluate_stamps", "normal_equations"]


@numba.njit(nogil=True, cache=True, inline="always")
def _weights(t, w, dw):
    """Cubic B-spline tap weights at -1, 0, 1, 2 and their derivatives, t in [0, 1)."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w[0] = s * s * s / 6.0
    w[1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
    w[2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    w[3] = t3 / 6.0
    dw[0] = -(s * s) / 2.0
    dw[1] = (3.0 * t2 - 4.0 * t) / 2.0
    dw[2] = (-3.0 * t2 + 2.0 * t + 1.0) / 2.0
    dw[3] = t2 / 2.0


@numba.njit(nogil=True, cache=True)
def _evaluate(coef, idx, wmix, x0, y0, cx, cy, radius, os_, centre_x, centre_y, value, dvx, dvy):
    n = x0.shape[0]
    nb, ny, nx = coef.shape
    s = 2 * radius + 1
    length = os_ * (s - 1) + 4
    nmix = idx.shape[1]
    window = np.empty((length, length))
    wx = np.empty(4)
    dwx = np.empty(4)
    wy = np.empty(4)
    dwy = np.empty(4)
    deriv = dvx.shape[0] > 0
    for k in range(n):
        u0 = (cx[k] - radius - x0[k]) * os_ + centre_x
        v0 = (cy[k] - radius - y0[k]) * os_ + centre_y
        fu = np.floor(u0)
        fv = np.floor(v0)
        _weights(u0 - fu, wx, dwx)
        _weights(v0 - fv, wy, dwy)
        c0 = int(fu) - 1
        r0 = int(fv) - 1
        # the star's mixed coefficients on its window (zero outside the basis grid);
        # plane by plane with contiguous inner loops (vectorised)
        window[:, :] = 0.0
        b_lo = max(0, -c0)
        b_hi = min(length, nx - c0)
        for m in range(nmix):
            wm = wmix[k, m]
            plane = idx[k, m]
            for a in range(max(0, -r0), min(length, ny - r0)):
                row = r0 + a
                for b in range(b_lo, b_hi):
                    window[a, b] += wm * coef[plane, row, c0 + b]
        for j in range(s):
            for i in range(s):
                val = 0.0
                gx = 0.0
                gy = 0.0
                for a in range(4):
                    ra = os_ * j + a
                    sx = 0.0
                    sdx = 0.0
                    for b in range(4):
                        c = window[ra, os_ * i + b]
                        sx += wx[b] * c
                        sdx += dwx[b] * c
                    val += wy[a] * sx
                    gx += wy[a] * sdx
                    gy += dwy[a] * sx
                value[k, j, i] = val
                if deriv:
                    dvx[k, j, i] = -os_ * gx
                    dvy[k, j, i] = -os_ * gy


def evaluate_stamps(
    coef: np.ndarray,
    idx: np.ndarray,
    wmix: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    radius: int,
    oversampling: int,
    centre: tuple[float, float],
    derivatives: bool = True,
):
    """ePSF values (unit flux) on each star's stamp, and the position derivatives.

    Parameters
    ----------
    coef : ndarray, shape (K, ny, nx)
        Cubic B-spline coefficients of the zero-padded basis ePSFs (float64).
    idx : ndarray of int, shape (N, M)
        Basis images mixed for each star.
    wmix : ndarray, shape (N, M)
        Their mixing weights.
    x0, y0 : ndarray, shape (N,)
        Star centres [pixel].
    cx, cy : ndarray of int, shape (N,)
        Stamp centre pixels (column, row).
    radius : int
        Stamp half-width [pixel].
    oversampling : int
        ePSF samples per detector pixel.
    centre : (float, float)
        Position of the star centre in ``coef``'s (column, row) sample coordinates.
    derivatives : bool
        Also return d value / d x0 and d value / d y0 [1/pixel].

    Returns
    -------
    value : ndarray, shape (N, S, S)
        Fraction of the flux in each stamp pixel, indexed [star, row, column].
    dx, dy : ndarray, shape (N, S, S)
        Derivatives with respect to x0 and y0 (only if ``derivatives``).
    """
    n = len(x0)
    s = 2 * int(radius) + 1
    value = np.empty((n, s, s))
    shape = (n, s, s) if derivatives else (0, s, s)
    dvx, dvy = np.empty(shape), np.empty(shape)
    _evaluate(
        np.ascontiguousarray(coef, dtype=np.float64),
        np.ascontiguousarray(idx, dtype=np.intp),
        np.ascontiguousarray(wmix, dtype=np.float64),
        np.ascontiguousarray(x0, dtype=np.float64),
        np.ascontiguousarray(y0, dtype=np.float64),
        np.ascontiguousarray(cx, dtype=np.intp),
        np.ascontiguousarray(cy, dtype=np.intp),
        int(radius),
        int(oversampling),
        float(centre[0]),
        float(centre[1]),
        value,
        dvx,
        dvy,
    )
    if not derivatives:
        return value
    return value, dvx, dvy


@numba.njit(nogil=True, cache=True)
def _normal(
    value, dvx, dvy, data, model_all, own, valid, flux, sky, slope, basis, rn2, first, a, b, w, r
):
    n, m = value.shape
    npar = a.shape[1]
    jac = np.empty(npar)
    for k in range(n):
        for p in range(npar):
            b[k, p] = 0.0
            for q in range(npar):
                a[k, p, q] = 0.0
        for i in range(m):
            neigh = model_all[k, i] - own[k, i]
            star = flux[k] * value[k, i]
            back = sky[k]
            if npar == 6:
                back += slope[k, 0] * basis[0, i] + slope[k, 1] * basis[1, i]
            res = data[k, i] - neigh - star - back
            var = neigh + star + back
            if var < 0.0:
                var = 0.0
            wi = valid[k, i] / (var + rn2)
            w[k, i] = wi
            r[k, i] = res
            if wi == 0.0:
                continue
            jac[0] = flux[k] * dvx[k, i]
            jac[1] = flux[k] * dvy[k, i]
            jac[2] = value[k, i]
            jac[3] = 1.0
            if npar == 6:
                jac[4] = basis[0, i]
                jac[5] = basis[1, i]
            # first = 2: the flux and sky rows only (positions held; their rows stay 0)
            for p in range(first, npar):
                jw = jac[p] * wi
                b[k, p] += jw * res
                for q in range(first, p + 1):
                    a[k, p, q] += jw * jac[q]
        for p in range(npar):
            for q in range(p):
                a[k, q, p] = a[k, p, q]


def normal_equations(
    value, dvx, dvy, data, model_all, own, valid, flux, sky, slope, basis, rn2, positions=True
):
    """Weights, residuals and the normal equations of N stars on their stamps, fused.

    The model of star k's stamp is its own ``flux value`` plus the neighbours'
    (``model_all - own``) plus its sky (a level, and a plane when ``slope`` has two
    columns used: ``basis`` is :func:`~mavispm.measure.stars.crlb.sky_plane_basis`);
    the weights are ``valid / (max(model, 0) + rn2)``; the parameters ``(x, y, flux,
    sky[, sky_x, sky_y])``, the Jacobian as :func:`~mavispm.measure.stars.crlb.jacobian`.

    Parameters
    ----------
    value, dvx, dvy : ndarray, shape (N, M)
        Unit-flux ePSF on the M stamp pixels and its position derivatives [1/pixel].
    data : ndarray, shape (N, M)
        Stamp pixels [electron].
    model_all, own : ndarray, shape (N, M)
        All stars' model on the stamp pixels, and this star's part of it [electron].
    valid : ndarray, shape (N, M)
        1 for pixels used, 0 for masked ones.
    flux, sky : ndarray, shape (N,)
        [electron], [electron / pixel].
    slope : ndarray, shape (N, 2) or None
        Sky slopes [electron / pixel^2]; None for a constant sky (4 parameters).
    basis : ndarray, shape (2, M)
        Pixel offsets of the stamp from its centre [pixel].
    rn2 : float
        Read-noise variance [electron^2].
    positions : bool
        False: the flux and sky rows only (``dvx``, ``dvy`` are not read and may be
        None); the position rows and columns of ``a`` and ``b`` are 0. The others are
        the same sums in the same order as with positions (bit-identical).

    Returns
    -------
    a : ndarray, shape (N, P, P)
        ``J W J^T``.
    b : ndarray, shape (N, P)
        ``J W r``.
    w, r : ndarray, shape (N, M)
        Weights [1/electron^2] and residuals [electron].
    """
    n, m = value.shape
    npar = 4 if slope is None else 6
    a = np.empty((n, npar, npar))
    b = np.empty((n, npar))
    w = np.empty((n, m))
    r = np.empty((n, m))
    f64 = np.float64
    value = np.ascontiguousarray(value, f64)
    if not positions:
        dvx = dvy = value  # not read
    _normal(
        value,
        np.ascontiguousarray(dvx, f64),
        np.ascontiguousarray(dvy, f64),
        np.ascontiguousarray(data, f64),
        np.ascontiguousarray(model_all, f64),
        np.ascontiguousarray(own, f64),
        np.ascontiguousarray(valid, f64),
        np.ascontiguousarray(flux, f64),
        np.ascontiguousarray(sky, f64),
        np.zeros((n, 2)) if slope is None else np.ascontiguousarray(slope, f64),
        np.ascontiguousarray(basis, f64),
        float(rn2),
        0 if positions else 2,
        a,
        b,
        w,
        r,
    )
    return a, b, w, r


@numba.njit(nogil=True, cache=True)
def _deposit_radial(
    pixels, shape, xs, ys, cxs, cys, radius, flux, profile, r_in, maps, nodes, w, out
):
    # maps (M, 2 half + 1, 2 half + 1): the modulation, mixed per star by the weights w
    # of its nodes (N, 4); half = 0 (one 1 x 1 map): none, every pixel's factor is 1
    ny, nx = shape
    r_out = r_in + len(profile) - 1
    half = (maps.shape[-1] - 1) // 2
    size = maps.shape[-1]
    # each star's nodes mixed once into g (a pixel then reads one map, not four: ~1e4
    # pixels per star on a crowded frame against (2 half + 1)^2 mixed values)
    g = np.empty((size, size))
    # where each frame row's pixels start in the sorted list: a star's row segment is
    # searched among that row's pixels only
    start = np.searchsorted(pixels, np.arange(ny + 1) * nx)
    for k in range(len(xs)):
        if half > 0:
            for u in range(size):
                for v in range(size):
                    g[u, v] = 0.0
            for a in range(4):
                if w[k, a] == 0.0:
                    continue
                m_a = maps[nodes[k, a]]
                for u in range(size):
                    for v in range(size):
                        g[u, v] += w[k, a] * m_a[u, v]
        row0 = max(0, int(np.floor(ys[k] - r_out)))
        row1 = min(ny - 1, int(np.ceil(ys[k] + r_out)))
        for row in range(row0, row1 + 1):
            dy = row - ys[k]
            if dy * dy >= r_out * r_out:
                continue
            span = np.sqrt(r_out * r_out - dy * dy)
            c0 = max(0, int(np.floor(xs[k] - span)))
            c1 = min(nx - 1, int(np.ceil(xs[k] + span)))
            s0, s1 = start[row], start[row + 1]
            lo = s0 + np.searchsorted(pixels[s0:s1], row * nx + c0)
            hi = s0 + np.searchsorted(pixels[s0:s1], row * nx + c1 + 1)
            own_row = abs(row - cys[k]) <= radius
            fy = dy + half
            jy = int(np.floor(fy))
            uy = fy - jy
            in_map = jy >= 0 and jy < 2 * half
            for q in range(lo, hi):
                col = pixels[q] - row * nx
                if own_row and abs(col - cxs[k]) <= radius:
                    continue
                dx = col - xs[k]
                r = np.sqrt(dx * dx + dy * dy)
                t = r - r_in
                if t < 0.0 or t >= len(profile) - 1:
                    continue
                i = int(t)
                f = t - i
                m = 1.0
                fx = dx + half
                jx = int(np.floor(fx))
                if in_map and jx >= 0 and jx < 2 * half:
                    ux = fx - jx
                    m = (1 - uy) * ((1 - ux) * g[jy, jx] + ux * g[jy, jx + 1]) + uy * (
                        (1 - ux) * g[jy + 1, jx] + ux * g[jy + 1, jx + 1]
                    )
                out[q] += flux[k] * m * (profile[i] * (1.0 - f) + profile[i + 1] * f)


def deposit_radial(
    pixels, shape, x, y, cx, cy, radius, flux, profile, r_in, out=None, modulation=None
):
    """Light of stars with a radial profile, on a sorted set of frame pixels.

    Each star adds ``flux * profile(r)`` (linear in ``r``, samples 1 pixel apart from
    ``r_in``, zero outside ``[r_in, r_in + len(profile) - 1)``) to the pixels of
    ``pixels`` at distance ``r`` from it, except those of its own
    ``(2 radius + 1)^2`` stamp centred on ``(cx, cy)``.

    Parameters
    ----------
    pixels : ndarray of int, shape (P,)
        Sorted flat frame indices (``row * nx + column``).
    shape : (ny, nx)
        Frame shape.
    x, y : ndarray, shape (N,)
        Star positions [pixel].
    cx, cy : ndarray of int, shape (N,)
        Their stamp centre pixels.
    radius : int
        Stamp half-width [pixel].
    flux : ndarray, shape (N,)
        Fluxes [electron].
    profile : ndarray, shape (L,)
        Light per unit flux per pixel [1/pixel] at ``r_in + 0, 1, ..., L - 1`` pixels.
    r_in : float
        Radius of the first sample [pixel].
    out : ndarray of float64, shape (P,), optional
        Added to in place (no new array: the fitter's model on 1e7 pixels).
    modulation : (maps, nodes, weights), optional
        A factor on each star's light (:mod:`~mavispm.measure.stars.halo_shape`): maps
        of shape (M, 2 h + 1, 2 h + 1) centred on the star (bilinear between pixels, 1
        beyond them), mixed by ``weights`` (N, 4) over the maps ``nodes`` (N, 4).

    Returns
    -------
    ndarray, shape (P,)
        The light on ``pixels`` [electron] (``out`` when given).
    """
    if out is None:
        out = np.zeros(len(pixels))
    if len(x) == 0 or len(profile) < 2:
        return out
    if pixels.dtype not in (np.int32, np.int64) or not pixels.flags.c_contiguous:
        pixels = np.ascontiguousarray(pixels, dtype=np.int64)
    if modulation is None:
        maps, nodes, weights = (
            np.ones((1, 1, 1)),
            np.zeros((len(x), 4), np.int64),
            np.zeros((len(x), 4)),
        )
    else:
        maps, nodes, weights = modulation
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    # stars in bands of rows, left to right: consecutive stars then add to the same
    # pixels while they are in the cache (the sums change only by rounding)
    order = np.lexsort((x, np.floor(y / 32.0)))
    _deposit_radial(
        pixels,
        (int(shape[0]), int(shape[1])),
        np.ascontiguousarray(x[order]),
        np.ascontiguousarray(y[order]),
        np.ascontiguousarray(np.asarray(cx)[order], dtype=np.int64),
        np.ascontiguousarray(np.asarray(cy)[order], dtype=np.int64),
        int(radius),
        np.ascontiguousarray(np.asarray(flux)[order], dtype=np.float64),
        np.ascontiguousarray(profile, dtype=np.float64),
        float(r_in),
        np.ascontiguousarray(maps, dtype=np.float64),
        np.ascontiguousarray(np.asarray(nodes)[order], dtype=np.int64),
        np.ascontiguousarray(np.asarray(weights)[order], dtype=np.float64),
        out,
    )
    return out
