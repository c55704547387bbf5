"""Compiled inner loops of the star renderer (numba), with numpy paths as reference.

Per star ``s`` and retained spectrum sample ``k`` the renderer mixes the PSF-node
transfer functions with the star's bilinear weights, multiplies by the
tip-tilt/blur Gaussian OTF and the sub-pixel phase ramp, and folds (sums) the
sample onto its alias ``target[k]`` among the stamp's rfft2 frequencies::

    out[s, target[k]] += (sum_j w[s, j] T[node[s, j], k])
                         * exp(a_s u_k^2 + b_s u_k v_k + c_s v_k^2) * phx[s, col_k] * phy[s, row_k]

with ``(a, b, c) = -2 pi^2 (C_xx, 2 C_xy, C_yy)``. Along a run of samples in one row at
consecutive frequencies (``u_k = u_{k-1} + du``) the compiled pass updates the Gaussian
by a recurrence instead of an ``exp`` per sample (``exp`` was ~40 % of the pass; numba
has no vectorised ``exp`` here): with ``q(u) = a u^2 + b u v + c v^2``,
``g_k = g_{k-1} r_k`` and ``r_k = r_{k-1} exp(2 a du^2)``, ``r_k = exp(q(u_k) - q(u_{k-1}))``,
in float64 (relative error ~ n^2 1e-16 after n steps, below 1e-11 for the longest runs
of a 512-pixel stamp; the float32 ``exp`` of the float32 exponent it replaces was off by
up to ~1e-6). The numpy version needs a
sparse mixing product, three temporaries of the size of the batch spectrum and a
sparse folding product (whose transposed result made the inverse FFTs strided);
the fused loop makes one pass with no temporaries, writes the folded spectrum
C-contiguous, releases the GIL for the renderer's threads, and is checked against
the numpy version in the tests. :func:`add_stamps` adds the stamps to the image
(clipped at its edges) in one compiled pass. :func:`inverse_rfft2_into` makes the stamps
from the folded spectra.
"""

from __future__ import annotations

import threading

import numba
import numpy as np

__all__ = [
    "add_stamps",
    "binned_max",
    "inverse_rfft2_into",
    "mix_kernel_fold",
    "mix_kernel_fold_numpy",
    "wrap_2d_into",
]


def mix_kernel_fold_numpy(
    transforms, node, w, coef, u, v, du, step, phx, phy, col, row, target, out
):
    """Reference implementation (adds into ``out`` (S, n_out)). ``coef`` (S, 3) = (a, b, c).

    Every Gaussian factor is an ``exp`` of its own (``du`` and ``step`` are accepted for
    the compiled version's signature and not used).

    Parameters
    ----------
    transforms : ndarray, shape (n_nodes, K), complex
        PSF-node transfer functions at the retained spectrum samples.
    node : ndarray of int, shape (S, J)
        PSF nodes mixed for each star.
    w : ndarray, shape (S, J)
        The stars' bilinear node weights.
    coef : ndarray, shape (S, 3)
        ``(a, b, c)`` of each star's Gaussian OTF exponent.
    u, v : ndarray, shape (K,)
        Spatial frequencies of the samples (units matching ``coef``).
    du : float
        Frequency step between consecutive columns (units of ``u``).
    step : ndarray of bool, shape (K,)
        Sample ``k`` lies at ``u[k - 1] + du`` in the row of sample ``k - 1``.
    phx, phy : ndarray, shape (S, n_col), (S, n_row), complex
        Sub-pixel phase ramps along x and y.
    col, row : ndarray of int, shape (K,)
        Column and row of each sample in the phase ramps.
    target : ndarray of int, shape (K,)
        Index of each sample's alias among the stamp's rfft2 frequencies.
    out : ndarray, shape (S, n_out), complex
        Folded spectra, added into in place.
    """
    import scipy.sparse  # only the reference needs it (~0.03-0.2 s of every frames process)

    n_star = node.shape[0]
    indptr = np.arange(0, node.size + 1, node.shape[1])
    mix = scipy.sparse.csr_matrix(
        (w.ravel(), node.ravel(), indptr), shape=(n_star, transforms.shape[0])
    )
    spec = np.asarray(mix @ transforms)
    basis = np.stack([u * u, u * v, v * v]).astype(coef.dtype)
    quad = coef @ basis
    spec = spec * np.exp(quad) * phx[:, col] * phy[:, row]
    fold = scipy.sparse.csr_matrix(
        (np.ones(len(target)), (np.arange(len(target)), target)),
        shape=(len(target), out.shape[1]),
    )
    out += np.asarray((fold.T @ spec.T).T)


@numba.njit(nogil=True, cache=True, inline="always")
def _mix_nodes(transforms, nodes, weights, re, im):  # pragma: no cover
    """One star's node-weighted transfer function into split real / imaginary buffers.

    ``re + i im = sum_j weights[j] transforms[nodes[j]]`` at every sample (the mixing
    step of :func:`mix_kernel_fold` and :func:`mix_kernel_fold_runs`).
    """
    n_samp = transforms.shape[1]
    t0 = transforms[nodes[0]]
    w0 = weights[0]
    for k in range(n_samp):
        re[k] = t0[k].real * w0
        im[k] = t0[k].imag * w0
    for j in range(1, nodes.shape[0]):
        tj = transforms[nodes[j]]
        wj = weights[j]
        for k in range(n_samp):
            re[k] += tj[k].real * wj
            im[k] += tj[k].imag * wj


@numba.njit(nogil=True, cache=True, inline="always")
def _mix_four_nodes(transforms, nodes, weights, re, im):  # pragma: no cover
    """:func:`_mix_nodes` for four nodes (bilinear weights) in one pass over the buffers.

    The same sum in the same order (``((w0 t0 + w1 t1) + w2 t2) + w3 t3``), so the same
    values; four passes that each read and write ``re`` and ``im`` cost ~1.6x as much.
    """
    t0 = transforms[nodes[0]]
    t1 = transforms[nodes[1]]
    t2 = transforms[nodes[2]]
    t3 = transforms[nodes[3]]
    w0 = weights[0]
    w1 = weights[1]
    w2 = weights[2]
    w3 = weights[3]
    for k in range(transforms.shape[1]):
        re[k] = t0[k].real * w0 + t1[k].real * w1 + t2[k].real * w2 + t3[k].real * w3
        im[k] = t0[k].imag * w0 + t1[k].imag * w1 + t2[k].imag * w2 + t3[k].imag * w3


@numba.njit(nogil=True, cache=True)
def mix_kernel_fold(
    transforms, node, w, coef, u, v, du, step, phx, phy, col, row, target, out
):  # pragma: no cover
    """Fused version of :func:`mix_kernel_fold_numpy` (numba; adds into ``out``).

    Real arithmetic on split real/imaginary buffers (measured ~2x faster than
    numba's complex products); ``transforms`` must be C-contiguous.

    Parameters
    ----------
    transforms : ndarray, shape (n_nodes, K), complex
        PSF-node transfer functions at the retained spectrum samples.
    node : ndarray of int, shape (S, J)
        PSF nodes mixed for each star.
    w : ndarray, shape (S, J)
        The stars' bilinear node weights.
    coef : ndarray, shape (S, 3)
        ``(a, b, c)`` of each star's Gaussian OTF exponent.
    u, v : ndarray, shape (K,)
        Spatial frequencies of the samples (units matching ``coef``).
    du : float
        Frequency step between consecutive columns (units of ``u``).
    step : ndarray of bool, shape (K,)
        Sample ``k`` lies at ``u[k - 1] + du`` in the row of sample ``k - 1``: its
        Gaussian factor follows from the previous one by the recurrence.
    phx, phy : ndarray, shape (S, n_col), (S, n_row), complex
        Sub-pixel phase ramps along x and y.
    col, row : ndarray of int, shape (K,)
        Column and row of each sample in the phase ramps.
    target : ndarray of int, shape (K,)
        Index of each sample's alias among the stamp's rfft2 frequencies.
    out : ndarray, shape (S, n_out), complex
        Folded spectra, added into in place.
    """
    n_star = node.shape[0]
    n_samp = u.shape[0]
    re = np.empty(n_samp, dtype=u.dtype)
    im = np.empty(n_samp, dtype=u.dtype)
    for s in range(n_star):
        _mix_nodes(transforms, node[s], w[s], re, im)
        a = np.float64(coef[s, 0])
        b = np.float64(coef[s, 1])
        c = np.float64(coef[s, 2])
        kappa = np.exp(2.0 * a * du * du)
        px = phx[s]
        py = phy[s]
        o = out[s]
        g = 0.0  # the Gaussian at sample k and its ratio to sample k - 1 (float64)
        r = 0.0
        for k in range(n_samp):
            if step[k]:
                r *= kappa
                g *= r
            else:
                uk = np.float64(u[k])
                vk = np.float64(v[k])
                g = np.exp(a * uk * uk + b * uk * vk + c * vk * vk)
                r = np.exp(a * du * (2.0 * uk - du) + b * vk * du)
            p = px[col[k]]
            q = py[row[k]]
            pr = (p.real * q.real - p.imag * q.imag) * g
            pi = (p.real * q.imag + p.imag * q.real) * g
            o[target[k]] += complex(re[k] * pr - im[k] * pi, re[k] * pi + im[k] * pr)


@numba.njit(nogil=True, cache=True)
def add_stamps(image, stamps, x0, y0) -> None:  # pragma: no cover
    """Add ``stamps`` (S, m, m) into ``image`` at corners (x0, y0), clipped at the edges.

    Parameters
    ----------
    image : ndarray (ny, nx)
        Added into [electron].
    stamps : ndarray (S, m, m)
        Stamps [electron].
    x0, y0 : ndarray of int
        Lower-left corner of each stamp [pixel].
    """
    ny, nx = image.shape
    m = stamps.shape[1]
    for s in range(stamps.shape[0]):
        cx = x0[s]
        cy = y0[s]
        ya = max(cy, 0)
        yb = min(cy + m, ny)
        xa = max(cx, 0)
        xb = min(cx + m, nx)
        # row views: a unit-stride inner loop that LLVM vectorises (2.2 -> 0.8 ns per
        # pixel, measured; indexing image[yy, xx] in the inner loop was not)
        for yy in range(ya, yb):
            row = image[yy, xa:xb]
            src = stamps[s, yy - cy, xa - cx : xb - cx]
            for i in range(xb - xa):
                row[i] += src[i]


@numba.njit(nogil=True, cache=True)
def wrap_2d_into(a, period, out) -> None:  # pragma: no cover
    """``out[i, (y - c) % period, (x - c) % period] += a[i, y, x]``, ``c = (n - 1) // 2``.

    Wraps (sums) the last two axes of ``a`` (i, n, n) onto ``period`` x ``period``
    bins, the central sample at [0, 0], in one pass (``out`` zeroed by the caller).

    Parameters
    ----------
    a : ndarray (i, n, n)
        Samples to wrap.
    period : int
        Output period [samples].
    out : ndarray (i, period, period)
        Zeroed output, added into.
    """
    first = (-((a.shape[2] - 1) // 2)) % period
    for i in range(a.shape[0]):
        by = first
        for y in range(a.shape[1]):
            bx = first
            for x in range(a.shape[2]):
                out[i, by, bx] += a[i, y, x]
                bx += 1
                if bx == period:
                    bx = 0
            by += 1
            if by == period:
                by = 0


@numba.njit(nogil=True, cache=True)
def binned_max(values, bins, n_bins, out) -> None:  # pragma: no cover
    """``out[i, b] = max(values[i, p] for p with bins[p] == b)`` (``out`` pre-filled with 0).

    Parameters
    ----------
    values : ndarray (i, p)
        Values.
    bins : ndarray of int (p,)
        Bin of each column.
    n_bins : int
        Number of bins.
    out : ndarray (i, n_bins)
        Filled with 0 by the caller; receives the maxima.
    """
    for i in range(values.shape[0]):
        for p in range(values.shape[1]):
            b = bins[p]
            if values[i, p] > out[i, b]:
                out[i, b] = values[i, p]


@numba.njit(nogil=True, cache=True)
def mix_kernel_fold_runs(
    transforms, node, w, coef, fxu, fyv, du, phx, phy, runs, out, scratch
):  # pragma: no cover
    """:func:`mix_kernel_fold` over runs of samples: one row, consecutive columns.

    The same sum. Per star the nodes are mixed into split real / imaginary buffers (four
    nodes, the bilinear case, in one pass). Along a run, with ``q(u0 + i du) = q0 + i d1
    + i**2 d2``, the Gaussian is ``exp(q0 + i d1) * exp(i**2 d2)``: the first factor from
    ``rho = exp(d1)`` in 8 independent float64 chains (``rho**j`` for ``j < 8``, then
    times ``rho**8`` every 8 samples: a loop LLVM vectorises), the second from a per-star
    table (``d2 = a du**2`` is the same for every run). Relative error of a sample's
    Gaussian ~ ``(8 + n / 8) * 1e-16`` plus that of ``rho`` amplified ``i`` times (below
    ~1e-13 for the runs of a 512-pixel stamp); the previous one-step recurrence
    (``g_k = g_{k-1} r_k``, ``r_k = r_{k-1} exp(2 a du**2)``) was a chain of dependent
    multiplications, latency-bound at ~40 % of the pass. Where a run's exponent falls
    below -700 at an end, or ``exp(q0 + i d1)`` could overflow (``(n - 1)**2 |d2| >=
    600``; extreme kernels only), an exact ``exp`` per sample instead. One loop over the
    run then multiplies the mixed transform, the phase ramps and the Gaussian and adds
    into ``out`` (its (real, imaginary) pairs directly). The loops read every array at
    consecutive addresses through slices (non-negative indices, no wrap-around checks),
    so LLVM vectorises them. At 10,000 stars (one thread) the pass takes 0.212-0.213 s of CPU
    against 0.256-0.259 s before, with the same frame bit for bit (measured, load ~2.4).

    Parameters
    ----------
    transforms : ndarray, shape (n_nodes, K), complex
        PSF-node transfer functions at the retained spectrum samples, in run order.
    node, w, coef
        As in :func:`mix_kernel_fold`.
    fxu : ndarray, shape (n_col,)
        Frequency ``u`` of each phase-ramp column (units matching ``coef``).
    fyv : ndarray, shape (n_row,)
        Frequency ``v`` of each phase-ramp row.
    du : float
        Frequency step between consecutive columns.
    phx, phy : ndarray, shape (S, n_col), (S, n_row), complex
        Sub-pixel phase ramps along x and y.
    runs : ndarray of int, shape (R, 5)
        ``(row, first column, first sample, first target, length)`` of each run: sample
        ``k0 + i`` lies in phase-ramp row ``row`` and column ``c0 + i`` and folds onto
        target ``t0 + i``.
    out : ndarray, shape (S, 2 n_out), real
        Folded spectra as (real, imaginary) pairs (``complex_array.view(real)``),
        added into in place.
    scratch : tuple of 7 ndarrays
        The pass's work memory, :func:`mix_scratch`: the kernel allocates nothing (a
        cached kernel calling ``np.empty`` makes numba import ``numba.np.arrayobj``,
        ~0.02-0.03 s of a process, when it loads).
    """
    n_star = node.shape[0]
    n_col = fxu.shape[0]
    n_node = node.shape[1]
    longest = 1
    for r in range(runs.shape[0]):
        longest = max(longest, runs[r, 4])
    # lin: exp(q0 + i d1) along a run (float64); quad: exp(i**2 d2), d2 = a du**2, the
    # same for every run of a star (float64)
    re, im, col_re, col_im, gauss, lin, quad = scratch
    for s in range(n_star):
        if n_node == 4:  # bilinear weights: one pass instead of four over the buffers
            _mix_four_nodes(transforms, node[s], w[s], re, im)
        else:
            _mix_nodes(transforms, node[s], w[s], re, im)
        a = np.float64(coef[s, 0])
        b = np.float64(coef[s, 1])
        c = np.float64(coef[s, 2])
        px = phx[s]
        py = phy[s]
        d2 = a * du * du
        for i in range(longest):
            quad[i] = np.exp(d2 * np.float64(i * i))
        for q in range(n_col):
            col_re[q] = px[q].real
            col_im[q] = px[q].imag
        o = out[s]  # real view: (re, im) pairs
        for r in range(runs.shape[0]):
            row = runs[r, 0]
            c0 = runs[r, 1]
            k0 = runs[r, 2]
            g0 = runs[r, 3]
            n = runs[r, 4]
            vr = np.float64(fyv[row])
            qr = py[row].real
            qi = py[row].imag
            # the Gaussian along the run, q(u0 + i du) = q0 + i d1 + i**2 d2:
            # exp(q0 + i d1) exp(i**2 d2), the first factor from rho = exp(d1) in
            # independent chains of 8 (rho**j, then times rho**8 every 8 samples), the
            # second from the star's table. Its exponent is concave along the run,
            # smallest at an end: where an end's would underflow, or the first factor
            # could overflow ((n - 1)**2 |d2| >= 600), an exact exp per sample instead
            # (extreme kernels only)
            u0 = np.float64(fxu[c0])
            u1 = u0 + (n - 1) * du
            q0 = a * u0 * u0 + b * u0 * vr + c * vr * vr
            q1 = a * u1 * u1 + b * u1 * vr + c * vr * vr
            if min(q0, q1) > -700.0 and -d2 * (n - 1) * (n - 1) < 600.0:
                rho = np.exp(du * (2.0 * a * u0 + b * vr))
                lin[0] = np.exp(q0)
                for i in range(1, min(n, 8)):
                    lin[i] = lin[i - 1] * rho
                rho2 = rho * rho
                rho4 = rho2 * rho2
                rho8 = rho4 * rho4
                for i in range(8, n):  # dependence distance 8: vectorised
                    lin[i] = lin[i - 8] * rho8
                for i in range(n):
                    gauss[i] = lin[i] * quad[i]
            else:
                for i in range(n):
                    uk = u0 + i * du
                    gauss[i] = np.exp(a * uk * uk + b * uk * vr + c * vr * vr)
            # slices: unit-stride loops over non-negative indices (LLVM vectorises them)
            cre = col_re[c0 : c0 + n]
            cim = col_im[c0 : c0 + n]
            oo = o[2 * g0 : 2 * (g0 + n)]
            rek = re[k0 : k0 + n]
            imk = im[k0 : k0 + n]
            for i in range(n):
                # phase ramps x Gaussian, times the mixed transform
                fr = (cre[i] * qr - cim[i] * qi) * gauss[i]
                fi = (cre[i] * qi + cim[i] * qr) * gauss[i]
                oo[2 * i] += rek[i] * fr - imk[i] * fi
                oo[2 * i + 1] += rek[i] * fi + imk[i] * fr


def mix_scratch(transforms, fxu, runs, dtype) -> tuple:
    """The work memory of :func:`mix_kernel_fold_runs` for one layout of samples.

    Parameters
    ----------
    transforms : ndarray, shape (n_nodes, K)
        The node transforms (K samples).
    fxu : ndarray, shape (n_col,)
        The phase-ramp columns' frequencies.
    runs : ndarray of int, shape (R, 5)
        The runs (their longest length).
    dtype : numpy dtype
        The real precision of the weights ``w``.

    Returns
    -------
    tuple of 7 ndarrays
        ``(re, im, col_re, col_im, gauss, lin, quad)``.
    """
    longest = max(1, int(runs[:, 4].max())) if len(runs) else 1
    n_samp, n_col = transforms.shape[1], fxu.shape[0]
    return (
        np.empty(n_samp, dtype=dtype),
        np.empty(n_samp, dtype=dtype),
        np.empty(n_col, dtype=dtype),
        np.empty(n_col, dtype=dtype),
        np.empty(longest, dtype=dtype),
        np.empty(longest),
        np.empty(longest),
    )


def fold_runs(col, row, target, fx) -> np.ndarray:
    """Runs of samples for :func:`mix_kernel_fold_runs` (samples already in run order).

    A run continues while the row is the same and the column, its integer frequency
    and the target each advance by one.

    Parameters
    ----------
    col, row, target : ndarray of int, shape (K,)
        Phase-ramp column and row and folding target of each sample.
    fx : ndarray, shape (n_col,)
        Integer frequency of each phase-ramp column.

    Returns
    -------
    ndarray of int64, shape (R, 5)
        ``(row, first column, first sample, first target, length)`` per run.
    """
    col = np.asarray(col, dtype=np.int64)
    row = np.asarray(row, dtype=np.int64)
    target = np.asarray(target, dtype=np.int64)
    n = len(col)
    cont = np.zeros(n, dtype=bool)
    if n > 1:
        cont[1:] = (
            (row[1:] == row[:-1])
            & (col[1:] == col[:-1] + 1)
            & (target[1:] == target[:-1] + 1)
            & (np.asarray(fx)[col[1:]] == np.asarray(fx)[col[:-1]] + 1)
        )
    first = np.flatnonzero(~cont)
    length = np.diff(np.append(first, n))
    return np.stack([row[first], col[first], first, target[first], length], axis=1)


@numba.njit(nogil=True, cache=True)
def phase_ramps_into(shift, freq, df, out, powers) -> None:  # pragma: no cover
    """``out[s, i] = exp(-2 pi i df shift[s] freq[i])`` for integer frequencies ``freq``.

    Per star one ``cos`` / ``sin`` pair, then the powers ``z**f`` of
    ``z = exp(-2 pi i df shift)`` by a float64 recurrence (relative error ~ |f| 1e-16,
    below 1e-13 for a 512-pixel stamp) and their conjugates for negative ``f``:
    ~10x faster than ``numpy``'s ``cos`` and ``sin`` of every phase.

    Parameters
    ----------
    shift : ndarray (S,)
        Star offsets [mas].
    freq : ndarray of int (F,)
        Integer frequencies (units of ``df``), any order and sign.
    df : float
        Frequency step [cycles/mas].
    out : ndarray (S, F), complex
        Receives the phase ramps.
    powers : ndarray (2, >= max |freq| + 1) float64
        Work memory (the kernel allocates nothing; see :func:`mix_kernel_fold_runs`).
    """
    top = 0
    for i in range(freq.shape[0]):
        top = max(top, abs(freq[i]))
    pw_re = powers[0]
    pw_im = powers[1]
    for s in range(shift.shape[0]):
        angle = -2.0 * np.pi * df * shift[s]
        zr = np.cos(angle)
        zi = np.sin(angle)
        xr = 1.0
        xi = 0.0
        for f in range(top + 1):
            pw_re[f] = xr
            pw_im[f] = xi
            xr, xi = xr * zr - xi * zi, xr * zi + xi * zr
        o = out[s]
        for i in range(freq.shape[0]):
            f = freq[i]
            if f >= 0:
                o[i] = complex(pw_re[f], pw_im[f])
            else:
                o[i] = complex(pw_re[-f], -pw_im[-f])


#: ``numpy.fft`` functions take ``out`` (numpy >= 2.0).
_FFT_OUT = int(np.__version__.split(".")[0]) >= 2

_POCKETFFT_NAME = "scipy.fft._pocketfft.pypocketfft"
_pocketfft_module = None  # None: not looked up yet; False: not usable
_pocketfft_lock = threading.Lock()  # the renderer's threads: one lookup


def _load_pocketfft():
    """scipy's pocketfft extension module on its own, or None; checked against numpy.

    The extension module (``scipy.fft._pocketfft.pypocketfft``, only numpy needed) is
    loaded from its file without importing ``scipy`` or ``scipy.fft`` (whose imports cost
    ~0.3 s of a frames process) and without entering it in ``sys.modules`` (a later
    ``import scipy.fft`` loads its own as usual). Used only if its two passes give
    numpy's values, bit for bit, on a small batch in both precisions.
    """
    import importlib.machinery
    import importlib.util
    import sys
    from pathlib import Path

    module = sys.modules.get(_POCKETFFT_NAME)
    try:
        if module is None:
            spec = importlib.util.find_spec("scipy")
            if spec is None or not spec.submodule_search_locations:
                return None
            folder = Path(next(iter(spec.submodule_search_locations))) / "fft" / "_pocketfft"
            suffixes = importlib.machinery.EXTENSION_SUFFIXES
            path = next((folder / f"pypocketfft{x}" for x in suffixes
                         if (folder / f"pypocketfft{x}").is_file()), None)  # fmt: skip
            if path is None:
                return None
            loader = importlib.machinery.ExtensionFileLoader(_POCKETFFT_NAME, str(path))
            ext_spec = importlib.util.spec_from_file_location(_POCKETFFT_NAME, path, loader=loader)
            module = importlib.util.module_from_spec(ext_spec)
            loader.exec_module(module)
        phase = np.arange(3 * 10 * 6).reshape(3, 10, 6)
        for cplx in (np.complex64, np.complex128):
            spec = (np.cos(phase) + 1j * np.sin(0.7 * phase) * phase).astype(cplx)
            want = np.fft.irfft(np.fft.ifft(spec, axis=1), n=10, axis=2).astype(spec.real.dtype)
            got = np.empty_like(want)
            _pocketfft_passes(module, spec, got, 10)
            if not np.array_equal(got, want):
                return None
    except Exception:  # an unusual build or another signature: numpy's transforms
        return None
    return module


def _pocketfft_passes(module, spec, out, m) -> None:
    module.c2c(spec, axes=(1,), forward=False, inorm=2, out=spec, nthreads=1)
    module.c2r(spec, axes=(2,), lastsize=m, forward=False, inorm=2, out=out, nthreads=1)


def inverse_rfft2_into(spec, out, m: int) -> None:
    """``out[...] = numpy.fft.irfft2(spec, s=(m, m), axes=(1, 2))``, overwriting ``spec``.

    The two passes of the inverse real FFT (complex along axis 1 in place, then
    complex-to-real along axis 2 into ``out``) by scipy's pocketfft extension module
    when it gives numpy's values (see :func:`_load_pocketfft`): numpy's and scipy's
    pocketfft are the same transforms, but numpy runs the strided first pass one column
    at a time while scipy's runs several columns at once in SIMD lanes (32.6 -> 31.4 us
    per 112-pixel float32 stamp measured, the same bits). Otherwise numpy's (into
    ``out`` from numpy 2.0). One thread: the renderer's threads share the stamps.

    Parameters
    ----------
    spec : ndarray (S, m, m // 2 + 1), complex64 or complex128, C-contiguous
        Folded spectra (rfft2 layout); overwritten.
    out : ndarray (S, m, m), float32 or float64 (the same precision)
        Receives the stamps.
    m : int
        Stamp side.
    """
    global _pocketfft_module
    if _pocketfft_module is None:
        with _pocketfft_lock:
            if _pocketfft_module is None:
                _pocketfft_module = _load_pocketfft() or False
    if _pocketfft_module:
        _pocketfft_passes(_pocketfft_module, spec, out, m)
    elif _FFT_OUT:
        np.fft.ifft(spec, axis=1, out=spec)
        np.fft.irfft(spec, n=m, axis=2, out=out)
    else:
        out[...] = np.fft.irfft2(spec, s=(m, m), axes=(1, 2))
