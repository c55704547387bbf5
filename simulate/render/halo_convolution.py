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

import dataclasses
from pathlib import Path

import numba
import numpy as np

from mavispm.core.array_cache import content_key, load_arrays, save_arrays

__all__ = [
    "add_bilinear",
    "deposit_cic",
    "halo_field",
]


def deposit_cic(field: np.ndarray, x: np.ndarray, y: np.ndarray, weight: np.ndarray) -> None:
    """Add ``weight`` at sub-pixel positions (x, y) with cloud-in-cell weights (in place).

    Points whose 2x2 cell is partly outside ``field`` keep only the inside part. The
    four corner weights of every point are summed per cell by one ``np.bincount``
    (~15x faster than ``np.add.at``; sums differ from a point-by-point loop only by
    the order of the additions).

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
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    weight = np.asarray(weight, dtype=np.float64)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = x - x0
    fy = y - y0
    cells, amounts = [], []
    for oy, wy in ((0, 1 - fy), (1, fy)):
        for ox, wx in ((0, 1 - fx), (1, fx)):
            xi = x0 + ox
            yi = y0 + oy
            ok = (xi >= 0) & (xi < nx) & (yi >= 0) & (yi < ny)
            cells.append(yi[ok] * nx + xi[ok])
            amounts.append((weight * wx * wy)[ok])
    cell = np.concatenate(cells)
    if cell.size == 0:
        return
    lo = int(cell.min())
    sums = np.bincount(cell - lo, np.concatenate(amounts))
    flat = field.reshape(-1) if field.flags.c_contiguous else None
    if flat is not None:
        flat[lo : lo + sums.size] += sums
    else:  # a strided view: add through the 2-D index of every touched cell
        hit = np.flatnonzero(sums) + lo
        field[hit // nx, hit % nx] += sums[hit - lo]


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
    fill: float | None = None,
    cache_dir=None,
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
    fill : float, optional
        ``out`` holds nothing yet (e.g. ``np.empty``): it is set to ``fill`` plus the
        field, in one pass over the frame (the same values as filling it with ``fill``
        first and adding the field).
    cache_dir : path, optional
        Keep the transform of the halo kernel in this folder
        (``halospec-<key>.npz``, see :func:`_kernel_spectrum`).

    Returns
    -------
    ndarray (ny, nx) float64
        Halo light per detector pixel (flux units of ``flux``), plus ``fill``: ``out``
        when given.
    """
    ny, nx = shape
    if out is None:
        out = np.zeros(shape) if fill is None else np.empty(shape)
    b = int(max(downsample, 1))
    ncy, ncx = -(-ny // b), -(-nx // b)
    kspec, (hky, hkx), fshape = _kernel_spectrum(halo, pixel_scale * b, (ncy, ncx), cache_dir)
    # the kernel field, padded by the kernel half-size so that the frame never wraps, is
    # deposited straight into the transform's zero grid (transformed there in place)
    grid = np.zeros(fshape)
    padded = grid[: ncy + 2 * hky, : ncx + 2 * hkx]
    xc = (np.asarray(x_pix, dtype=float) + 0.5) / b - 0.5 + hkx
    yc = (np.asarray(y_pix, dtype=float) + 0.5) / b - 0.5 + hky
    deposit_cic(padded, xc, yc, np.asarray(flux, dtype=float))
    if not padded.any():
        if fill is not None:
            out.fill(fill)
        return out
    seeing = _convolve_spectrum(padded, kspec, fshape, grid=grid)
    coarse = np.ascontiguousarray(seeing[hky : hky + ncy, hkx : hkx + ncx])
    if b == 1:
        if fill is None:
            out += coarse
        else:
            np.add(coarse, fill, out=out)
        return out
    # detector pixel centres in coarse-pixel coordinates; flux density per detector pixel
    ylo, yfrac = _linear_interpolation_weights(ny, ncy, b)
    xlo, xfrac = _linear_interpolation_weights(nx, ncx, b)
    accumulate = fill is None
    _bilinear_into(
        out,
        coarse * (1.0 / b**2),
        ylo,
        yfrac,
        xlo,
        xfrac,
        0.0 if accumulate else fill,
        accumulate,
        np.empty((2, nx)),  # the kernel's work memory: it allocates nothing
    )
    return out


#: Version of the cached halo-kernel transforms (bump when their computation changes).
HALO_SPECTRUM_CACHE_VERSION = 1

#: Kernel transforms made or loaded in this process, by cache key (a few per scene).
_SPECTRA: dict[str, tuple] = {}


def _kernel_spectrum(halo, kernel_pixel_mas: float, coarse_shape, cache_dir=None):
    """The halo kernel's transform for a coarse frame of ``coarse_shape``.

    The kernel (``halo.kernel``: its profile interpolated on ~670 x 670 coarse
    pixels) and its transform cost ~0.03-0.04 s of every ``simulate frames``
    process; for a :class:`~mavispm.simulate.optics.seeing_halo.Halo` (a dataclass of
    arrays and numbers) they are a pure function of its fields, the coarse pixel and
    the frame shape, and are kept in ``cache_dir`` (the stamp plans' folder) and in
    this process. Other halo objects are transformed every time.

    Returns
    -------
    spectrum : ndarray complex128
        ``rfft2`` of the kernel wrapped around ``fshape`` (centre at [0, 0]).
    half : tuple of int
        The kernel's half-sizes (ky, kx).
    fshape : list of int
        Transform shape: the coarse frame padded by ``half`` on each side, rounded up
        to a fast length.
    """
    key = None
    if dataclasses.is_dataclass(halo) and not isinstance(halo, type):
        parts = [
            np.asarray(v) if isinstance(v, np.ndarray) else v
            for v in (getattr(halo, f.name) for f in dataclasses.fields(halo))
        ]
        key = content_key(
            HALO_SPECTRUM_CACHE_VERSION,
            type(halo).__name__,
            np.__version__,  # its pocketfft made the stored transform
            [float(kernel_pixel_mas), [int(n) for n in coarse_shape]],
            *parts,
        )
        if key in _SPECTRA:
            return _SPECTRA[key]
        path = None if cache_dir is None else Path(cache_dir) / f"halospec-{key}.npz"
        stored = load_arrays(path) if path is not None else None
        if stored is not None and set(stored) == {"spectrum", "half", "fshape"}:
            found = (
                stored["spectrum"],
                tuple(int(k) for k in stored["half"]),
                [int(n) for n in stored["fshape"]],
            )
            _SPECTRA[key] = found
            return found
    kernel = np.asarray(halo.kernel(kernel_pixel_mas), dtype=np.float64)
    ky, kx = kernel.shape[0] // 2, kernel.shape[1] // 2
    padded_shape = (coarse_shape[0] + 2 * ky, coarse_shape[1] + 2 * kx)
    fshape = [max(next_fast_len(n), 2 * k + 1) for n, k in zip(padded_shape, (ky, kx))]
    made = (np.fft.rfft2(_wrap_kernel(kernel, fshape)), (ky, kx), fshape)
    if key is not None:
        _SPECTRA[key] = made
        if cache_dir is not None:
            save_arrays(
                Path(cache_dir) / f"halospec-{key}.npz",
                {"spectrum": made[0], "half": np.array(made[1]), "fshape": np.array(fshape)},
            )
    return made


def _convolve_spectrum(
    field: np.ndarray, kernel_spectrum: np.ndarray, fshape, grid: np.ndarray | None = None
) -> np.ndarray:
    """:func:`_convolve_same` with the kernel's transform on ``fshape`` already made.

    The transforms of ``np.fft.rfft2`` / ``irfft2`` (the same one-axis passes in the same
    order, the same values bit for bit; tested) written into two buffers: the real grid
    and one spectrum, instead of a fresh array per pass (~35 -> ~23 MB of fresh memory at
    1200 x 1200).

    Parameters
    ----------
    field : ndarray (ny, nx)
        The field, at most ``fshape``.
    kernel_spectrum : ndarray complex128 (fshape[0], fshape[1] // 2 + 1)
        ``rfft2`` of the wrapped kernel.
    fshape : sequence of 2 int
        Transform shape.
    grid : ndarray float64 (fshape), C-contiguous, optional
        A zero grid whose top-left block is ``field`` (a view of it): transformed in
        place and overwritten by the convolution (default: a new one).

    Returns
    -------
    ndarray (ny, nx)
        The convolution's top-left block (a view of the grid).
    """
    fy, fx = (int(n) for n in fshape)
    if grid is None:
        grid = np.zeros((fy, fx))
        grid[: field.shape[0], : field.shape[1]] = field
    spec = np.empty((fy, fx // 2 + 1), dtype=np.complex128)
    np.fft.rfft(grid, axis=1, out=spec)
    np.fft.fft(spec, axis=0, out=spec)
    spec *= kernel_spectrum
    np.fft.ifft(spec, axis=0, out=spec)
    np.fft.irfft(spec, fx, axis=1, out=grid)
    return grid[: field.shape[0], : field.shape[1]]


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
    return _convolve_spectrum(field, np.fft.rfft2(_wrap_kernel(kernel, fshape)), fshape)


def _wrap_kernel(kernel: np.ndarray, fshape) -> np.ndarray:
    """``kernel`` on a zero grid of ``fshape`` with its centre at [0, 0], wrapped around.

    The four quadrants are copied into the corners: the values of
    ``np.roll(padded, (-ky, -kx), axis=(0, 1))`` without the full-grid copies of a roll.
    """
    ky, kx = kernel.shape[0] // 2, kernel.shape[1] // 2
    fy, fx = fshape
    wrapped = np.zeros(fshape)
    wrapped[: ky + 1, : kx + 1] = kernel[ky:, kx:]
    wrapped[: ky + 1, fx - kx :] = kernel[ky:, :kx]
    wrapped[fy - ky :, : kx + 1] = kernel[:ky, kx:]
    wrapped[fy - ky :, fx - kx :] = kernel[:ky, :kx]
    return wrapped


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


def add_bilinear(out, coarse, ylo, yfrac, xlo, xfrac) -> None:
    """``out[i, j] += `` the bilinear interpolation of ``coarse`` at (ylo + yfrac, xlo + xfrac).

    One pass over ``out`` in row order (no full-size temporary).

    Parameters
    ----------
    out : ndarray (ny, nx) float64, C-contiguous
        Fine grid, added into.
    coarse : ndarray
        Coarse grid.
    ylo, xlo : ndarray of int
        Lower coarse index per fine row / column.
    yfrac, xfrac : ndarray
        Fractional coarse offsets per fine row / column.
    """
    _bilinear_into(
        out,
        np.ascontiguousarray(coarse, dtype=np.float64),
        np.ascontiguousarray(ylo, dtype=np.int64),
        np.ascontiguousarray(yfrac, dtype=np.float64),
        np.ascontiguousarray(xlo, dtype=np.int64),
        np.ascontiguousarray(xfrac, dtype=np.float64),
        0.0,
        True,
        np.empty((2, out.shape[1])),
    )


@numba.njit(nogil=True, cache=True)
def _bilinear_into(
    out, coarse, ylo, yfrac, xlo, xfrac, base, accumulate, rows
) -> None:  # pragma: no cover
    """``out[i, j] (+)= `` the bilinear interpolation of ``coarse`` (``base +`` it: set).

    The interpolations along x of the two coarse rows bracketing a fine row are
    computed once per coarse row pair (``downsample`` fine rows share them), so the
    pass over ``out`` is a vectorised ``top + fy (bot - top)``; the arithmetic is
    the same, in the same order, as interpolating every pixel on its own.

    Parameters
    ----------
    out : ndarray (ny, nx) float64
        Fine grid.
    coarse : ndarray (ncy, ncx) float64
        Coarse grid.
    ylo, xlo : ndarray of int64
        Lower coarse index per fine row / column.
    yfrac, xfrac : ndarray of float64
        Fractional coarse offsets per fine row / column.
    base : float
        Set ``out = base + interpolation`` (when ``accumulate`` is False).
    accumulate : bool
        Add into ``out`` instead.
    rows : ndarray (2, nx) float64
        Work memory: the kernel allocates nothing (a cached kernel calling ``np.empty``
        makes numba import ``numba.np.arrayobj``, ~0.02-0.03 s of a process, when it
        loads).
    """
    ny, nx = out.shape
    ncy, ncx = coarse.shape
    top = rows[0]
    bot = rows[1]
    r_done = -1
    for i in range(ny):
        r0 = ylo[i]
        if r0 != r_done:
            r1 = min(r0 + 1, ncy - 1)
            for j in range(nx):
                c0 = xlo[j]
                c1 = min(c0 + 1, ncx - 1)
                fx = xfrac[j]
                top[j] = coarse[r0, c0] + fx * (coarse[r0, c1] - coarse[r0, c0])
                bot[j] = coarse[r1, c0] + fx * (coarse[r1, c1] - coarse[r1, c0])
            r_done = r0
        fy = yfrac[i]
        row = out[i]
        if accumulate:
            for j in range(nx):
                row[j] += top[j] + fy * (bot[j] - top[j])
        else:
            for j in range(nx):
                row[j] = base + (top[j] + fy * (bot[j] - top[j]))
