"""The seeing halo: light beyond the AO control radius, added by one FFT convolution.

As in MAVISIM (paper section 3.2): every star's flux is deposited in a "kernel
field" at its rendered position, and the kernel field is convolved once with the
halo kernel (the large central PSF with its core removed and ramped, summing to
the halo fraction), giving the "seeing field". The halo is smooth on the scale of
the control radius (~0.28"), so the convolution can run on pixels ``downsample``
times larger and be interpolated back to the detector grid.

The transforms are numpy's (pocketfft, as scipy's): importing ``scipy.fft`` cost
~0.3 s of every ``simulate frames`` process for a convolution of ~0.05 s.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "add_bilinear",
    "deposit_cic",
    "halo_field",
]


def deposit_cic(field: np.ndarray, x: np.ndarray, y: np.ndarray, weight: np.ndarray) -> None:
    """Add ``weight`` at sub-pixel positions (x, y) with cloud-in-cell weights (in place).

    Points whose 2x2 cell is partly outside ``field`` keep only the inside part.

    Parameters
    ----------
    field : ndarray (ny, nx)
        Grid added into.
    x, y : ndarray
        Positions [grid pixels].
    weight : ndarray
        Amount per point (any unit).
    """
    ny, nx = field.shape
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = x - x0
    fy = y - y0
    for oy, wy in ((0, 1 - fy), (1, fy)):
        for ox, wx in ((0, 1 - fx), (1, fx)):
            xi = x0 + ox
            yi = y0 + oy
            ok = (xi >= 0) & (xi < nx) & (yi >= 0) & (yi < ny)
            np.add.at(field, (yi[ok], xi[ok]), (weight * wx * wy)[ok])


def halo_field(
    x_pix,
    y_pix,
    flux,
    shape,
    halo,
    pixel_scale: float,
    downsample: int = 1,
    threads: int = 1,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """The seeing field of a set of stars on the detector grid.

    Parameters
    ----------
    x_pix, y_pix : ndarray (N,)
        Star positions in detector pixels (0-based centres).
    flux : ndarray (N,)
        Total star fluxes (the halo holds ``halo.fraction`` of each).
    shape : tuple (ny, nx)
        Detector frame shape.
    halo : object
        ``halo.kernel(pixel_scale_mas)`` -> centred 2-D kernel summing to the halo fraction.
    pixel_scale : float
        Detector pixel size, mas.
    downsample : int
        Convolve on pixels ``downsample`` times larger, then interpolate back.
    threads : int
        Accepted for compatibility: the (small, coarse-grid) transforms run on one
        thread.
    out : ndarray (ny, nx) float64, optional
        Add the field into this array (in place) instead of a new one.

    Returns
    -------
    ndarray (ny, nx) float64
        Halo light per detector pixel (flux units of ``flux``): ``out`` when given.
    """
    ny, nx = shape
    if out is None:
        out = np.zeros(shape)
    b = int(max(downsample, 1))
    kernel = np.asarray(halo.kernel(pixel_scale * b), dtype=np.float64)
    hky, hkx = kernel.shape[0] // 2, kernel.shape[1] // 2
    ncy, ncx = -(-ny // b), -(-nx // b)
    padded = np.zeros((ncy + 2 * hky, ncx + 2 * hkx))
    xc = (np.asarray(x_pix, dtype=float) + 0.5) / b - 0.5 + hkx
    yc = (np.asarray(y_pix, dtype=float) + 0.5) / b - 0.5 + hky
    deposit_cic(padded, xc, yc, np.asarray(flux, dtype=float))
    if not padded.any():
        return out
    # the kernel field is padded by the kernel half-size, so the frame never wraps
    seeing = _convolve_same(padded, kernel)
    coarse = np.ascontiguousarray(seeing[hky : hky + ncy, hkx : hkx + ncx])
    if b == 1:
        out += coarse
        return out
    # detector pixel centres in coarse-pixel coordinates; flux density per detector pixel
    ylo, yfrac = _linear_interpolation_weights(ny, ncy, b)
    xlo, xfrac = _linear_interpolation_weights(nx, ncx, b)
    add_bilinear(out, coarse * (1.0 / b**2), ylo, yfrac, xlo, xfrac)
    return out


def _convolve_same(field: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolution of ``field`` with an odd-sized centred ``kernel``, exact away from the rim.

    A circular convolution with the period of ``field`` (rounded up to a fast FFT
    length): output pixels at least the kernel's half-size from the field's edges
    equal those of ``scipy.signal.fftconvolve(field, kernel, mode="same")`` (the
    kernel never wraps for them); the rim, which the caller discards, wraps. This
    needs transforms ~2.5 times smaller than the linear convolution.
    """
    ky, kx = kernel.shape[0] // 2, kernel.shape[1] // 2
    fshape = [max(next_fast_len(n), 2 * k + 1) for n, k in zip(field.shape, (ky, kx))]
    wrapped = np.zeros(fshape)
    wrapped[: kernel.shape[0], : kernel.shape[1]] = kernel
    wrapped = np.roll(wrapped, (-ky, -kx), axis=(0, 1))  # kernel centre at [0, 0]
    spec = np.fft.rfft2(field, fshape)
    spec *= np.fft.rfft2(wrapped)
    conv = np.fft.irfft2(spec, fshape)
    return conv[: field.shape[0], : field.shape[1]]


def next_fast_len(n: int) -> int:
    """Smallest ``m >= n`` whose prime factors are 2, 3 and 5 (fast real FFT lengths).

    Same as ``scipy.fft.next_fast_len(n, real=True)`` (tested), without importing it.

    Parameters
    ----------
    n : int
        Minimum length (>= 1).

    Returns
    -------
    int
    """
    m = max(int(n), 1)
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def _linear_interpolation_weights(n_fine: int, n_coarse: int, b: int):
    """Lower coarse index and weight of the upper one for each fine pixel centre.

    Fine pixel ``i`` sits at coarse coordinate ``(i + 0.5) / b - 0.5``; beyond the
    outermost coarse centres the edge value is held (nearest).
    """
    pos = np.clip((np.arange(n_fine) + 0.5) / b - 0.5, 0.0, n_coarse - 1.0)
    lo = np.minimum(np.floor(pos).astype(np.int64), max(n_coarse - 2, 0))
    frac = pos - lo
    if n_coarse == 1:
        frac[:] = 0.0
    return lo, frac


@numba.njit(nogil=True, cache=True)
def add_bilinear(out, coarse, ylo, yfrac, xlo, xfrac) -> None:  # pragma: no cover
    """``out[i, j] += `` the bilinear interpolation of ``coarse`` at (ylo + yfrac, xlo + xfrac).

    One pass over ``out`` in row order (no full-size temporary).

    Parameters
    ----------
    out : ndarray (ny, nx)
        Fine grid, added into.
    coarse : ndarray
        Coarse grid.
    ylo, xlo : ndarray of int
        Lower coarse index per fine row / column.
    yfrac, xfrac : ndarray
        Fractional coarse offsets per fine row / column.
    """
    ny, nx = out.shape
    ncx = coarse.shape[1]
    ncy = coarse.shape[0]
    for i in range(ny):
        r0 = ylo[i]
        r1 = min(r0 + 1, ncy - 1)
        fy = yfrac[i]
        for j in range(nx):
            c0 = xlo[j]
            c1 = min(c0 + 1, ncx - 1)
            fx = xfrac[j]
            top = coarse[r0, c0] + fx * (coarse[r0, c1] - coarse[r0, c0])
            bot = coarse[r1, c0] + fx * (coarse[r1, c1] - coarse[r1, c0])
            out[i, j] += top + fy * (bot - top)
