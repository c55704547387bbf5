"""Star-count normalisation: the model's tracer number inside the observed field.

The star-count term of the likelihood divides each star's surface density by

    N_field = int_field Sigma(R) c(R) dA

the tracer number (unit mass) inside the circular field of radius ``R_field``
about the *field* centre, weighted by the sample's completeness ``c(R)``. For a
model centre offset by ``d`` from the field centre, the fraction of the ring at
model radius ``R`` inside the field is ``arccos((R^2 + d^2 - R_field^2) / (2 R d)) / pi``
for ``|R_field - d| < R < R_field + d`` (1 inside, 0 outside). The radial integral
is 16-point Gauss-Legendre in ``ln R`` on pieces split where the integrand has kinks
(the completeness knots, ``R_field - d`` and ``R_field + d``); inside ``0.01 R_field``
the projected mass fraction is used. :func:`ln_field_number` is compiled (numba):
it runs on every likelihood call.
"""

from __future__ import annotations

import numba
import numpy as np

from mavispm.dynamics.star_sums import cubic_point_weights

__all__ = [
    "ln_field_number",
]

_GL16_T, _GL16_W = np.polynomial.legendre.leggauss(16)


@numba.njit(nogil=True, cache=True)
def _cubic(values, x0, step, q):  # pragma: no cover - compiled
    """4-point Lagrange interpolation of ``values`` on the uniform grid (clamped ends)."""
    j, w0, w1, w2, w3 = cubic_point_weights(q, x0, step, values.size)
    return w0 * values[j - 1] + w1 * values[j] + w2 * values[j + 1] + w3 * values[j + 2]


@numba.njit(nogil=True, cache=True)
def ln_field_number(
    x0, step, ln_sig, ln_proj, ln_a, offset, field_radius, comp_r, comp_c, gl_t, gl_w
):  # pragma: no cover - compiled
    """ln N_field (unit tracer mass) for a model centre offset from the field centre.

    Parameters
    ----------
    x0, step : float
        Start and step of the uniform ``ln X`` grid (``X = R / a``).
    ln_sig, ln_proj : ndarray
        ln surface density (unit mass, per a^2) and ln projected mass fraction on the grid.
    ln_a : float
        ln scale radius [ln arcsec].
    offset : float
        Model centre's distance from the field centre [arcsec] (clipped to half the field).
    field_radius : float
        Radius of the circular field [arcsec].
    comp_r, comp_c : ndarray
        Completeness table (radius [arcsec], value; linear interpolation, constant
        beyond the ends); empty arrays for a flat completeness.
    gl_t, gl_w : ndarray
        Gauss-Legendre nodes and weights on [-1, 1].
    """
    has_c = comp_r.size > 0
    if not has_c and offset <= 0.0:
        return _cubic(ln_proj, x0, step, np.log(field_radius) - ln_a)
    r_f = field_radius
    r_in = 0.01 * r_f
    d = min(offset, 0.5 * r_f)
    c_in = np.interp(r_in, comp_r, comp_c) if has_c else 1.0
    total = np.exp(_cubic(ln_proj, x0, step, np.log(r_in) - ln_a)) * c_in
    cuts = [r_in, r_f - d, r_f + d]
    if has_c:
        for r in comp_r:
            if r_in < r < r_f + d:
                cuts.append(r)
    cuts_arr = np.sort(np.array(cuts))
    acc = 0.0
    for p in range(cuts_arr.size - 1):
        lo, hi = np.log(cuts_arr[p]), np.log(cuts_arr[p + 1])
        if not hi > lo:
            continue
        half = 0.5 * (hi - lo)
        mid = 0.5 * (hi + lo)
        for k in range(gl_t.size):
            ln_r = mid + half * gl_t[k]
            r = np.exp(ln_r)
            f = np.exp(_cubic(ln_sig, x0, step, ln_r - ln_a) + 2.0 * (ln_r - ln_a))
            if has_c:
                f *= np.interp(r, comp_r, comp_c)
            if d > 0.0:
                cosang = (r * r + d * d - r_f * r_f) / (2.0 * r * d)
                f *= np.arccos(min(max(cosang, -1.0), 1.0)) / np.pi
            acc += f * gl_w[k] * half
    total += 2.0 * np.pi * acc
    return np.log(max(total, 1e-300))
