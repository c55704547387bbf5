"""The seeing halo: light beyond the AO control radius, added by one FFT convolution.

As in MAVISIM (paper section 3.2): every star's flux is deposited in a "kernel
field" at its rendered position, and the kernel field is convolved once with the
halo kernel (the large central PSF with its core removed and ramped, summing to
the halo fraction), giving the "seeing field". The halo is smooth on the scale of
the control radius (~0.28"), so the convolution can run on pixels ``downsample``
times larger and be interpolated back to the detector grid.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.fft
import scipy.signal
import scipy.sparse


def deposit_cic(field: np.ndarray, x: np.ndarray, y: np.ndarray, weight: np.ndarray) -> None:
    """Add ``weight`` at sub-pixel positions (x, y) with cloud-in-cell weights (in place).

    Points whose 2x2 cell is partly outside ``field`` keep only the inside part.
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
    x_pix, y_pix, flux, shape, halo, pixel_scale: float, downsample: int = 1, threads: int = 1
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
        FFT worker threads (0: all cores).

    Returns
    -------
    ndarray (ny, nx) float64
        Halo light per detector pixel (flux units of ``flux``).
    """
    ny, nx = shape
    b = int(max(downsample, 1))
    kernel = np.asarray(halo.kernel(pixel_scale * b), dtype=np.float64)
    hky, hkx = kernel.shape[0] // 2, kernel.shape[1] // 2
    ncy, ncx = -(-ny // b), -(-nx // b)
    padded = np.zeros((ncy + 2 * hky, ncx + 2 * hkx))
    xc = (np.asarray(x_pix, dtype=float) + 0.5) / b - 0.5 + hkx
    yc = (np.asarray(y_pix, dtype=float) + 0.5) / b - 0.5 + hky
    deposit_cic(padded, xc, yc, np.asarray(flux, dtype=float))
    if not padded.any():
        return np.zeros(shape)
    with scipy.fft.set_workers(threads or os.cpu_count() or 1):
        seeing = scipy.signal.fftconvolve(padded, kernel, mode="same")
    coarse = seeing[hky : hky + ncy, hkx : hkx + ncx]
    if b == 1:
        return coarse
    # detector pixel centres in coarse-pixel coordinates; flux density per detector pixel
    rows = _linear_interpolation_matrix(ny, ncy, b)
    cols = _linear_interpolation_matrix(nx, ncx, b)
    fine = np.asarray(rows @ (cols @ coarse.T).T)
    fine *= 1.0 / b**2
    return fine


def _linear_interpolation_matrix(n_fine: int, n_coarse: int, b: int) -> scipy.sparse.csr_matrix:
    """Sparse (n_fine, n_coarse) linear interpolation from coarse to fine pixel centres.

    Fine pixel ``i`` sits at coarse coordinate ``(i + 0.5) / b - 0.5``; beyond the
    outermost coarse centres the edge value is held (nearest).
    """
    pos = np.clip((np.arange(n_fine) + 0.5) / b - 0.5, 0.0, n_coarse - 1.0)
    lo = np.minimum(np.floor(pos).astype(np.int64), max(n_coarse - 2, 0))
    frac = pos - lo
    hi = np.minimum(lo + 1, n_coarse - 1)
    data = np.concatenate([1.0 - frac, frac])
    rows = np.concatenate([np.arange(n_fine), np.arange(n_fine)])
    return scipy.sparse.csr_matrix(
        (data, (rows, np.concatenate([lo, hi]))), shape=(n_fine, n_coarse)
    )
