"""The star renderer: field-variable PSF x tip-tilt Gaussian, pixel-integrated, on stamps.

Each star's image is computed in the Fourier domain on a small periodic stamp of
``M x M`` detector pixels (``M`` even, chosen per star from its flux and the PSF
wing; see :func:`stamp_sizes`)::

    G(u) = [sum_n w_n P_n(u)]                     bilinear mix of the PSF-grid nodes
           * exp(-2 pi^2 u^T C u)                 tip-tilt + blur Gaussian, covariance C
           * sinc(u s_x) sinc(v s_y)              the detector pixel (box of side s)
           * exp(-2 pi i u . d)                   the exact sub-pixel position d

``P_n`` is the Fourier transform of PSF-grid node ``n`` at the stamp's frequencies
(an FFT of the finely sampled PSF wrapped onto the stamp period when that period
is a whole number of PSF pixels, a matrix DFT otherwise; both exact for a
band-limited PSF); it is computed once per node and stamp size and cached, and
bilinear interpolation in the field commutes with the transform. The pixel values
are the samples of the pixel-integrated image at the pixel centres; to get them
without aliasing, ``G`` is evaluated up to ``oversampling / (2 s)`` and folded
(summed over its aliases) onto the stamp's ``M x M`` frequencies before one
inverse real FFT. With an even ``oversampling`` >= 2 this is exact for any
optical PSF whose transfer function vanishes beyond ``1/s`` (MAVIS: D/lambda =
0.07 cycles/mas < 1/7.5 mas); ``oversampling = 1`` ignores aliasing (faster,
less accurate). Stars are batched by stamp size and transformed together.

The light of a star that falls beyond its stamp wraps around inside it, so every
stamp holds exactly the star's flux; the stamp is sized so that the wing at its
edge is below ``stamp_threshold`` times the per-pixel noise.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal

import numpy as np

from mavispm.core.array_cache import content_key, is_immutable, load_arrays, save_arrays
from mavispm.core.cores import usable_cores
from mavispm.simulate.render.pixel_response import pixel_transfer
from mavispm.simulate.render.stamp_kernels import (
    add_stamps,
    binned_max,
    fold_runs,
    inverse_rfft2_into,
    mix_kernel_fold_runs,
    mix_scratch,
    phase_ramps_into,
    wrap_2d_into,
)
from mavispm.simulate.render.symmetric2x2 import eigvals_2x2
from mavispm.simulate.render.thread_count import frame_threads

__all__ = [
    "FLOAT32_ROUNDOFF",
    "PLAN_CACHE_VERSION",
    "PLAN_FLOOR_DECADES",
    "RenderParams",
    "STAMP_CENTRE_BIAS",
    "STAMP_SIZES",
    "StampPlan",
    "StarRenderer",
    "stamp_centre",
]

#: Round-off of a float32 stamp relative to its flux (measured: ~1e-7 of the peak).
FLOAT32_ROUNDOFF = 3e-8

#: A stamp plan keeps spectrum samples this many decades below ``spectrum_floor``,
#: for the lower floors of bright-star batches.
PLAN_FLOOR_DECADES = 4

#: Stamp centres round positions up from this far below a half pixel (see stamp_centre).
STAMP_CENTRE_BIAS = 1e-7

#: Folded spectra of this many bytes go through the mixing pass and the inverse FFTs
#: together (a few stars: with their stamps they stay in a core's 2 MB L2 cache between the
#: two passes; 128 KB - 2 MB measured within the load's noise, 256 KB the steadiest).
STAMP_CHUNK_BYTES = 1 << 18

#: Kernel sigmas are rounded up to a multiple of this [pixel] when the wing envelope is
#: blurred to size the stamps (see ``StarRenderer._blurred_envelope``).
BLUR_SIGMA_STEP = 0.125

#: Version of the wing envelope (part of its disk-cache file name; 2: square radii).
ENVELOPE_VERSION = 2

#: Version of the stamp-plan computation (part of the disk-cache key).
PLAN_CACHE_VERSION = 2

#: Even stamp sizes with prime factors 2, 3, 5, 7 (fast FFTs), about 15-25 % apart, and
#: 7-13 % apart from 112 to 160 px, where the stars of the default optics land (a PSF
#: tapered at ~0.46" needs ~130 px: 144 instead of 160 px is 19 % fewer pixels).
STAMP_SIZES = (8, 12, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 112, 120, 128, 144, 160)
STAMP_SIZES += (192, 224, 256)
STAMP_SIZES += (320, 384, 448, 512)


@dataclass(frozen=True)
class RenderParams:
    """Accuracy / speed knobs of the renderer in one place (TOML table ``[render]``).

    In the spirit of GalSim's ``GSParams``: every trade of run time against error
    is made here.

    Parameters
    ----------
    oversampling : int
        Frequency oversampling of the stamp spectra before folding (1 = no alias
        correction, fastest; 2 = exact for MAVIS PSFs at 7.5 mas, default).
    stamp_threshold : float
        A star's stamp extends until its PSF wing falls below this fraction of the
        per-pixel noise sigma of the stack (default 0.05).
    min_stamp, max_stamp : int
        Bounds on the stamp side in pixels (``max_stamp = 0``: from the PSF-grid
        extent plus the tip-tilt kernel, beyond which the core PSF has no light).
    halo : bool
        Render the seeing halo (the light beyond the AO control radius) when the
        optics provides one.
    halo_downsample : int
        The halo convolution runs on pixels this many times larger and is
        interpolated back (0 = automatic: about 8 pixels per AO control radius).
    psf_interpolation : {"bilinear", "nearest"}
        How the PSF grid is interpolated to a star's position.
    dtype : {"float32", "float64"}
        Precision of the spectra and stamps (float32, the default, halves memory and
        time at ~1e-6 relative error).
    batch_size : int
        Most stars of one stamp size evaluated to one spectrum floor and precision (those
        of the brightest). A batch is rendered band by band, each chunk of stamps added
        to the image as soon as it is transformed: larger batches add more stamps to the
        same image rows in turn (4096: 0.88 s CPU for a 10,000-star frame on one thread,
        512: 1.03 s); memory ~100 bytes per star plus one copy of the node transforms.
    spectrum_floor : float
        Spectrum samples where every PSF node's transfer function, times the
        narrowest tip-tilt/blur kernel of the batch, is below this fraction of the
        total are dropped (the OTF vanishes beyond D/lambda; default 1e-5).
    threads : int
        Threads for stamp batches and the noise draw (0: automatic, one thread for
        frames of fewer than 20,000 stars and all cores from there:
        :mod:`~mavispm.simulate.render.thread_count`). Results do not depend on it.
    gaussian_skew_limit : float
        Photon + read noise of the stack is drawn as a Gaussian with the exact mean
        and variance where its skewness is below this value, and exactly
        (Poisson + Gaussian) where it reaches ``poisson_skew_limit`` (0 = always
        exact, slower).
    poisson_skew_limit : float
        Between ``gaussian_skew_limit`` and this skewness the stack noise is a
        skew-corrected Gaussian (exact mean and variance, skewness to ``O(g**3)``,
        see ``detector.skewed_normal``); from it up, exact Poisson + Gaussian. The
        largest skewness of the default MAVIS stack (120 x 30 s, 3 e- read noise)
        is 0.012, so the default 0.1 draws no Poisson variates there. With
        ``gaussian_skew_limit = 0`` every pixel is drawn exactly.
    outer_convolution : {"auto", "on", "off"}
        Split rendering (``simulate/render/outer_convolution.py``): each star's PSF
        inside ``split_radius`` on a small exact stamp, the rest for all stars of a
        PSF-grid cell by one FFT convolution per node. Stars whose aliasing bound
        exceeds a tenth of ``stamp_threshold`` x the noise keep full stamps. ``auto``
        splits when at least ``split_min_stars`` stars qualify (the convolutions cost a
        few seconds per frame, the full stamps ~0.5 ms per star).
    split_radius : float
        Radius [pixel] where the inner part ends (raised-cosine taper from half of it).
    split_min_stars : int
        Stars needed for ``outer_convolution = "auto"`` to split.
    """

    oversampling: int = 2
    stamp_threshold: float = 0.05
    min_stamp: int = 16
    max_stamp: int = 0
    halo: bool = True
    halo_downsample: int = 0
    psf_interpolation: Literal["bilinear", "nearest"] = "bilinear"
    dtype: Literal["float64", "float32"] = "float32"
    batch_size: int = 4096
    spectrum_floor: float = 1e-5
    gaussian_skew_limit: float = 0.01
    poisson_skew_limit: float = 0.1
    threads: int = 0
    outer_convolution: Literal["auto", "on", "off"] = "auto"
    split_radius: float = 8.0
    split_min_stars: int = 50000

    def __post_init__(self):
        if self.oversampling < 1:
            raise ValueError(f"render.oversampling must be >= 1, got {self.oversampling}")
        if not self.stamp_threshold > 0:
            raise ValueError(f"render.stamp_threshold must be > 0, got {self.stamp_threshold}")
        if self.min_stamp < 2 or self.min_stamp % 2:
            raise ValueError(f"render.min_stamp must be even and >= 2, got {self.min_stamp}")
        if self.max_stamp and (self.max_stamp < self.min_stamp or self.max_stamp % 2):
            raise ValueError("render.max_stamp must be 0 or an even number >= render.min_stamp")
        if self.halo_downsample < 0:
            raise ValueError("render.halo_downsample must be >= 0")
        if not 0 <= self.spectrum_floor < 1:
            raise ValueError("render.spectrum_floor must be in [0, 1)")
        if self.gaussian_skew_limit < 0:
            raise ValueError("render.gaussian_skew_limit must be >= 0")
        if self.poisson_skew_limit < 0:
            raise ValueError("render.poisson_skew_limit must be >= 0")
        if self.threads < 0:
            raise ValueError("render.threads must be >= 0 (0: automatic)")
        if self.batch_size < 1:
            raise ValueError("render.batch_size must be >= 1")
        if self.outer_convolution not in ("auto", "on", "off"):
            raise ValueError(
                f"render.outer_convolution must be auto, on or off, got {self.outer_convolution!r}"
            )
        if not self.split_radius >= 2:
            raise ValueError(f"render.split_radius must be >= 2 pixels, got {self.split_radius}")
        if self.split_min_stars < 0:
            raise ValueError("render.split_min_stars must be >= 0")


@dataclass
class StampPlan:
    """Everything about one stamp size that does not depend on the star (cached).

    Parameters
    ----------
    m : int
        Stamp side (pixels).
    u, v : ndarray (nsup,)
        Spatial frequencies (cycles/mas) of the retained spectrum samples: those
        where some PSF node's transfer function exceeds the plan floor.
    col, row : ndarray (nsup,) int
        Their column/row in the separable frequency axes ``fx``/``fy``.
    fx, fy : ndarray
        Integer frequency axes (see :func:`_folding_frequencies`).
    transforms : ndarray (n_nodes, nsup) complex
        Node transforms times the pixel transfer function at the retained samples.
    peak : ndarray (nsup,)
        Largest node transfer-function modulus at each retained sample (relative to 1).
    target : ndarray (nsup,) int
        Index of each sample's alias among the stamp's flattened rfft2
        frequencies ``(m, m//2+1)``: folding sums the samples onto it.
    """

    m: int
    u: np.ndarray
    v: np.ndarray
    col: np.ndarray
    row: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    transforms: np.ndarray
    peak: np.ndarray
    target: np.ndarray


def _stamp_size_at_least(n: int, floor: int) -> int:
    """Smallest tabulated stamp size >= max(n, floor) (or the next even number)."""
    n = max(int(np.ceil(n)), floor)
    for size in STAMP_SIZES:
        if size >= n:
            return size
    return n + (n % 2)


def _stamp_sizes_at_least(n, floor: int) -> np.ndarray:
    """:func:`_stamp_size_at_least` of every element of ``n`` (vectorised; the same sizes)."""
    need = np.maximum(np.ceil(np.asarray(n, dtype=float)), floor).astype(np.int64)
    table = np.asarray(STAMP_SIZES, dtype=np.int64)
    pos = np.searchsorted(table, need, side="left")
    beyond = need + need % 2
    return np.where(pos < len(table), table[np.minimum(pos, len(table) - 1)], beyond)


def _folding_frequencies(m: int, k: int):
    """Integer frequencies (units of 1/(m s)) evaluated for a stamp of side ``m``.

    Returns
    -------
    fy : ndarray (k*m,)
        Row frequencies in FFT order of a length ``k*m`` transform; folding is
        ``reshape(k, m).sum(0)``.
    fx : ndarray (k*(m//2+1),)
        Column frequencies ``c + j m`` (fft order of length ``k*m``) for output rfft
        columns ``c = 0..m/2``, laid out ``(k, m//2+1)``; folding sums over ``k``.
    """
    n = k * m
    fy = np.fft.fftfreq(n, 1.0 / n)
    cols = np.arange(m // 2 + 1)
    idx = (cols[None, :] + m * np.arange(k)[:, None]).ravel()
    fx = np.where(idx < n / 2, idx, idx - n).astype(float)
    return fy, fx


class StarRenderer:
    """Renders point sources through a PSF grid onto a detector image.

    Parameters
    ----------
    psf_grid : object
        The optics PSF grid: ``cube`` (n_nodes_y, n_nodes_x, n, n) each summing to 1
        with the optical axis at the central pixel, ``pixel_scale`` (mas per PSF pixel),
        ``bilinear_weights(x, y) -> (iy, ix, w)`` for positions in arcsec.
    pixel_scale : float
        Detector pixel size, mas.
    params : RenderParams
    cache_dir : path, optional
        Folder where the stamp plans (node transforms) are also kept on disk, keyed by
        the PSF cube, the pixel scales and the knobs they depend on, so that other
        processes rendering the same scene (e.g. the other epochs of a workflow)
        load them instead of recomputing them. None: in memory only.
    intrapixel_amplitude : float
        Intra-pixel sensitivity dip (see ``pixel_response``).
    slice_cubes : array (K, n_nodes_y, n_nodes_x, n, n), optional
        Monochromatic grids at ``K`` wavelengths across the band, sampled like
        ``psf_grid`` (which then only gives the node positions). Each batch of stars is
        drawn with the broadband kernel ``sum_k w_k P_k(r - s_k)`` of its spectrum
        (weights ``w_k``, shifts ``s_k``; see :mod:`mavispm.simulate.optics.broadband`),
        mixed from the slice transforms at the stamp frequencies.

    Notes
    -----
    Node transforms are cached per stamp size on the instance: reuse one renderer
    for all epochs of a scene (or give every renderer the same ``cache_dir``).
    """

    def __init__(
        self,
        psf_grid,
        pixel_scale: float,
        params: RenderParams | None = None,
        cache_dir=None,
        intrapixel_amplitude: float = 0.0,
        slice_cubes=None,
    ):
        self.psf_grid = psf_grid
        self.pixel_scale = float(pixel_scale)
        self.intrapixel_amplitude = float(intrapixel_amplitude)
        self.params = params or RenderParams()
        cube = np.asarray(psf_grid.cube, dtype=np.float64)
        if cube.ndim != 4 or cube.shape[2] != cube.shape[3] or cube.shape[2] % 2 == 0:
            raise ValueError(
                f"PSF grid cube must have shape (ny, nx, n, n) with n odd, got {cube.shape}"
            )
        self.n_nodes_y, self.n_nodes_x, n, _ = cube.shape
        self.n_slices = 1
        if slice_cubes is not None:
            slices = np.asarray(slice_cubes, dtype=np.float64)
            if slices.ndim != 5 or slices.shape[1:] != cube.shape:
                raise ValueError(
                    f"slice cubes must have shape (K, {', '.join(map(str, cube.shape))}), "
                    f"got {slices.shape}"
                )
            self.n_slices = len(slices)
            cube = slices
        self._cube = cube.reshape(-1, n, n)
        self.psf_pixel_scale = float(_value(psf_grid.pixel_scale, "mas"))
        self._plans: dict[int, StampPlan] = {}
        self._typed: dict[tuple, tuple] = {}  # (m, dtype) -> (plan, columns, their copy)
        self._split = None  # (inner renderer, OuterConvolver), built on first split render
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self._cache_key = None
        if self.cache_dir is not None:
            p = self.params
            # a cube mapped read-only from a keyed cache file (the tapered cube of
            # ``optics.model.cached_taper``) is keyed by that key, not hashed (~0.05 s)
            known = getattr(psf_grid, "cube_key", None) if slice_cubes is None else None
            if known is not None and not is_immutable(psf_grid.cube):
                known = None  # a key of the content only while it cannot be written
            content = self._cube
            if known is not None:
                content = {
                    "provenance": known,
                    "shape": list(content.shape),
                    "dtype": content.dtype.str,
                }
            self._cache_key = content_key(
                PLAN_CACHE_VERSION,
                [
                    self.psf_pixel_scale,
                    self.pixel_scale,
                    p.oversampling,
                    p.spectrum_floor,
                    PLAN_FLOOR_DECADES,
                ]
                + ([self.intrapixel_amplitude] if self.intrapixel_amplitude else []),
                content,
            )
        radii, env = self._cached_envelope()
        # a star's wing is at most the widest of its slices
        self._envelope = radii, env.reshape(self.n_slices, -1, env.shape[-1]).max(axis=0)
        self._blurred: dict[int, tuple] = {}  # blur step -> blurred envelope

    def _cached_envelope(self):
        """:func:`_wing_envelope` of the cube, kept in ``cache_dir`` next to the stamp plans."""
        path = None
        if self.cache_dir is not None:
            path = self.cache_dir / f"stampenv{ENVELOPE_VERSION}-{self._cache_key}.npz"
            stored = load_arrays(path)
            if stored is not None and set(stored) == {"radii", "env"}:
                return np.asarray(stored["radii"]), np.asarray(stored["env"])
        radii, env = _wing_envelope(self._cube, self.psf_pixel_scale, self.pixel_scale)
        if path is not None:
            save_arrays(path, {"radii": radii, "env": env})
        return radii, env

    # ------------------------------------------------------------------ sizes
    @property
    def psf_extent_pixels(self) -> float:
        """Side of the PSF-grid stamps in detector pixels."""
        return self._cube.shape[-1] * self.psf_pixel_scale / self.pixel_scale

    def max_stamp(self, max_sigma_mas: float = 0.0) -> int:
        """Largest stamp side needed: the PSF extent plus the kernel, in pixels.

        Parameters
        ----------
        max_sigma_mas : float
            Largest tip-tilt/blur kernel sigma [mas].

        Returns
        -------
        int
            Stamp side [pixel].
        """
        if self.params.max_stamp:
            return self.params.max_stamp
        need = self.psf_extent_pixels + 2 * (5 * max_sigma_mas / self.pixel_scale + 1)
        return _stamp_size_at_least(need, self.params.min_stamp)

    def stamp_sizes(
        self, flux, noise_sigma: float, sigma_mas, x_field=None, y_field=None
    ) -> np.ndarray:
        """Stamp side per star: where the wing falls below ``stamp_threshold * noise_sigma``.

        Parameters
        ----------
        flux : ndarray (N,)
            Star fluxes, in the units of ``noise_sigma``.
        noise_sigma : float
            Per-pixel noise sigma of the frame (same units); <= 0 gives maximal stamps.
        sigma_mas : ndarray (N,)
            Largest standard deviation of each star's kernel (mas).
        x_field, y_field : ndarray (N,), optional
            Field positions (arcsec): the wing envelope is then the largest of the
            star's interpolation nodes, otherwise of all nodes.
        """
        flux = np.asarray(flux, dtype=float)
        sigma_mas = np.broadcast_to(np.asarray(sigma_mas, dtype=float), flux.shape)
        biggest = self.max_stamp(float(np.max(sigma_mas, initial=0.0)))
        if noise_sigma <= 0:
            return np.full(flux.shape, biggest, dtype=int)
        level = self.params.stamp_threshold * noise_sigma / np.maximum(flux, 1e-300)
        # the wing blurred by each star's kernel (its largest sigma, rounded up to a step)
        steps = np.ceil(sigma_mas / self.pixel_scale / BLUR_SIGMA_STEP - 1e-9).astype(np.int64)
        steps = np.maximum(steps, 0)
        node = w = None
        if x_field is not None and len(flux):
            node, w = self._node_weights(x_field, y_field)
        radius_pix = np.zeros(len(flux))
        if len(steps):
            self._blurred_envelope(int(steps.max()))  # every step up to the widest at once
        for step in np.unique(steps):
            radii, env_nodes = self._blurred_envelope(int(step))
            mine = np.flatnonzero(steps == step)
            # index of the first envelope radius at or below the level (env non-increasing)
            if node is None:
                pos = np.searchsorted(-env_nodes.max(axis=0), -level[mine], side="left")
            else:
                pos = np.zeros(len(mine), dtype=np.int64)
                for k in range(node.shape[1]):
                    # stars grouped by node through one sort (not one pass over all per node)
                    order = np.argsort(node[mine, k], kind="stable")
                    nodes, first = np.unique(node[mine[order], k], return_index=True)
                    for n, a, b in zip(nodes, first, np.append(first[1:], len(order))):
                        sel = order[a:b]
                        sel = sel[w[mine[sel], k] > 0]
                        here = np.searchsorted(-env_nodes[n], -level[mine[sel]], side="left")
                        pos[sel] = np.maximum(pos[sel], here)
            radius_pix[mine] = radii[np.minimum(pos, len(radii) - 1)]
        # square radius (see _wing_envelope): the stamp's square holds the square of it
        half = radius_pix + 1.5
        return np.minimum(_stamp_sizes_at_least(2 * half, self.params.min_stamp), biggest)

    def _blurred_envelope(self, step: int):
        """The stamp-sizing envelope for kernels of largest sigma ``step * BLUR_SIGMA_STEP`` px.

        A star's image is its PSF convolved with its kernel (and the pixel). At a pixel
        ``q`` at square radius ``R``, say ``|q_x| = R``, the PSF at ``p`` is at most
        ``env(|p|_inf) <= env(|p_x|)`` (non-increasing), so the blurred value is at most
        the 1-D convolution of ``env(|x|)`` with the kernel's marginal along x
        (:func:`_blur_envelope`), whose sigma is at most the kernel's largest. A narrower
        Gaussian keeps more of a plateau near its edge, a wider one pushes more of it
        outwards: the envelope is the largest of the convolutions with every sigma from
        0 to the kernel's largest rounded up, in steps of ``BLUR_SIGMA_STEP`` (between two
        steps the convolution changes by ~(step / sigma)**2 of itself). Replaces the
        margin of 4 sigma that was added to the unblurred envelope's radius. Cached.

        Returns
        -------
        radii : ndarray (nr,)
            Square radii [pixel] (0, 0.5, ...), beyond the PSF by 8 sigma.
        env : ndarray (n_nodes, nr)
            The envelope per node, non-increasing.
        """
        if step not in self._blurred:
            radii, env = self._envelope
            for k, got in enumerate(_sizing_envelopes(radii, env, step, BLUR_SIGMA_STEP)):
                self._blurred[k] = got
        return self._blurred[step]

    # ------------------------------------------------------------- transforms
    def plan(self, m: int) -> StampPlan:
        """The cached :class:`StampPlan` of stamp side ``m`` (node transforms etc.).

        The node transforms are the exact transforms of each PSF node at the
        stamp's folding frequencies: FFTs of the node wrapped onto the stamp period
        when that period is a whole number of PSF pixels (7.5 mas / 1.875 mas), a
        direct (matrix) DFT for any other sampling; only samples where
        some node exceeds ``spectrum_floor * 10**-PLAN_FLOOR_DECADES`` of its total are
        kept (the optical transfer function vanishes beyond D/lambda).

        Parameters
        ----------
        m : int
            Stamp side [pixel].
        """
        return self.plans([m])[m]

    def plans(self, sizes) -> dict[int, StampPlan]:
        """The :class:`StampPlan` of every stamp side in ``sizes``, computed together.

        Plans missing from memory are loaded from ``cache_dir`` or computed; stamp
        periods that divide one another (same odd factor, e.g. 128, 64, 32 pixels)
        share one FFT per PSF node (see :func:`_node_transforms_fft`).

        Parameters
        ----------
        sizes : iterable of int
            Stamp sides [pixel].

        Returns
        -------
        dict of int to StampPlan
        """
        missing = sorted({int(m) for m in sizes} - set(self._plans))
        todo = []
        for m in missing:
            stored = load_arrays(self._plan_path(m)) if self.cache_dir is not None else None
            if stored is not None and set(stored) == {f.name for f in fields(StampPlan)}:
                stored["m"] = int(stored["m"])
                self._plans[m] = StampPlan(**stored)
            else:
                todo.append(m)
        for plan in self._make_plans(todo):
            self._plans[plan.m] = plan
            if self.cache_dir is not None:
                arrays = {f.name: np.asarray(getattr(plan, f.name)) for f in fields(plan)}
                save_arrays(self._plan_path(plan.m), arrays)
        return {int(m): self._plans[int(m)] for m in sizes}

    def _plan_path(self, m: int) -> Path:
        return self.cache_dir / f"stampplan-{self._cache_key}-m{m}.npz"

    def _make_plans(self, sizes):
        """Compute the plans of ``sizes`` (yields them one by one)."""
        k = self.params.oversampling
        s = self.pixel_scale
        periodic = {}  # odd factor of the period -> [(m, period, fy, fx)]
        for m in sizes:
            fy, fx = _folding_frequencies(m, k)
            period = m * s / self.psf_pixel_scale  # stamp period in PSF pixels
            if abs(period - round(period)) < 1e-9 * period:
                p = int(round(period))
                periodic.setdefault(p // (p & -p), []).append((m, p, fy, fx))
            else:
                step = self.psf_pixel_scale / (m * s)
                yield self._plan_from(m, fy, fx, _node_transforms_dft(self._cube, step, fy, fx))
        for group in periodic.values():
            requests = [(p, fy, fx) for _, p, fy, fx in group]
            workers = self.params.threads or usable_cores()
            full = _node_transforms_fft(self._cube, requests, workers=workers)
            for (m, _, fy, fx), transforms in zip(group, full):
                yield self._plan_from(m, fy, fx, transforms)

    def _plan_from(self, m: int, fy, fx, full) -> StampPlan:
        """The plan of side ``m`` from the node transforms ``full`` (nodes, nfy, nfx)."""
        s = self.pixel_scale
        df = 1.0 / (m * s)  # cycles/mas per integer frequency
        a = self.intrapixel_amplitude
        full *= (
            pixel_transfer(fy * df, s, a)[None, :, None]
            * pixel_transfer(fx * df, s, a)[None, None, :]
        )
        peak = np.abs(full).max(axis=0)
        peak /= peak.max()
        # keep PLAN_FLOOR_DECADES below the floor: bright-star batches use lower floors
        keep = peak > self.params.spectrum_floor * 10.0**-PLAN_FLOOR_DECADES
        row, col = np.nonzero(keep)
        mh = m // 2 + 1
        target = (row % m) * mh + (col % mh)
        return StampPlan(
            m=m,
            u=fx[col] * df,
            v=fy[row] * df,
            col=col,
            row=row,
            fx=fx,
            fy=fy,
            transforms=np.ascontiguousarray(full[:, row, col]),
            peak=peak[row, col],
            target=target.astype(np.int64),
        )

    def _node_weights(self, x, y):
        iy, ix, w = self.psf_grid.bilinear_weights(x, y)
        iy = np.asarray(iy, dtype=np.int64)
        ix = np.asarray(ix, dtype=np.int64)
        w = np.asarray(w, dtype=np.float64)
        node = iy * self.n_nodes_x + ix
        if self.params.psf_interpolation == "nearest":
            best = np.argmax(w, axis=1)
            rows = np.arange(len(w))
            node = node[rows, best][:, None]
            w = np.ones((len(w), 1))
        return node, w

    # ----------------------------------------------------------------- stamps
    def render_stamps(
        self,
        m: int,
        x_pix,
        y_pix,
        x_field,
        y_field,
        cov,
        flux,
        floor=None,
        dtype=None,
        spectrum=None,
        work=None,
    ):
        """Noise-free stamps of side ``m`` for a batch of stars.

        Parameters
        ----------
        m : int
            Stamp side (even).
        x_pix, y_pix : ndarray (S,)
            Exact star positions in detector pixels (0-based, centres at integers).
        x_field, y_field : ndarray (S,)
            Field positions (arcsec) used to interpolate the PSF grid.
        cov : ndarray (S, 2, 2)
            Kernel covariance (tip-tilt + blur), mas^2, [[xx, xy], [xy, yy]].
        flux : ndarray (S,)
            Star fluxes.
        floor : float, optional
            Spectrum floor (default ``params.spectrum_floor``).
        dtype : {"float32", "float64"}, optional
            Precision (default ``params.dtype``).
        spectrum : tuple of arrays, optional
            ``(weights (K,), shifts (K, 2) [mas])`` of the batch's broadband kernel;
            required (and only used) with ``slice_cubes``.
        work : _WorkBuffers, optional
            Reused memory for the folded spectra and the stamps (see :meth:`render`);
            None: fresh arrays. The values do not depend on it.

        Returns
        -------
        stamps : ndarray (S, m, m)
            Pixel values; ``stamps[i]`` covers rows ``y0[i]..y0[i]+m-1`` and
            columns ``x0[i]..x0[i]+m-1``; each sums to ``flux[i]``.
        x0, y0 : ndarray (S,) int
            Detector pixel of each stamp's corner ``[0, 0]``.
        """
        batch = self._prepare(m, x_pix, y_pix, x_field, y_field, cov, flux, floor, dtype, spectrum)
        nst = len(batch.x0)
        if work is None:
            folded = np.empty((batch.chunk, m * batch.mh), dtype=batch.cplx)
            stamps = np.empty((nst, m, m), dtype=batch.real)
        else:
            folded = work.folded((batch.chunk, m * batch.mh), batch.cplx)
            stamps = work.stamps((nst, m, m), batch.real)
        _render_chunks(batch, 0, nst, folded, stamps)
        return stamps, batch.x0, batch.y0

    def _prepare(
        self, m, x_pix, y_pix, x_field, y_field, cov, flux, floor=None, dtype=None, spectrum=None
    ) -> _Batch:
        """Everything :func:`_render_chunks` needs for the stamps of side ``m`` of a batch.

        The arguments are those of :meth:`render_stamps`; the per-star arrays of the
        result follow the order of the stars given.
        """
        s = self.pixel_scale
        x_pix = np.asarray(x_pix, dtype=np.float64)
        y_pix = np.asarray(y_pix, dtype=np.float64)
        ixc = stamp_centre(x_pix)
        iyc = stamp_centre(y_pix)
        # offset of the star from stamp pixel 0, in mas (star sits at stamp index m/2)
        dx = (x_pix - ixc) * s + m * s / 2
        dy = (y_pix - iyc) * s + m * s / 2
        plan = self.plan(m)
        df = 1.0 / (m * s)
        nst = len(x_pix)
        floor = self.params.spectrum_floor if floor is None else floor
        real = np.float32 if (dtype or self.params.dtype) == "float32" else np.float64
        cplx = np.complex64 if real is np.float32 else np.complex128
        cov = np.asarray(cov, dtype=np.float64)
        sel = _batch_samples(plan, cov, floor)
        u, v = plan.u[sel], plan.v[sel]
        node, w = self._node_weights(x_field, y_field)
        if self.n_slices == 1 and spectrum is None:
            transforms = self._typed_columns(plan, cplx, sel)
        else:
            mixed = self._mixed_transforms(plan.transforms[:, sel], u, v, spectrum)
            transforms = np.ascontiguousarray(mixed, dtype=cplx)
        # Gaussian OTF exp(-2 pi^2 u^T C u) (the phase ramps of the sub-pixel shifts are
        # made a few stars at a time, see _render_chunks)
        coef = (cov.reshape(nst, 4)[:, [0, 1, 3]] * [1.0, 2.0, 1.0]) * (-2.0 * np.pi**2)
        # the flux scales the node weights: the transform is linear, and the stamps need
        # no separate pass to scale them
        w = np.ascontiguousarray(w * np.asarray(flux, dtype=np.float64)[:, None], dtype=real)
        mh = m // 2 + 1
        # a few stars at a time through the mixing pass and the inverse FFTs: their folded
        # spectra stay in the core's cache between the two (the same values per star)
        chunk = max(1, min(nst, STAMP_CHUNK_BYTES // (m * mh * np.dtype(cplx).itemsize)))
        return _Batch(
            m=m,
            mh=mh,
            real=real,
            cplx=cplx,
            df=df,
            fx=plan.fx,
            fy=plan.fy,
            fxu=plan.fx * df,
            fyv=plan.fy * df,
            transforms=transforms,
            runs=fold_runs(plan.col[sel], plan.row[sel], plan.target[sel], plan.fx),
            node=node,
            w=w,
            coef=np.ascontiguousarray(coef, dtype=real),
            dx=dx,
            dy=dy,
            x0=ixc - m // 2,
            y0=iyc - m // 2,
            chunk=chunk,
        )

    def _typed_columns(self, plan: StampPlan, cplx, sel) -> np.ndarray:
        """``plan.transforms[:, sel]`` in ``cplx``, C-contiguous: a batch's node transforms.

        Taken from a copy of the columns that the batches use (kept per plan and
        type, extended when a batch needs more; :meth:`render` makes it for all its
        batches before they start): the same values as casting each batch's columns
        (a cast commutes with taking columns), without a cast per batch or reading
        the memory map of a cached plan, whose members are not aligned in the
        ``.npz`` file (numpy's unaligned copies are several times slower; ~0.2 s of
        CPU at 10,000 stars). The faint stars' batches use about a third of a plan's
        columns.

        Parameters
        ----------
        plan : StampPlan
        cplx : numpy dtype
            complex64 or complex128.
        sel : ndarray of int, sorted
            The batch's columns.
        """
        key = (plan.m, np.dtype(cplx).str)
        entry = self._typed.get(key)
        if entry is None or entry[0] is not plan:
            self._keep_columns(plan, cplx, sel)
        elif not _is_subset(sel, entry[1]):
            self._keep_columns(plan, cplx, np.union1d(entry[1], sel))
        _, cols, typed = self._typed[key]
        if len(sel) == len(cols):  # all of them (sel is a subset of cols): no copy
            return typed
        return np.take(typed, np.searchsorted(cols, sel), axis=1)  # C order (a[:, i] is not)

    def _keep_columns(self, plan: StampPlan, cplx, cols) -> None:
        """Keep ``plan.transforms[:, cols]`` in ``cplx`` for :meth:`_typed_columns`.

        Cast a few rows at a time: no complex128 copy of all the columns on the way to
        complex64 (twice the kept array's fresh memory); a cast commutes with taking
        columns, so the values are the same.
        """
        cols = np.asarray(cols, dtype=np.int64)
        src = plan.transforms
        typed = np.empty((src.shape[0], len(cols)), dtype=cplx)
        step = max(1, KEEP_COLUMNS_BYTES // max(1, len(cols) * src.dtype.itemsize))
        for i in range(0, src.shape[0], step):
            typed[i : i + step] = src[i : i + step, cols]
        self._typed[(plan.m, np.dtype(cplx).str)] = (plan, cols, typed)

    def _mixed_transforms(self, transforms, u, v, spectrum):
        """Node transforms of the batch's kernel: the slices weighted and phase-shifted.

        ``transforms`` (K * nodes, nsel) at frequencies ``u, v`` [cycles/mas]; one slice
        without a spectrum is returned as is.
        """
        if self.n_slices == 1 and spectrum is None:
            return transforms
        if spectrum is None:
            raise ValueError(f"a renderer with {self.n_slices} slices needs each batch's spectrum")
        weights, shifts = (np.asarray(a, dtype=np.float64) for a in spectrum)
        shifts = shifts.reshape(self.n_slices, 2)
        if weights.shape != (self.n_slices,):
            raise ValueError(f"spectrum weights must have {self.n_slices} entries")
        phase = np.exp(-2j * np.pi * (np.outer(shifts[:, 0], u) + np.outer(shifts[:, 1], v)))
        t = transforms.reshape(self.n_slices, -1, transforms.shape[-1])
        return np.einsum("k,kns,ks->ns", weights, t, phase)

    def render(
        self,
        image,
        x_pix,
        y_pix,
        x_field,
        y_field,
        cov,
        flux,
        sizes,
        noise_sigma=None,
        progress=False,
        colour=None,
        spectra=None,
        threads=None,
    ):
        """Add stars to ``image`` in place (noise-free), batched by stamp size.

        Parameters
        ----------
        image : ndarray (ny, nx)
            Accumulator; stamps are clipped at its edges.
        x_pix, y_pix, x_field, y_field, cov, flux
            As in :meth:`render_stamps`, for all stars.
        sizes : ndarray (N,) int
            Stamp side per star (see :meth:`stamp_sizes`); stars with size 0 or
            zero flux, or whose stamp misses the image, are skipped.
        noise_sigma : float, optional
            Per-pixel noise (flux units). When given, batches of bright stars use a
            spectrum floor and a precision whose errors stay below
            ``stamp_threshold * noise_sigma`` (float64 where float32 round-off would not).
        progress : bool
            Show a tqdm progress bar.
        colour : ndarray (N,) int, optional
            Colour bin of each star (index into ``spectra``).
        spectra : list of tuple, optional
            Broadband kernel ``(weights, shifts)`` of each colour bin (see
            :meth:`render_stamps`); needed with ``slice_cubes``.
        threads : int, optional
            Threads (the image does not depend on it). Default: ``params.threads``,
            0 resolved by :func:`~mavispm.simulate.render.thread_count.frame_threads`
            from the stars drawn.

        Returns
        -------
        ndarray (N,) bool
            Which stars were rendered (their stamp overlaps the image).
        """
        ny, nx = image.shape
        sizes = np.asarray(sizes, dtype=np.int64)
        x_pix = np.asarray(x_pix, dtype=np.float64)
        y_pix = np.asarray(y_pix, dtype=np.float64)
        flux = np.asarray(flux, dtype=np.float64)
        x_field = np.asarray(x_field, dtype=np.float64)
        y_field = np.asarray(y_field, dtype=np.float64)
        cov = np.asarray(cov, dtype=np.float64)
        half = sizes // 2
        cx, cy = stamp_centre(x_pix), stamp_centre(y_pix)
        overlaps = (cx + half > 0) & (cx - half < nx) & (cy + half > 0) & (cy - half < ny)
        todo = overlaps & (sizes > 0) & (flux > 0)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=int(todo.sum()), desc="stars", unit="star", leave=False)
        batch = self.params.batch_size
        colour = np.zeros(len(flux), np.int64) if colour is None else np.asarray(colour, np.int64)
        # split rendering: small stamps of the inner PSF, the outer PSF by convolution
        split = self._split_mask(flux, cov, noise_sigma, todo)
        parts = {False: self}
        if split.any():
            inner, outer = self._split_parts()
            parts[True] = inner
            sig = np.sqrt(np.clip(eigvals_2x2(cov[split])[1], 0, None))
            sizes = sizes.copy()
            sizes[split] = inner.stamp_sizes(
                flux[split], noise_sigma or 1e-300, sig, x_field[split], y_field[split]
            )
        jobs = []
        f64 = self._float64_flux(noise_sigma)
        for part, renderer in parts.items():
            mine = todo & (split == part)
            for m in np.unique(sizes[mine]):
                for b in np.unique(colour[mine & (sizes == m)]):
                    idx = np.flatnonzero(mine & (sizes == m) & (colour == b))
                    idx = idx[np.argsort(flux[idx], kind="stable")]
                    for sel in _flux_batches(idx, flux[idx], batch, f64):
                        # similar fluxes: one spectrum floor and precision per batch
                        jobs.append((int(m), sel, renderer))
        if threads is None:
            threads = frame_threads(self.params.threads, int(todo.sum()))
        for renderer in parts.values():  # build plans once, before the threads share them
            renderer.plans({m for m, _, r in jobs if r is renderer})
        if spectra is None:  # and the columns of their transforms that the batches take
            self._prepare_columns(jobs, flux, cov, noise_sigma)
        # Bands of stamp centre rows, as tall as the largest stamp: a stamp reaches at most
        # half a band beyond its own, so the bands of one parity touch disjoint rows. Batch
        # by batch, the even bands are rendered and added in parallel, then the odd ones:
        # every pixel gets its stamps in the same order whatever the number of threads.
        # Within a band the stars go left to right and each chunk of stamps is added as
        # soon as it is transformed, from the core's cache, into image rows that the band's
        # previous stamps brought into it (not the whole frame's width, as in row order).
        height = max((m for m, _, _ in jobs), default=1)
        n_bands = max(1, -(-ny // height))
        cx, cy = stamp_centre(x_pix), stamp_centre(y_pix)
        buffers = _WorkPool(max(threads, 1))

        def add_band(item) -> None:
            prep, lo, hi = item
            buf = buffers.take()
            try:
                _render_chunks(
                    prep, lo, hi,
                    buf.folded((prep.chunk, prep.m * prep.mh), prep.cplx),
                    buf.stamps((prep.chunk, prep.m, prep.m), prep.real),
                    image,
                )  # fmt: skip
            finally:
                buffers.release(buf)

        with ThreadPoolExecutor(max_workers=max(threads, 1)) as pool:
            for m, sel, renderer in jobs:
                floor, dtype = renderer._batch_accuracy(float(flux[sel].max()), noise_sigma)
                order, bounds = _band_order(cx[sel], cy[sel], height, n_bands)
                sel = sel[order]
                spectrum = None if spectra is None else spectra[colour[sel[0]]]
                prep = renderer._prepare(
                    m, x_pix[sel], y_pix[sel], x_field[sel], y_field[sel], cov[sel],
                    flux[sel], floor, dtype, spectrum,
                )  # fmt: skip
                for parity in (0, 1):
                    runs = bounds[parity::2]
                    if len(runs) == 0 or runs[-1, 1] <= runs[0, 0]:
                        continue
                    parts = 1 if len(sel) < SPLIT_BANDS_STARS else threads
                    items = [(prep, lo, hi) for lo, hi in _band_groups(runs, parts)]
                    if len(items) > 1:
                        list(pool.map(add_band, items))
                    else:  # one thread: the parity's bands in turn, as one run of stars
                        add_band(items[0])
                if bar is not None:
                    bar.update(len(sel))
        buffers = None  # freed before the outer convolution's own memory peak
        if split.any():
            node, w = self._node_weights(x_field[split], y_field[split])
            _, dtype = self._batch_accuracy(float(flux[split].max()), noise_sigma)
            allowed = None
            if noise_sigma is not None and noise_sigma > 0:
                allowed = 0.05 * self.params.stamp_threshold * noise_sigma
            outer.add(
                image, x_pix[split], y_pix[split], node, w, cov[split], flux[split],
                dtype=dtype, threads=threads, allowed=allowed,
            )  # fmt: skip
        if bar is not None:
            bar.close()
        return overlaps

    # ------------------------------------------------------------ split rendering
    def _split_parts(self):
        """(inner renderer, :class:`OuterConvolver`) of split rendering (built once)."""
        if self._split is None:
            from dataclasses import replace

            from mavispm.simulate.render.outer_convolution import OuterConvolver, split_cube

            n = self._cube.shape[-1]
            inner, outer = split_cube(
                self._cube, self.psf_pixel_scale, self.pixel_scale, self.params.split_radius
            )
            grid = _TaperedGrid(self.psf_grid, inner.reshape(self.n_nodes_y, self.n_nodes_x, n, n))
            params = replace(self.params, outer_convolution="off")
            self._split = (
                StarRenderer(grid, self.pixel_scale, params, self.cache_dir,
                             intrapixel_amplitude=self.intrapixel_amplitude),
                OuterConvolver(outer, self.psf_pixel_scale, self.pixel_scale,
                               self.intrapixel_amplitude),
            )  # fmt: skip
        return self._split

    def split_possible(self) -> bool:
        """Whether split rendering applies (one PSF slice; half a pixel = whole PSF samples)."""
        k = 0.5 * self.pixel_scale / self.psf_pixel_scale
        return self.n_slices == 1 and k >= 1 - 1e-9 and abs(k - round(k)) <= 1e-9 * k

    def _split_mask(self, flux, cov, noise_sigma, todo) -> np.ndarray:
        """Stars to render split (inner stamp + outer convolution); see ``RenderParams``."""
        mode = self.params.outer_convolution
        none = np.zeros(len(flux), dtype=bool)
        if mode == "off" or not todo.any():
            return none
        if not self.split_possible():
            if mode == "on":
                raise ValueError(
                    "render.outer_convolution = 'on' needs one PSF slice and half a detector "
                    "pixel equal to a whole number of PSF samples"
                )
            return none
        if mode == "auto" and todo.sum() < self.params.split_min_stars:
            return none
        _, outer = self._split_parts()
        mask = todo.copy()
        if noise_sigma is not None and noise_sigma > 0:
            allowed = 0.1 * self.params.stamp_threshold * noise_sigma
            mask &= flux * outer.alias_bound(cov) <= allowed
        if mode == "auto" and mask.sum() < self.params.split_min_stars:
            return none
        return mask

    @staticmethod
    def _prepare_columns(jobs, flux, cov, noise_sigma) -> None:
        """Copy, per renderer, plan and type, the transform columns that ``jobs`` take.

        Done before the batches start, so that the threads only read the copies (see
        :meth:`_typed_columns`).
        """
        need: dict[tuple, tuple] = {}
        for m, sel, renderer in jobs:
            floor, dtype = renderer._batch_accuracy(float(flux[sel].max()), noise_sigma)
            cplx = np.complex64 if dtype == "float32" else np.complex128
            plan = renderer.plan(m)
            key = (id(renderer), m, np.dtype(cplx).str)
            cols = _batch_samples(plan, cov[sel], floor)
            if key in need:
                cols = np.union1d(need[key][3], cols)
            need[key] = (renderer, plan, cplx, cols)
        for renderer, plan, cplx, cols in need.values():
            entry = renderer._typed.get((plan.m, np.dtype(cplx).str))
            if entry is None or entry[0] is not plan or not _is_subset(cols, entry[1]):
                renderer._keep_columns(plan, cplx, cols)

    def _float64_flux(self, noise_sigma) -> float:
        """Flux from which a star needs float64 stamps (float32 round-off above the threshold)."""
        if self.params.dtype != "float32" or noise_sigma is None or noise_sigma <= 0:
            return np.inf
        return self.params.stamp_threshold * noise_sigma / FLOAT32_ROUNDOFF

    def _batch_accuracy(self, flux_max: float, noise_sigma) -> tuple[float, str]:
        """Spectrum floor and precision keeping a batch's errors below the threshold."""
        floor, dtype = self.params.spectrum_floor, self.params.dtype
        if noise_sigma is None or noise_sigma <= 0 or flux_max <= 0:
            return floor, dtype
        allowed = self.params.stamp_threshold * noise_sigma / flux_max
        if flux_max > self._float64_flux(noise_sigma):
            dtype = "float64"
        return min(floor, allowed), dtype


#: Bytes of plan columns taken at a time by :meth:`StarRenderer._keep_columns` before the
#: cast (fits in the core's cache).
KEEP_COLUMNS_BYTES = 1 << 20


class _WorkBuffers:
    """Work memory of one thread: folded spectra and stamps of a chunk, grown as needed.

    Parameters
    ----------
    folded_bytes, stamps_bytes : int
        Memory reserved up front (untouched until used).
    """

    def __init__(self, folded_bytes: int = 0, stamps_bytes: int = 0):
        self._folded = np.empty(folded_bytes, dtype=np.uint8)
        self._stamps = np.empty(stamps_bytes, dtype=np.uint8)

    @staticmethod
    def _view(buf, shape, dtype):
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        if buf.size < n:
            buf = np.empty(n, dtype=np.uint8)
        return buf, buf[:n].view(dtype).reshape(shape)

    def folded(self, shape, dtype) -> np.ndarray:
        """An uninitialised array for the folded spectra."""
        self._folded, view = self._view(self._folded, shape, dtype)
        return view

    def stamps(self, shape, dtype) -> np.ndarray:
        """An uninitialised array for the stamps."""
        self._stamps, view = self._view(self._stamps, shape, dtype)
        return view


class _WorkPool:
    """``size`` :class:`_WorkBuffers`, one per thread.

    A band of stars takes a free one before it renders and gives it back once its
    stamps are in the image.

    Parameters
    ----------
    size : int
        Buffers.
    folded_bytes, stamps_bytes : int
        Memory reserved in each (see :class:`_WorkBuffers`).
    """

    def __init__(self, size: int, folded_bytes: int = 0, stamps_bytes: int = 0):
        import queue

        self._free = queue.SimpleQueue()
        for _ in range(size):
            self._free.put(_WorkBuffers(folded_bytes, stamps_bytes))

    def take(self) -> _WorkBuffers:
        """A free buffer (waits while every buffer is in use)."""
        return self._free.get()

    def release(self, buf: _WorkBuffers) -> None:
        """Give ``buf`` back (after its stamps were added)."""
        self._free.put(buf)


#: Batches of fewer stars are rendered by one thread (each parity's bands as one run of
#: stars: full chunks, no hand-over between threads); the image is the same.
SPLIT_BANDS_STARS = 64

#: A batch of stars spans at most this factor in flux: its spectrum floor follows its
#: brightest star, so a wider batch would evaluate its faint stars to a needlessly low floor.
BATCH_FLUX_SPAN = 10.0


def _flux_batches(idx, flux, size: int, float64_flux: float = np.inf):
    """Split stars sorted by flux into batches of similar accuracy needs.

    A batch holds at most ``size`` stars, spans at most ``BATCH_FLUX_SPAN`` in flux and
    never mixes stars below and at or above ``float64_flux`` (the flux from which
    float32 stamps are not accurate enough), so that one very bright star does not put
    a whole batch into float64 or a lower spectrum floor.

    Parameters
    ----------
    idx : ndarray (N,) int
        Star indices, sorted by ascending flux.
    flux : ndarray (N,)
        Their fluxes (ascending).
    size : int
        Largest batch.
    float64_flux : float
        Flux from which a star is rendered in float64.

    Returns
    -------
    list of ndarray
        The batches (consecutive slices of ``idx``).
    """
    out, a, n = [], 0, len(idx)
    while a < n:
        lo = max(float(flux[a]), 1e-300)
        limit = lo * BATCH_FLUX_SPAN
        if lo < float64_flux:
            limit = min(limit, float64_flux)
            b = int(np.searchsorted(flux, limit, side="left"))
        else:
            b = int(np.searchsorted(flux, limit, side="right"))
        b = min(max(b, a + 1), a + size, n)
        out.append(idx[a:b])
        a = b
    return out


class _TaperedGrid:
    """A PSF grid with the nodes replaced by their inner parts (same node positions)."""

    def __init__(self, grid, cube):
        self._grid = grid
        self.cube = cube
        self.pixel_scale = grid.pixel_scale

    def bilinear_weights(self, x, y):
        return self._grid.bilinear_weights(x, y)


def _column_steps(fx, row) -> np.ndarray:
    """Which samples lie one column step after the previous sample, in its row.

    ``step[k]``: ``row[k] == row[k - 1]`` and ``fx[k] == fx[k - 1] + 1`` (integer
    frequencies); there the mixing pass continues its Gaussian by the recurrence
    (see :func:`~mavispm.simulate.render.stamp_kernels.mix_kernel_fold`).

    Parameters
    ----------
    fx : ndarray (K,)
        Integer column frequency of each sample.
    row : ndarray of int (K,)
        Row of each sample.
    """
    step = np.zeros(len(row), dtype=np.bool_)
    step[1:] = (row[1:] == row[:-1]) & (fx[1:] == fx[:-1] + 1)
    return step


def _phase_ramps(shift, freq, df: float, cplx) -> np.ndarray:
    """``exp(-2 pi i df * outer(shift, freq))`` in ``cplx`` (integer frequencies).

    One ``cos`` / ``sin`` per star and the powers of its phase factor by a float64
    recurrence (:func:`~mavispm.simulate.render.stamp_kernels.phase_ramps_into`; ~1e-13
    relative error): ``numpy``'s ``cos`` and ``sin`` of every phase cost ~6 us per star
    of a 120-pixel stamp.

    Parameters
    ----------
    shift : ndarray (S,)
        Star offsets [mas].
    freq : ndarray (F,)
        Integer frequencies (units of ``df``).
    df : float
        Frequency step [cycles/mas].
    cplx : numpy dtype
        complex64 or complex128.
    """
    out = np.empty((len(shift), len(freq)), dtype=cplx)
    whole = np.rint(np.asarray(freq, dtype=np.float64)).astype(np.int64)
    top = int(np.abs(whole).max()) if whole.size else 0
    powers = np.empty((2, top + 1))  # the kernel's work memory: it allocates nothing
    phase_ramps_into(np.asarray(shift, dtype=np.float64), whole, float(df), out, powers)
    return out


@dataclass
class _Batch:
    """A batch of stars of one stamp side, ready for :func:`_render_chunks`.

    ``transforms`` (nodes, K) are the node transforms at the batch's spectrum samples,
    ``runs`` their layout (see ``fold_runs``); per star: PSF ``node`` indices and flux-scaled
    weights ``w``, Gaussian OTF coefficients ``coef``, offsets ``dx``, ``dy`` [mas] from stamp
    pixel 0 and the stamp corner ``x0``, ``y0`` [pixel]. ``chunk`` stars go through the
    mixing pass and the inverse FFTs together.
    """

    m: int
    mh: int
    real: type
    cplx: type
    df: float
    fx: np.ndarray
    fy: np.ndarray
    fxu: np.ndarray
    fyv: np.ndarray
    transforms: np.ndarray
    runs: np.ndarray
    node: np.ndarray
    w: np.ndarray
    coef: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    chunk: int


def _render_chunks(batch: _Batch, lo: int, hi: int, folded, stamps, image=None) -> None:
    """The stamps of stars ``lo:hi`` of ``batch``, a chunk of stars at a time.

    Per chunk: the mixing pass into ``folded`` (zeroed here), the two passes of the
    inverse real FFT, then either into ``stamps[i - lo]`` (``image`` None) or into
    ``stamps[:n]`` (a chunk's worth of memory, reused) and added at once to ``image``
    (clipped at its edges), while they are still in the core's cache.

    Parameters
    ----------
    batch : _Batch
    lo, hi : int
        The stars (indices into the batch's per-star arrays).
    folded : ndarray (>= chunk, m * mh) complex
        Work memory for the folded spectra.
    stamps : ndarray (hi - lo, m, m) or (>= chunk, m, m) real
        The stamps, or work memory for a chunk of them when ``image`` is given.
    image : ndarray (ny, nx), optional
        Added into, in the order of the stars.
    """
    m, mh, real = batch.m, batch.mh, batch.real
    if hi <= lo:
        return
    phx = _phase_ramps(batch.dx[lo:hi], batch.fx, batch.df, batch.cplx)
    phy = _phase_ramps(batch.dy[lo:hi], batch.fy, batch.df, batch.cplx)
    scratch = mix_scratch(batch.transforms, batch.fxu, batch.runs, batch.w.dtype)
    for a in range(lo, hi, batch.chunk):
        b = min(a + batch.chunk, hi)
        out = folded[: b - a]
        out.fill(0)
        mix_kernel_fold_runs(
            batch.transforms, batch.node[a:b], batch.w[a:b], batch.coef[a:b], batch.fxu,
            batch.fyv, batch.df, phx[a - lo : b - lo], phy[a - lo : b - lo], batch.runs,
            out.view(real), scratch,
        )  # fmt: skip
        spec = out.reshape(b - a, m, mh)
        dest = stamps[: b - a] if image is not None else stamps[a - lo : b - lo]
        inverse_rfft2_into(spec, dest, m)  # irfft2's two passes into reused memory
        if image is not None:
            add_stamps(image, dest, batch.x0[a:b], batch.y0[a:b])


def _band_order(cx, cy, height: int, n_bands: int):
    """Stars by band of stamp-centre rows (``height`` rows each), left to right in a band.

    A stamp of side ``m <= height`` centred in band ``k`` covers rows
    ``[k height - m / 2, (k + 1) height + m / 2)``, so bands ``k`` and ``k + 2`` touch
    disjoint rows; centres above or below the image go to its first or last band (only
    their rows inside the image matter). The even bands come first, then the odd ones,
    so that each parity's stars are consecutive.

    Parameters
    ----------
    cx, cy : ndarray of int (S,)
        Stamp-centre column and row of each star.
    height : int
        Band height [rows], at least the largest stamp side.
    n_bands : int
        Bands covering the image rows (``ceil(ny / height)``).

    Returns
    -------
    order : ndarray of int (S,)
        The stars by band parity, band, then column (stable).
    bounds : ndarray of int (n_bands, 2)
        Band ``k`` holds ``order[bounds[k, 0]:bounds[k, 1]]``.
    """
    band = np.clip(np.asarray(cy) // height, 0, n_bands - 1)
    order = np.lexsort((cx, band, band % 2))
    ranked = np.arange(n_bands)
    ranked = np.concatenate([ranked[0::2], ranked[1::2]])  # bands in the order of ``order``
    counts = np.bincount(band, minlength=n_bands)[ranked]
    ends = np.cumsum(counts)
    bounds = np.empty((n_bands, 2), dtype=np.int64)
    bounds[ranked, 0] = ends - counts
    bounds[ranked, 1] = ends
    return order, bounds


def _band_groups(runs, parts: int) -> list[tuple[int, int]]:
    """Consecutive bands of one parity in ``parts`` runs of about equal star counts.

    ``runs`` (n, 2) are the bands' ``[lo, hi)`` star ranges, consecutive (``runs[k, 1] ==
    runs[k + 1, 0]``; see :func:`_band_order`). Each group is cut at a band boundary (so two
    groups touch disjoint image rows) and holds at least one star; at most ``parts`` groups,
    fewer when there are fewer non-empty bands.

    Returns
    -------
    list of (lo, hi)
        Star ranges covering ``runs[0, 0]:runs[-1, 1]`` in order.
    """
    start, end = int(runs[0, 0]), int(runs[-1, 1])
    cuts = np.asarray(runs[:-1, 1], dtype=np.int64)  # band boundaries inside the run
    groups, lo = [], start
    for k in range(1, max(int(parts), 1)):
        target = start + (end - start) * k / parts
        # the band boundary nearest the equal share, past the previous cut
        cand = cuts[cuts > lo]
        if cand.size == 0:
            break
        cut = int(cand[np.argmin(np.abs(cand - target))])
        if cut >= end:
            break
        groups.append((lo, cut))
        lo = cut
    groups.append((lo, end))
    return groups


def _is_subset(values, sorted_set) -> bool:
    """Whether every element of ``values`` is in the sorted array ``sorted_set``."""
    if len(sorted_set) == 0:
        return len(values) == 0
    pos = np.minimum(np.searchsorted(sorted_set, values), len(sorted_set) - 1)
    return bool(np.array_equal(sorted_set[pos], values))


def _batch_samples(plan: StampPlan, cov, floor: float) -> np.ndarray:
    """The plan's spectrum samples a batch evaluates (sorted indices).

    Those the batch's narrowest kernel (covariances ``cov`` (S, 2, 2) [mas^2]) does not
    suppress below ``floor``.
    """
    sig2_min = max(float(np.linalg.eigvalsh(cov)[:, 0].min(initial=np.inf)), 0.0)
    damp = plan.peak * np.exp(-2.0 * np.pi**2 * sig2_min * (plan.u**2 + plan.v**2))
    return np.flatnonzero(damp > floor)


def stamp_centre(pix) -> np.ndarray:
    """The pixel a star's stamp is centred on: its position rounded, halves up.

    A star exactly on a pixel boundary (``k + 0.5``) lands there only up to the
    round-off of the frame-centre offset ``(n - 1) / 2``, which differs between
    frame sizes; the boundary is therefore moved ``STAMP_CENTRE_BIAS`` pixels below
    the half, so that such a star gets the same stamp, offset by the same whole
    number of pixels, in every frame (the stamp is periodic: its centre pixel only
    decides which copy of the wing is kept, not where the star is).

    Parameters
    ----------
    pix : array-like
        Star positions [pixel].
    """
    return np.floor(np.asarray(pix, dtype=np.float64) + (0.5 + STAMP_CENTRE_BIAS)).astype(np.int64)


def _node_transforms_dft(cube, step: float, fy, fx) -> np.ndarray:
    """Direct DFT of every PSF node at integer frequencies ``fy`` x ``fx``.

    ``step`` is the frequency unit times the PSF pixel (cycles per PSF pixel);
    the optical axis is the central PSF pixel. Returns (nodes, nfy, nfx) complex.
    """
    nodes, n, _ = cube.shape
    offsets = np.arange(n) - (n - 1) / 2  # PSF pixels
    arg_x = -2.0 * np.pi * step * np.outer(offsets, fx)  # (n, nfx)
    # stage 1 over PSF columns: two real GEMMs for all nodes at once
    flat = cube.reshape(nodes * n, n)
    half = (flat @ np.cos(arg_x)) + 1j * (flat @ np.sin(arg_x))  # (nodes*n, nfx)
    half = half.reshape(nodes, n, len(fx))
    ey = np.exp(-2j * np.pi * step * np.outer(fy, offsets))  # (nfy, n)
    return np.matmul(ey[None], half)


def _node_transforms_fft(cube, requests, chunk: int = 8, workers: int = 1) -> list[np.ndarray]:
    """Same as :func:`_node_transforms_dft` for stamp periods of whole PSF pixels.

    ``requests`` is a list of ``(period, fy, fx)`` (period in PSF pixels) whose
    periods all divide the largest, ``B``. The DFT at frequencies ``q / period`` of
    a finely sampled PSF equals the FFT of that PSF wrapped (summed) onto ``period``
    samples with the optical axis at 0, and also the FFT of it wrapped onto ``B``
    samples taken at every ``B / period``-th frequency, so one FFT per node serves
    every request; this is exact, not an approximation. Nodes are done a few at a
    time. Returns one (nodes, len(fy), len(fx)) complex array per request.
    """
    import scipy.fft  # plans only (cached on disk): a warm frames process never imports it

    nodes = cube.shape[0]
    base = max(int(p) for p, _, _ in requests)
    outs, picks = [], []
    for period, fy, fx in requests:
        if base % int(period):
            raise ValueError(f"stamp period {period} does not divide {base}")
        step = base // int(period)
        iy = (np.asarray(fy, dtype=np.int64) % period) * step
        ix = (np.asarray(fx, dtype=np.int64) % period) * step
        # the nodes are real: rfft along x, negative frequencies by conjugate symmetry
        picks.append((iy, np.minimum(ix, base - ix), ix > base - ix))
        outs.append(np.empty((nodes, len(fy), len(fx)), dtype=np.complex128))
    for a in range(0, nodes, chunk):
        block = cube[a : a + chunk]
        wrapped = np.zeros((len(block), base, base))
        wrap_2d_into(block, base, wrapped)
        spec = scipy.fft.rfft2(wrapped, workers=workers)  # (c, B, B // 2 + 1)
        for out, (iy, ax, neg) in zip(outs, picks):
            sel = spec[:, iy][:, :, ax]
            # T(ky, -kx) = conj T(-ky, kx) for a real node
            sel[..., neg] = spec[:, (base - iy) % base][:, :, ax[neg]].conj()
            out[a : a + chunk] = sel
    return outs


def _wing_envelope(cube: np.ndarray, psf_scale: float, pixel_scale: float):
    """Envelope of each PSF node in detector-pixel units, against the square radius.

    The radius of a sample is its Chebyshev distance ``max(|dx|, |dy|)`` from the
    optical axis: a stamp is a square, and the light it misses (wrapped inside it) is
    the light outside the square of its half side, whatever its Euclidean radius. An
    AO PSF's wing is square too (the corrected region of the deformable mirror's
    actuator grid), so the square radius where it falls below a level is up to ~10 %
    smaller than the Euclidean one (MAVIS PSF database: 53.5 instead of 60 pixels at
    1e-7 of the flux), and the stamps of bright stars one or two sizes smaller.

    Returns
    -------
    radii : ndarray (nr,)
        Square radii in detector pixels (0, 0.5, 1, ...).
    env : ndarray (n_nodes, nr)
        Upper bound of the fraction of a star's flux in one detector pixel at or
        beyond each square radius, per node, non-increasing in radius.
    """
    n = cube.shape[-1]
    c = (n - 1) / 2
    yy, xx = np.mgrid[0:n, 0:n]
    r_pix = np.maximum(abs(xx - c), abs(yy - c)).ravel() * psf_scale / pixel_scale
    radii = np.arange(0.0, r_pix.max() + 1.0, 0.5)
    # bin k holds the samples with radii[k] <= r < radii[k + 1]; the envelope at
    # radii[k] is the largest bin maximum at or beyond k
    bins = np.minimum(np.floor(r_pix / 0.5).astype(np.int64), len(radii) - 1)
    bin_max = np.zeros((len(cube), len(radii)))
    binned_max(cube.reshape(len(cube), -1), bins, len(radii), bin_max)
    env = np.maximum.accumulate(bin_max[:, ::-1], axis=1)[:, ::-1]
    # a detector pixel holds about (s/p)^2 PSF samples; clip so it never exceeds 1
    return radii, np.minimum(env * (pixel_scale / psf_scale) ** 2, 1.0)


def _blur_envelope(radii, env, sigma: float, r_out=None):
    """The wing envelope ``env`` convolved with a 1-D Gaussian of ``sigma`` pixels (a bound).

    ``env[:, k]`` bounds the PSF at square radii ``>= radii[k]`` (steps of 0.5 pixel), so
    on ``|x|`` in ``[radii[k], radii[k] + 0.5)`` the function ``env(|x|)`` is at most
    ``env[:, k]`` (and 0 beyond the last radius); its convolution with the Gaussian at
    ``R`` is at most the sum over ``k`` of ``env[:, k]`` times the Gaussian's mass on
    those two intervals (exact, from ``erf``). The result is symmetric and unimodal in
    ``R``, hence non-increasing on the returned radii.

    Parameters
    ----------
    radii : ndarray (nr,)
        0, 0.5, 1, ... [pixel].
    env : ndarray (n, nr)
        Envelopes, non-increasing along the radius.
    sigma : float
        Gaussian sigma [pixel]; 0 returns ``env`` on ``r_out`` (0 beyond ``radii``).
    r_out : ndarray, optional
        Radii of the result, on the grid of ``radii`` (default: ``radii`` extended by 8
        sigma).

    Returns
    -------
    r_out : ndarray (nr_out,)
    blurred : ndarray (n, nr_out)
    """
    import math

    dr = 0.5
    nr = len(radii)
    if r_out is None:
        r_out = np.arange(0.0, radii[-1] + dr + 8 * sigma + dr, dr)
    n_out = len(r_out)
    if sigma <= 0:
        out = np.zeros((len(env), n_out))
        out[:, : min(nr, n_out)] = env[:, :n_out]
        return r_out, out
    # the Gaussian's CDF at every multiple of dr that the interval ends take
    top = n_out + nr + 1
    near = min(top, int(10 * sigma / dr) + 1)  # beyond 10 sigma the CDF is 0 or 1
    half = np.ones(top + 1)
    half[:near] = [0.5 * (1.0 + math.erf(j * dr / (sigma * math.sqrt(2.0)))) for j in range(near)]
    cdf = np.concatenate([1.0 - half[:0:-1], half])  # at -top..top (symmetric)

    def at(j):  # CDF at j * dr
        return cdf[j + top]

    i = np.arange(n_out)[:, None]
    k = np.arange(nr)[None, :]
    mass = (at(i - k) - at(i - k - 1)) + (at(i + k + 1) - at(i + k))
    blurred = env @ mass.T
    # non-increasing to round-off (the bound is unimodal): enforce it for searchsorted
    return r_out, np.maximum.accumulate(blurred[:, ::-1], axis=1)[:, ::-1]


def _sizing_envelopes(radii, env, steps: int, step: float) -> list:
    """For ``k = 0..steps``: the largest of ``env`` blurred by ``0, step, ..., k step`` pixels.

    See ``StarRenderer._blurred_envelope``: entry ``k`` bounds the PSF convolved with any
    Gaussian kernel whose marginal sigmas are at most ``k step`` (on the grid of sigmas).

    Returns
    -------
    list of (radii, envelope)
        Per ``k``, radii extended 8 ``k step`` beyond ``radii`` and the envelopes on them.
    """
    r_top, _ = _blur_envelope(radii, env, steps * step)
    out, best = [], None
    for k in range(steps + 1):
        _, blurred = _blur_envelope(radii, env, k * step, r_top)
        best = blurred if best is None else np.maximum(best, blurred)
        n_k = len(np.arange(0.0, radii[-1] + 1.0 + 8 * k * step, 0.5))  # _blur_envelope's
        out.append((r_top[:n_k], best[:, :n_k].copy()))
    return out


def _value(q, unit: str) -> float:
    """Float value of a Quantity in ``unit``, or the number itself."""
    if hasattr(q, "to_value"):
        return q.to_value(unit)
    return q
