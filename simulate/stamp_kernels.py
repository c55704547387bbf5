"""Compiled inner loop of the star renderer (numba), with the numpy path as reference.

Per star ``s`` and retained spectrum sample ``k`` the renderer multiplies the
interpolated PSF transfer function by the tip-tilt/blur Gaussian OTF and the
sub-pixel phase ramp::

    spec[s, k] *= exp(a_s u_k^2 + b_s u_k v_k + c_s v_k^2) * phx[s, col_k] * phy[s, row_k]

with ``(a, b, c) = -2 pi^2 (C_xx, 2 C_xy, C_yy)``. The numpy version needs three
temporaries of the size of ``spec``; the fused loop makes one pass (measured ~3x
faster for this step), releases the GIL for the renderer's threads, and is checked
against the numpy version in the tests.
"""

from __future__ import annotations

import numba
import numpy as np


def kernel_and_shift_numpy(spec, coef, u, v, phx, phy, col, row) -> None:
    """Reference implementation (in place). ``coef`` (S, 3) = (a, b, c) per star."""
    basis = np.stack([u * u, u * v, v * v]).astype(coef.dtype)
    quad = coef @ basis
    spec *= np.exp(quad, out=quad)
    spec *= phx[:, col]
    spec *= phy[:, row]


@numba.njit(nogil=True, cache=True)
def kernel_and_shift(spec, coef, u, v, phx, phy, col, row) -> None:  # pragma: no cover
    """Fused in-place version of :func:`kernel_and_shift_numpy` (numba)."""
    n_star, n_samp = spec.shape
    for s in range(n_star):
        a = coef[s, 0]
        b = coef[s, 1]
        c = coef[s, 2]
        for k in range(n_samp):
            uk = u[k]
            vk = v[k]
            g = np.exp(a * uk * uk + b * uk * vk + c * vk * vk)
            spec[s, k] = spec[s, k] * (g * phx[s, col[k]] * phy[s, row[k]])
