"""The detector: photon noise, read noise, gain and 16-bit saturation of a stack.

A frame is the sum of ``nexp`` sub-exposures of a static scene. The expected
electrons per pixel of one sub-exposure, ``mu``, are rendered once; the stack is

    S = sum_i min(Poisson(mu) + Normal(0, RN), full_well_i)

For pixels that can never reach saturation in a sub-exposure (``mu`` many sigma
below the level) the clip is a no-op, the sum of the ``nexp`` Poisson draws is one
Poisson draw of ``nexp * mu`` and the read noise adds in quadrature, so the noise of
the sum is drawn once (optionally as a Gaussian with the exact mean and variance
where the skewness of the sum is negligible, e.g. read-noise dominated sky). The few pixels that can saturate are drawn sub-exposure by
sub-exposure and clipped individually, so saturation acts per sub-exposure exactly.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np

from mavispm.core.config import unit_field
from mavispm.core.cores import usable_cores

__all__ = [
    "DetectorSettings",
    "NOISE_CHUNK",
    "SATURATION_SAFETY_SIGMA",
    "expose_stack",
    "normal_stack_draws",
    "skewed_normal",
]

#: Pixels per chunk of the vectorised noise draw (fits in cache; fixes the random streams).
NOISE_CHUNK = 1 << 18

#: Pixels whose sub-exposure mean lies more than this many sigma below the
#: saturation level are treated as never saturating (probability < 1e-20).
SATURATION_SAFETY_SIGMA = 10.0


@dataclass(frozen=True)
class DetectorSettings:
    """Detector of a scene (TOML table ``[detector]``).

    Parameters
    ----------
    nx, ny : int
        Frame size in pixels (4000 x 4000 covers 30" x 30" at 7.5 mas).
    pixel_scale : float
        Pixel size, mas (7.5 in the paper; the CCD250 baseline is 7.36).
    read_noise : float
        Read noise per sub-exposure, electron (3).
    gain : float
        Conversion gain, electron/adu (1.0).
    bits : int
        ADC depth; one sub-exposure saturates at ``2**bits - 1`` adu (16 bits: 65535 adu).
    intrapixel_amplitude : float
        Relative sensitivity dip at the pixel edges (0: uniform pixels); see
        ``simulate/render/pixel_response.py``.
    flat_residual : float
        RMS of the pixel-to-pixel QE pattern left after flat-fielding (0: none).
    flat_seed : int
        Seed of that fixed pattern (one detector: the same in every epoch).
    """

    nx: int = 4000
    ny: int = 4000
    pixel_scale: float = unit_field(7.5, "mas")
    read_noise: float = unit_field(3.0, "electron")
    gain: float = unit_field(1.0, "electron / adu")
    bits: int = 16
    intrapixel_amplitude: float = 0.0
    flat_residual: float = 0.0
    flat_seed: int = 0

    def __post_init__(self):
        if self.nx < 1 or self.ny < 1:
            raise ValueError(f"detector.nx and detector.ny must be >= 1, got {self.nx}, {self.ny}")
        if not self.pixel_scale > 0:
            raise ValueError(f"detector.pixel_scale must be > 0 mas, got {self.pixel_scale}")
        if self.read_noise < 0:
            raise ValueError(f"detector.read_noise must be >= 0, got {self.read_noise}")
        if not self.gain > 0:
            raise ValueError(f"detector.gain must be > 0, got {self.gain}")
        if not 1 <= self.bits <= 32:
            raise ValueError(f"detector.bits must be in [1, 32], got {self.bits}")
        if not 0.0 <= self.intrapixel_amplitude < 1.0:
            raise ValueError(
                f"detector.intrapixel_amplitude must be in [0, 1), got {self.intrapixel_amplitude}"
            )
        if not 0.0 <= self.flat_residual < 0.2:
            raise ValueError(
                f"detector.flat_residual must be in [0, 0.2), got {self.flat_residual}"
            )

    @property
    def saturation_adu(self) -> float:
        """Saturation level of one sub-exposure (adu)."""
        return float(2**self.bits - 1)

    @property
    def saturation_electrons(self) -> float:
        """Saturation level of one sub-exposure (electron)."""
        return self.saturation_adu * self.gain


def expose_stack(
    mean_electrons: np.ndarray,
    nexp: int,
    settings: DetectorSettings,
    rng: np.random.Generator,
    noise: bool = True,
    skew_limit: float = 0.0,
    threads: int = 1,
    poisson_skew_limit: float | None = None,
    out: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Read out a stack of ``nexp`` sub-exposures of a static scene.

    Parameters
    ----------
    mean_electrons : ndarray (ny, nx)
        Expected electrons per pixel in ONE sub-exposure (stars + halo + sky), >= 0.
    nexp : int
        Number of sub-exposures summed.
    settings : DetectorSettings
    rng : numpy.random.Generator
    noise : bool
        False gives the noise-free stack (still clipped per sub-exposure).
    skew_limit : float
        Where the skewness of Poisson(nexp mu) + read noise, ``g = nexp mu / var**1.5``,
        is below this value the sum is drawn as a Gaussian with its exact mean and
        variance ``var = nexp (mu + RN^2)`` (much faster). 0: always exact.
    threads : int
        Threads for the per-pixel work (0: all cores); the result does not depend on it.
    poisson_skew_limit : float, optional
        Where ``g`` is at least this value the sum is drawn exactly (Poisson +
        Gaussian); between ``skew_limit`` and it, as a skew-corrected Gaussian
        (:func:`skewed_normal`: exact mean and variance, skewness ``g`` to
        ``O(g**3)``). Default: ``skew_limit`` (no skew-corrected tier). Ignored when
        ``skew_limit`` is 0 (exact everywhere).
    out : ndarray (ny, nx) float32, optional
        Write the stack here (and return it) instead of into a new array. It may be
        ``mean_electrons`` itself (C-contiguous float32), which is then overwritten
        chunk by chunk once each chunk's means are read: the frames program's 64 MB of
        fresh memory for a 4000 x 4000 stack saved; the same values either way.

    Returns
    -------
    image_adu : ndarray (ny, nx) float32
        The summed stack in adu (``out`` when given).
    saturated : ndarray (ny, nx) bool
        Pixels saturated in at least one sub-exposure.
    """
    if nexp < 1:
        raise ValueError(f"nexp must be >= 1, got {nexp}")
    full = settings.saturation_electrons
    rn = settings.read_noise
    mean = np.asarray(mean_electrons)
    in_place = _check_out(out, mean)
    if not noise:
        if out is None:
            mu = np.array(mean, dtype=np.float32, copy=True)
        else:
            mu = out
            np.copyto(mu, mean)  # nothing to copy when out is mean itself
        np.clip(mu, 0.0, np.float32(full), out=mu)
        saturated = mu >= full
        mu *= np.float32(nexp / settings.gain)
        return mu, saturated
    if mean.dtype not in (np.float32, np.float64):
        mean = mean.astype(np.float64)
    flat_mu = mean.reshape(-1)
    var_rn = nexp * rn**2
    # in chunks on `threads` threads, one generator per chunk so the result does not
    # depend on the thread count: a Gaussian with the exact mean and variance of the
    # sum (float32), skew-corrected or exact where its skewness matters
    total = np.empty(flat_mu.size, dtype=np.float32) if out is None else out.reshape(-1)
    starts = range(0, flat_mu.size, NOISE_CHUNK)
    chunk_rngs = rng.spawn(len(starts))
    # skew_limit = 0 means exact draws everywhere, whatever poisson_skew_limit says
    exact_limit = skew_limit
    if poisson_skew_limit is not None and skew_limit > 0:
        exact_limit = max(poisson_skew_limit, skew_limit)
    lo, hi = _skewed_window(var_rn, exact_limit)
    corrected = 0 < skew_limit < exact_limit
    risky_floor = full - SATURATION_SAFETY_SIGMA * np.sqrt(full + rn**2)

    def chunk(args):
        start, crng = args
        sl = slice(start, start + NOISE_CHUNK)
        mu_chunk = flat_mu[sl]
        # what the chunk's means decide, read before an in-place draw overwrites them:
        # the exact Poisson + Gaussian where the skewness lam / var**1.5 of the sum
        # reaches the limit, the window [lo, hi] of lam where it does (see
        # _skewed_window), and the pixels that may saturate
        exact = None
        if lo <= hi:
            lam = np.maximum(mu_chunk, 0.0) * float(nexp)
            exact = np.flatnonzero((lam >= lo) & (lam <= hi))
            lam_exact = lam[exact]
        risky = np.flatnonzero(mu_chunk >= risky_floor)
        mu_risky = mu_chunk[risky]
        # in place: the chunk is drawn into a scratch array (cache-sized) and copied
        # over its means (a compiled loop reading and writing one array through two
        # arguments is not vectorised: ~2x the CPU of the draw)
        out_chunk = np.empty(mu_chunk.size, np.float32) if in_place else total[sl]
        # the chunk's standard normals (numpy's float32 sampler, run compiled on the
        # generator's PCG64 state: the same stream), then Gaussian, skew-corrected where
        # skewness >= skew_limit
        z = _draw_chunk(
            mu_chunk, crng, nexp, var_rn, skew_limit if corrected else np.inf, out_chunk
        )
        if exact is not None and exact.size:
            counts = crng.poisson(lam_exact)
            out_chunk[exact] = counts + np.sqrt(var_rn) * z[exact].astype(np.float64)
        if in_place:
            total[sl] = out_chunk
        return risky + start, mu_risky

    results = _map_threads(chunk, zip(starts, chunk_rngs), threads)
    risky_c = np.concatenate([r[0] for r in results]) if results else np.zeros(0, int)
    mu_c = np.concatenate([r[1] for r in results]).astype(np.float64) if results else None
    # pixels that can saturate in a sub-exposure: drawn and clipped one by one
    saturated = np.zeros(flat_mu.shape, dtype=bool)
    if mu_c is None:
        mu_c = np.zeros(0)
    can = mu_c + SATURATION_SAFETY_SIGMA * np.sqrt(mu_c + rn**2) >= full
    risky = risky_c[can]
    if risky.size:
        mu_r = mu_c[can]
        subs = rng.poisson(np.broadcast_to(mu_r, (nexp, mu_r.size))).astype(np.float64)
        subs += rng.normal(0.0, rn, subs.shape)
        saturated[risky] = np.any(subs >= full, axis=0)
        total[risky] = np.minimum(subs, full).sum(axis=0)
    if settings.gain != 1.0:  # a pass over the frame for nothing at unit gain
        total *= np.float32(1.0 / settings.gain)
    stack = total.reshape(mean.shape) if out is None else out
    return stack, saturated.reshape(mean.shape)


def _check_out(out: np.ndarray | None, mean: np.ndarray) -> bool:
    """Check :func:`expose_stack`'s ``out``; True when it is ``mean`` itself (in place)."""
    if out is None:
        return False
    if out.dtype != np.float32 or out.shape != mean.shape or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {mean.shape}")
    if not np.may_share_memory(out, mean):
        return False
    same = (
        mean.dtype == np.float32
        and mean.flags.c_contiguous
        and out.__array_interface__["data"][0] == mean.__array_interface__["data"][0]
    )
    if not same:
        raise ValueError("out overlaps mean_electrons without being that array")
    return True


def skewed_normal(lam: np.ndarray, var_rn: float, z: np.ndarray, skew_limit: float) -> np.ndarray:
    """Draws of Poisson(lam) + N(0, var_rn) from standard normals ``z``, matching 3 moments.

    ``lam + sd (z + a (z**2 - 1)) / sqrt(1 + 2 a**2)`` with ``sd**2 = lam + var_rn``
    and ``a = g / 6``, ``g = lam / sd**3`` the skewness of the sum (the first
    Cornish-Fisher term): the mean and variance are exact, the skewness is ``g``
    to ``O(g**3)`` (relative error ``5 g**2 / 108``), and the excess kurtosis is
    ``4 g**2 / 3`` instead of ``lam / sd**4 = g / sd``, both < 2e-4 at the largest
    skewness of a MAVIS stack (0.012). Where ``g < skew_limit``, ``a = 0`` (a
    plain Gaussian with the exact mean and variance).

    Parameters
    ----------
    lam : ndarray
        Poisson means (electrons of the stack), float32 or float64.
    var_rn : float
        Read-noise variance of the stack (electron^2).
    z : ndarray
        Standard normal draws, same shape as ``lam``.
    skew_limit : float
        Below this skewness the correction is left out.
    """
    sd = np.sqrt(lam + var_rn)
    a = lam / (sd * sd * sd)
    a[~(a >= skew_limit)] = 0.0  # also 0/0 where lam = var_rn = 0
    a *= 1.0 / 6.0
    out = z * z
    out -= 1.0
    out *= a
    out += z
    a *= a
    a *= 2.0
    a += 1.0
    np.sqrt(a, out=a)
    out *= sd
    out /= a
    out += lam
    return out


# error_model="numpy": IEEE division (no ZeroDivisionError branch), which lets LLVM
# vectorise the loop (half the CPU of the draw, 16e6 pixels: ~0.09 -> ~0.05 s); the
# divisor is never 0 (the 1e-300 guard), so the results are the same bits.
@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def normal_stack_draws(mu, z, nexp, var_rn, skew_limit, out) -> None:  # pragma: no cover
    """Compiled :func:`skewed_normal` of ``lam = nexp * max(mu, 0)`` into ``out`` (float32).

    ``skew_limit = inf``: plain Gaussians with the exact mean and variance.

    Parameters
    ----------
    mu : ndarray
        Expected electrons per sub-exposure.
    z : ndarray
        Standard-normal deviates, one per pixel.
    nexp : int
        Sub-exposures in the stack.
    var_rn : float
        Read-noise variance of the stack [electron^2].
    skew_limit : float
        Skewness above which the skew correction applies (inf: none).
    out : ndarray of float32
        Receives the stacked electrons.
    """
    for i in range(mu.size):
        lam = max(mu[i], 0.0) * nexp
        sd = np.sqrt(lam + var_rn)
        g = lam / (sd * sd * sd + 1e-300)
        a = g * (1.0 / 6.0) if g >= skew_limit else 0.0
        zi = z[i]
        out[i] = lam + sd * (zi + a * (zi * zi - 1.0)) / np.sqrt(1.0 + 2.0 * a * a)


try:  # numba's copy of numpy's ziggurat tables, for the compiled sampler
    from mavispm.simulate.render.pcg64 import (
        pcg64_put,
        pcg64_take,
        standard_normals_f32_pcg64,
    )
except ImportError:  # pragma: no cover - a numba without them: numpy draws the normals
    _COMPILED_NORMALS = False
else:
    _COMPILED_NORMALS = True


@numba.njit(nogil=True, cache=True)
def _normal_stack_chunk(mu, state, z, nexp, var_rn, skew_limit, out):  # pragma: no cover
    """:func:`standard_normals_f32_pcg64` into ``z``, then :func:`normal_stack_draws`.

    One compiled call (one cached kernel to load per process instead of two).
    """
    standard_normals_f32_pcg64(state, z)
    normal_stack_draws(mu, z, nexp, var_rn, skew_limit, out)


def _draw_chunk(mu, rng, nexp, var_rn, skew_limit, out) -> np.ndarray:
    """The chunk's standard normals and its Gaussian draws.

    The normals are ``rng.standard_normal(mu.size, dtype=np.float32)``: the same
    numbers, and ``rng`` continues after them as it would after numpy's call. A PCG64
    generator (numpy's default, and every generator the frames command spawns) is
    stepped inside the compiled sampler (:mod:`mavispm.simulate.render.pcg64`, ~0.04 s
    per 16e6 draws against ~0.11 s through numba's bit-generator function pointer); any
    other goes through numpy.

    Returns
    -------
    ndarray of float32
        The standard normals drawn.
    """
    z = np.empty(mu.size, dtype=np.float32)
    state = pcg64_take(rng) if _COMPILED_NORMALS else None
    if state is None:
        rng.standard_normal(mu.size, dtype=np.float32, out=z)
        normal_stack_draws(mu, z, nexp, var_rn, skew_limit, out)
        return z
    _normal_stack_chunk(mu, state, z, nexp, var_rn, skew_limit, out)
    pcg64_put(rng, state)
    return z


def _skewed_window(var_rn: float, skew_limit: float) -> tuple[float, float]:
    """Range of the stack mean ``lam`` where the skewness of Poisson(lam) + N(0, var_rn) is large.

    The skewness ``lam / (lam + var_rn)**1.5`` rises from 0, peaks at
    ``lam = 2 var_rn`` and falls as ``lam**-0.5``; the window holds the ``lam`` where
    it is at least ``skew_limit`` (empty: ``lo > hi``). ``skew_limit = 0``: every ``lam``.
    """
    if skew_limit <= 0:
        return 0.0, np.inf

    def excess(lam):
        return lam / (lam + var_rn) ** 1.5 - skew_limit

    top = 2.0 * var_rn
    if var_rn <= 0:
        return 0.0, skew_limit**-2  # pure Poisson: skewness lam**-0.5
    if excess(top) < 0:
        return 1.0, 0.0
    lo = _bisect(excess, 0.0, top, xtol=1e-12, rtol=1e-12)
    hi = _bisect(excess, top, 2.0 * skew_limit**-2 + top, xtol=1e-9, rtol=1e-12)
    return lo, hi


def _bisect(f, a: float, b: float, xtol: float, rtol: float) -> float:
    """Root of ``f`` in ``[a, b]`` (opposite signs at the ends) by bisection.

    Used instead of ``scipy.optimize.brentq``, whose import costs ~0.5-2 s of every
    ``mavispm simulate frames`` process; the two roots here take ~50 halvings.
    """
    fa = f(a)
    for _ in range(200):
        m = 0.5 * (a + b)
        if b - a <= xtol + rtol * abs(m):
            break
        fm = f(m)
        if (fm < 0) == (fa < 0):
            a, fa = m, fm
        else:
            b = m
    return 0.5 * (a + b)


def _map_threads(fn, items, threads: int) -> list:
    """``list(map(fn, items))`` on up to ``threads`` threads (0: all cores), in order."""
    items = list(items)
    n = threads or usable_cores()
    if n <= 1 or len(items) <= 1:
        return [fn(it) for it in items]
    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(fn, items))
