"""Split rendering: the outer PSF of every star by one FFT convolution per PSF-grid cell.

A star's image is ``F [sum_n w_n P_n] * K_C * box`` (bilinear mix of the PSF-grid nodes
``P_n``, tip-tilt/blur Gaussian ``K_C``, pixel box). Each node is split by a smooth radial
taper ``T`` (1 inside ``r_split / 2``, raised cosine to 0 at ``r_split``)::

    P_n = T P_n + (1 - T) P_n = inner_n + outer_n.

The inner parts are rendered on small exact stamps by the usual
:class:`~mavispm.simulate.render.stamps.StarRenderer` (their support ends at
``r_split``). The outer parts are added for all stars of one PSF-grid cell together:
each star is deposited as its own Gaussian ``F w_n K_C`` (exact covariance, exact
sub-pixel position) on a grid of half detector pixels, one deposit field per node of
the cell, and ``image = sum_n outer_n * box * deposit_n`` is one FFT convolution per
node, with one inverse transform per cell, sampled at the detector pixel centres.

Why this is exact (to the bound :meth:`OuterConvolver.alias_bound`): on a grid of
spacing ``g = s / 2`` the sampled Gaussian deposit and the sampled outer kernel convolve
to the continuous convolution except for aliases; these need a frequency ``f`` where
the kernel's transform is non-zero and ``1 - f`` (cycles per grid pixel) where the
Gaussian's is: ``exp(-2 pi^2 sigma^2 (1 - f)^2)``. MAVIS PSFs vanish beyond
``D / lambda ~ 0.26`` cycles per 3.75 mas grid pixel, so with a kernel of
``sigma >= 4.6 mas`` (the blur alone) the aliases are ~1e-7 of the star's outer light.
Stars whose bound exceeds the noise budget are rendered on full stamps instead.

The node transforms are exact DFTs of the (tapered) PSF samples at the grid's
frequencies (sub-lattice FFTs when the grid pixel is ``k >= 1`` PSF pixels).
"""

from __future__ import annotations

import numba
import numpy as np

from mavispm.simulate.render.halo_convolution import next_fast_len
from mavispm.simulate.render.pixel_response import pixel_transfer
from mavispm.simulate.render.symmetric2x2 import eigvals_2x2

__all__ = [
    "OuterConvolver",
    "deposit_gaussians",
    "radial_taper",
    "split_cube",
]

#: The deposit Gaussians are cut where they fall below exp(-cut**2 / 2): at most at
#: GAUSS_CUT, less (not below MIN_GAUSS_CUT) where the light left out is below the budget.
GAUSS_CUT = 7.0
MIN_GAUSS_CUT = 4.0


def radial_taper(r, r_split: float) -> np.ndarray:
    """1 inside ``r_split / 2``, a raised cosine to 0 at ``r_split``, 0 beyond.

    Parameters
    ----------
    r : array
        Radius [pixel].
    r_split : float
        Outer edge of the inner part [pixel].

    Returns
    -------
    numpy.ndarray
        The taper, in [0, 1].
    """
    r1 = 0.5 * r_split
    t = np.clip((np.asarray(r, float) - r1) / (r_split - r1), 0.0, 1.0)
    return 0.5 + 0.5 * np.cos(np.pi * t)


def split_cube(cube, psf_scale: float, pixel_scale: float, r_split: float):
    """Inner and outer parts of every PSF node (their sum is the node, exactly).

    Parameters
    ----------
    cube : ndarray (..., n, n)
        PSF nodes, optical axis at the central sample.
    psf_scale, pixel_scale : float
        PSF sample and detector pixel [mas].
    r_split : float
        Radius [detector pixel] where the inner part ends (see :func:`radial_taper`).

    Returns
    -------
    inner, outer : ndarray (..., n, n)
    """
    n = cube.shape[-1]
    c = (n - 1) / 2
    off = (np.arange(n) - c) * psf_scale / pixel_scale
    t = radial_taper(np.hypot(off[:, None], off[None, :]), r_split)
    inner = cube * t
    return inner, cube - inner


@numba.njit(nogil=True, cache=True)
def deposit_gaussians(
    fields, slot, weight, xg, yg, inv, norm, half, cut
) -> None:  # pragma: no cover
    """Add each star's Gaussian, times its node weights, into the node fields (in place).

    Parameters
    ----------
    fields : ndarray (T, Ly, Lx)
        One deposit field per node of the cell, added into.
    slot : ndarray (S, J) int
        Field of each of a star's node weights (-1: none).
    weight : ndarray (S, J)
        Flux times bilinear weight.
    xg, yg : ndarray (S,)
        Star positions [grid pixel].
    inv : ndarray (S, 3)
        ``(a, b, c)`` of the inverse covariance [grid pixel^-2].
    norm : ndarray (S,)
        ``1 / (2 pi sqrt(det C))`` [grid pixel^-2].
    half : ndarray (S,) int
        Half-size of each star's window [grid pixel].
    cut : ndarray (S,)
        Each Gaussian is kept inside the ellipse ``d^T C^-1 d < cut^2`` (about, with a
        margin of a sample per row); the kept samples are scaled to sum to 1, so every
        star keeps its flux exactly and the ``exp(-cut^2 / 2)`` left out is spread over
        the kept samples in proportion.
    """
    ly, lx = fields.shape[1], fields.shape[2]
    ex = np.empty(2 * half.max() + 1)
    buf = np.empty((2 * half.max() + 1, 2 * half.max() + 1))
    lo = np.zeros(2 * half.max() + 1, dtype=np.int64)
    hi = np.zeros(2 * half.max() + 1, dtype=np.int64)
    for s in range(xg.shape[0]):
        cx = int(np.floor(xg[s] + 0.5))
        cy = int(np.floor(yg[s] + 0.5))
        h = half[s]
        a, b, c = inv[s, 0], inv[s, 1], inv[s, 2]
        x_lo, x_hi = max(cx - h, 0), min(cx + h + 1, lx)
        if x_lo >= x_hi:
            continue
        dx0 = x_lo - xg[s]
        for i in range(x_hi - x_lo):  # exp(-a dx^2 / 2) of the window's columns
            dx = dx0 + i
            ex[i] = np.exp(-0.5 * a * dx * dx)
        geometric = abs(b) * (h + 1.0) ** 2 < 300.0  # no overflow of the running factor
        cut2 = cut[s] * cut[s]
        cond = c - b * b / a  # exponent of the row's peak: -cond dy^2 / 2
        y_lo, y_hi = max(cy - h, 0), min(cy + h + 1, ly)
        total = 0.0
        for r in range(y_hi - y_lo):  # pass 1: the samples, and their sum
            dy = y_lo + r - yg[s]
            lo[r] = 0
            hi[r] = 0
            # only the samples inside the star's cut ellipse (not the window's corners)
            room = cut2 - cond * dy * dy
            if room <= 0.0:
                continue
            mid = xg[s] - b * dy / a
            width = np.sqrt(room / a) + 1.0
            i0 = max(int(np.floor(mid - width)) - x_lo, 0)
            i1 = min(int(np.ceil(mid + width)) + 1 - x_lo, x_hi - x_lo)
            lo[r] = i0
            hi[r] = max(i1, i0)
            # exp(-b dx dy) along the row: a geometric sequence (no exp per sample)
            step = np.exp(-b * dy)
            cross = norm[s] * np.exp(-0.5 * c * dy * dy - b * (dx0 + i0) * dy)
            for i in range(i0, i1):
                if geometric:
                    g = ex[i] * cross
                    cross *= step
                else:
                    dx = dx0 + i
                    g = norm[s] * np.exp(-0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy))
                buf[r, i] = g
                total += g
        if total <= 0.0:
            continue
        scale = 1.0 / total  # the kept samples carry the whole flux (exact to round-off)
        for r in range(y_hi - y_lo):  # pass 2: add them to the node fields
            iy = y_lo + r
            for i in range(lo[r], hi[r]):
                g = buf[r, i] * scale
                for j in range(slot.shape[1]):
                    t = slot[s, j]
                    if t >= 0:
                        fields[t, iy, x_lo + i] += weight[s, j] * g


class OuterConvolver:
    """Adds the outer parts of many stars' PSFs to an image, one convolution per grid cell.

    Parameters
    ----------
    outer : ndarray (n_nodes, n, n)
        Outer parts of the PSF nodes (:func:`split_cube`), optical axis at the centre.
    psf_scale, pixel_scale : float
        PSF sample and detector pixel [mas]; ``pixel_scale / 2`` must be a whole number of
        PSF samples.
    intrapixel_amplitude : float
        Intra-pixel sensitivity dip (see ``pixel_response``).

    Raises
    ------
    ValueError
        When half a detector pixel is not a whole number of PSF samples.
    """

    def __init__(self, outer, psf_scale: float, pixel_scale: float, intrapixel_amplitude=0.0):
        k = 0.5 * pixel_scale / psf_scale
        if k < 1 - 1e-9 or abs(k - round(k)) > 1e-9 * k:
            raise ValueError(
                f"split rendering needs half a detector pixel ({0.5 * pixel_scale:g} mas) to be "
                f"a whole number of PSF samples ({psf_scale:g} mas)"
            )
        self.k = int(round(k))
        self.outer = np.asarray(outer, dtype=np.float64)
        self.pixel_scale = float(pixel_scale)
        self.grid = 0.5 * self.pixel_scale  # mas per grid pixel
        self.amplitude = float(intrapixel_amplitude)
        n = self.outer.shape[-1]
        self.radius = int(np.ceil((n - 1) / 2 / self.k))  # kernel half-size [grid pixel]
        self._tail = self._spectral_tail()

    def _spectral_tail(self):
        """Largest outer-node transform (per unit flux) at or beyond each frequency.

        Returns ``(f, tail)``: ``f`` in cycles per grid pixel, ``tail`` non-increasing.
        """
        n = self.outer.shape[-1]
        spec = np.abs(np.fft.rfft2(self.outer, axes=(1, 2))).max(axis=0)
        fy = np.fft.fftfreq(n) * self.k
        fx = np.fft.rfftfreq(n) * self.k
        fr = np.hypot(fy[:, None], fx[None, :]).ravel()
        order = np.argsort(fr)[::-1]
        tail = np.maximum.accumulate(spec.ravel()[order])[::-1]
        return fr[order][::-1], tail

    def alias_bound(self, cov_mas2) -> np.ndarray:
        """Estimate of the aliasing error of the outer part per unit flux, per star.

        A kernel frequency ``f`` (cycles per grid pixel, ``|f| = rho``) meets the
        Gaussian's alias nearest to it at a distance ``1 - rho`` (``rho <= 1/2``) or
        ``rho`` (the corners of the band), where the Gaussian's transform is
        ``exp(-2 pi^2 sigma^2 d^2)``; the estimate is the largest product of that and
        the outer-node transforms at or beyond ``rho``, times the 4 grid pixels of a
        detector pixel (``sigma``: the star's smallest kernel standard deviation).

        Parameters
        ----------
        cov_mas2 : ndarray (S, 2, 2)
            Kernel covariances [mas^2].

        Returns
        -------
        ndarray (S,)
        """
        lam = np.clip(eigvals_2x2(cov_mas2)[0], 0, None)
        s2 = lam / self.grid**2
        if len(s2) == 0:
            return s2
        f, tail = self._tail
        keep = f <= np.sqrt(0.5)  # the grid's band (corners included)
        f, tail = f[keep], tail[keep]
        step = max(1, len(f) // 512)
        f, tail = f[::step], tail[::step]
        d2 = np.where(f <= 0.5, 1.0 - f, f) ** 2
        # the estimate falls with sigma: tabulate it on a fine grid of sigma^2 and give each
        # star the value at the grid point at or below its own (an upper estimate; memory
        # and time independent of the number of stars)
        lo, hi = float(s2.min()), float(s2.max())
        grid = np.unique(np.concatenate([[lo], np.geomspace(max(lo, 1e-6), max(hi, 1e-6), 256)]))
        table = (np.exp(-2 * np.pi**2 * np.outer(grid, d2)) * tail[None, :]).max(axis=1)
        at = np.clip(np.searchsorted(grid, s2, side="right") - 1, 0, len(grid) - 1)
        return 4.0 * table[at]

    def kernel_transform(self, node: int, ly: int, lx: int, dtype=np.complex64):
        """rfft2 (ly, lx // 2 + 1) of node ``node``'s outer part times the pixel response.

        The exact DFT of the PSF samples at the grid frequencies (period ``ly`` x ``lx``
        grid pixels), the optical axis at grid pixel [0, 0].

        Parameters
        ----------
        node : int
            PSF-grid node (flat index).
        ly, lx : int
            Transform shape [grid pixel].
        dtype : numpy dtype
            ``complex64`` (float32 transforms) or ``complex128``.

        Returns
        -------
        ndarray (ly, lx // 2 + 1)
        """
        a = self.outer[node]
        k = self.k
        c = (a.shape[-1] - 1) // 2
        fy = np.fft.fftfreq(ly)
        fx = np.fft.rfftfreq(lx)
        import scipy.fft  # 4x faster than numpy's rfft2 here (numpy's column pass is strided)

        real = np.float32 if dtype == np.complex64 else np.float64
        out = np.zeros((ly, lx // 2 + 1), dtype=dtype)
        for ry in range(k):
            sub_y = a[ry::k]
            qy, fracy = divmod(ry - c, k)
            iy = (np.arange(sub_y.shape[0]) + qy) % ly
            for rx in range(k):
                sub = sub_y[:, rx::k]
                qx, fracx = divmod(rx - c, k)
                ix = (np.arange(sub.shape[1]) + qx) % lx
                # only the rows holding samples need the row transform
                rows = np.zeros((len(iy), lx), dtype=real)
                rows[:, ix] = sub
                spec = np.zeros((ly, lx // 2 + 1), dtype=dtype)
                spec[iy] = scipy.fft.rfft(rows, axis=1)
                spec = scipy.fft.fft(spec, axis=0, overwrite_x=True)
                if fracy or fracx:
                    spec *= np.exp(
                        (-2j * np.pi / k) * (fy[:, None] * fracy + fx[None, :] * fracx)
                    ).astype(dtype)
                out += spec
        s, g = self.pixel_scale, self.grid
        # the convolution is light per grid pixel: a detector pixel holds (s / g)^2 = 4 of them
        out *= (4.0 * pixel_transfer(fy / g, s, self.amplitude)[:, None]).astype(real)
        out *= pixel_transfer(fx / g, s, self.amplitude)[None, :].astype(real)
        return out

    def add(
        self, image, x_pix, y_pix, node, w, cov, flux, dtype="float32", threads=1, allowed=None
    ) -> None:
        """Add the outer parts of the stars to ``image`` (in place).

        Parameters
        ----------
        image : ndarray (ny, nx) float64
            Added into [flux units].
        x_pix, y_pix : ndarray (S,)
            Star positions [detector pixel, centres at integers].
        node : ndarray (S, J) int
            PSF nodes of each star (as the stamp renderer's bilinear weights).
        w : ndarray (S, J)
            Their weights.
        cov : ndarray (S, 2, 2)
            Kernel covariances [mas^2].
        flux : ndarray (S,)
            Fluxes.
        dtype : {"float32", "float64"}
            Precision of the deposits and transforms.
        threads : int
            Cells transformed at once (results do not depend on it).
        allowed : float, optional
            Error allowed per pixel [flux units] for cutting each deposit Gaussian short of
            ``GAUSS_CUT``: the light moved from its wing to its core, ``exp(-cut^2 / 2) F``,
            spread by the largest outer-kernel pixel, stays below it (cut at least
            ``MIN_GAUSS_CUT``; the flux is kept exactly). None: every Gaussian is cut at
            ``GAUSS_CUT``.
        """
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        import scipy.fft

        ny, nx = image.shape
        x_pix = np.asarray(x_pix, float)
        y_pix = np.asarray(y_pix, float)
        flux = np.asarray(flux, float)
        cov = np.asarray(cov, float)
        if len(flux) == 0:
            return
        cg = cov / self.grid**2
        det = cg[:, 0, 0] * cg[:, 1, 1] - cg[:, 0, 1] ** 2
        if np.any(det <= 0):
            raise ValueError("split rendering needs a positive definite kernel covariance")
        inv = np.stack([cg[:, 1, 1], -cg[:, 0, 1], cg[:, 0, 0]], axis=1) / det[:, None]
        norm = 1.0 / (2 * np.pi * np.sqrt(det))
        sig = np.sqrt(np.maximum(cg[:, 0, 0], cg[:, 1, 1]))
        cut = np.full(len(flux), GAUSS_CUT)
        if allowed is not None and allowed > 0:
            kmax = 4.0 * self.k**2 * float(self.outer.max())  # per unit flux, per pixel
            ratio = np.maximum(flux * kmax / allowed, 1.0)
            cut = np.clip(np.sqrt(2.0 * np.log(ratio)), MIN_GAUSS_CUT, GAUSS_CUT)
        half = np.ceil(cut * sig).astype(np.int64) + 1
        reach = (self.radius + half.max() + 2) / 2.0 + 1  # detector pixels
        near = (x_pix > -reach) & (x_pix < nx - 1 + reach) & (y_pix > -reach)
        near &= (y_pix < ny - 1 + reach) & (flux > 0)
        idx = np.flatnonzero(near)
        if not len(idx):
            return
        key = np.asarray(node)[idx, 0]
        groups = [idx[key == g] for g in np.unique(key)]
        pad = int(np.ceil(reach))
        # one transform size for all cells: the node transforms are shared
        spans = [
            (np.ceil(y_pix[g].max()) - np.floor(y_pix[g].min()), np.ceil(x_pix[g].max())
             - np.floor(x_pix[g].min())) for g in groups
        ]  # fmt: skip
        ly = _fast_multiple_of_4(int(2 * (max(s[0] for s in spans) + 2 * pad) + 2))
        lx = _fast_multiple_of_4(int(2 * (max(s[1] for s in spans) + 2 * pad) + 2))
        real = np.float32 if dtype == "float32" else np.float64
        cplx = np.complex64 if real is np.float32 else np.complex128
        last_use = {}
        nodes_of = []
        for i, g in enumerate(groups):
            ns = np.unique(np.asarray(node)[g][np.asarray(w)[g] > 0])
            nodes_of.append(ns)
            for n_ in ns:
                last_use[int(n_)] = i
        kernels: dict[int, np.ndarray] = {}

        def work(i):
            g, ns = groups[i], nodes_of[i]
            y0 = int(np.floor(y_pix[g].min())) - pad
            x0 = int(np.floor(x_pix[g].min())) - pad
            nd = np.asarray(node)[g]
            ww = np.asarray(w)[g]
            slot = np.minimum(np.searchsorted(ns, nd), len(ns) - 1)
            slot[(ns[slot] != nd) | (ww <= 0)] = -1
            fields = np.zeros((len(ns), ly, lx), dtype=real)
            deposit_gaussians(
                fields, slot, ww * flux[g][:, None], 2.0 * (x_pix[g] - x0),
                2.0 * (y_pix[g] - y0), inv[g], norm[g], half[g], cut[g],
            )  # fmt: skip
            spec = None
            for t, n_ in enumerate(ns):
                term = scipy.fft.rfft2(fields[t])
                term *= kernels[int(n_)]
                if spec is None:
                    spec = term
                else:
                    spec += term
            return y0, x0, _even_samples(spec, ly, lx)

        def add_done(item):
            i, fut = item
            y0, x0, block = fut.result()
            ya, yb = max(y0, 0), min(y0 + block.shape[0], ny)
            xa, xb = max(x0, 0), min(x0 + block.shape[1], nx)
            if ya < yb and xa < xb:
                image[ya:yb, xa:xb] += block[ya - y0 : yb - y0, xa - x0 : xb - x0]
            for n_ in list(kernels):
                if last_use[n_] <= i:
                    del kernels[n_]

        threads = max(int(threads), 1)
        with ThreadPoolExecutor(max_workers=threads) as pool:
            pending = deque()
            for i in range(len(groups)):
                for n_ in nodes_of[i]:
                    if int(n_) not in kernels:
                        kernels[int(n_)] = self.kernel_transform(int(n_), ly, lx, cplx)
                pending.append((i, pool.submit(work, i)))
                if len(pending) >= threads:
                    add_done(pending.popleft())
            while pending:
                add_done(pending.popleft())


def _fast_multiple_of_4(n: int) -> int:
    """Smallest multiple of 4 >= ``n`` with prime factors 2, 3, 5 (a fast FFT length)."""
    m = next_fast_len(n)
    while m % 4:
        m = next_fast_len(m + 1)
    return m


def _even_samples(spec, ly: int, lx: int):
    """``irfft2(spec, s=(ly, lx))[::2, ::2]`` by one transform of a quarter of the size.

    Sampling every second point folds the spectrum: ``Y(k) = X(k) + X(k + L/2)`` per
    axis (along x the upper half comes from the conjugate-symmetric lower half), and
    the inverse transform of length ``L/2`` carries a factor 2 per axis.

    Parameters
    ----------
    spec : ndarray (ly, lx // 2 + 1) complex
        rfft2 of a real ``ly x lx`` array (``ly``, ``lx`` multiples of 4).
    ly, lx : int
        Its shape.

    Returns
    -------
    ndarray (ly // 2, lx // 2)
    """
    import scipy.fft

    hy, hx = ly // 2, lx // 2
    yf = spec[:hy] + spec[hy:]  # (hy, lx // 2 + 1)
    flip = yf[(-np.arange(hy)) % hy]  # row -ky
    z = yf[:, : hx // 2 + 1] + np.conj(flip[:, hx - np.arange(hx // 2 + 1)])
    return scipy.fft.irfft2(z, s=(hy, hx)) * 0.25
