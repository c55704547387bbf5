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

from dataclasses import dataclass

import numpy as np

from mavispm.core.config import unit_field

#: Pixels whose sub-exposure mean lies more than this many sigma below the
#: saturation level are treated as never saturating (probability < 1e-20).
SATURATION_SAFETY_SIGMA = 10.0


@dataclass(frozen=True)
class DetectorSettings:
    """Detector of a scene (TOML table ``[detector]``).

    Attributes
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
    """

    nx: int = 4000
    ny: int = 4000
    pixel_scale: float = unit_field(7.5, "mas")
    read_noise: float = unit_field(3.0, "electron")
    gain: float = unit_field(1.0, "electron / adu")
    bits: int = 16

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
        Where the skewness of Poisson(nexp mu) + read noise, ``nexp mu / var**1.5``,
        is below this value the sum is drawn as a Gaussian with its exact mean and
        variance ``var = nexp (mu + RN^2)`` (much faster); elsewhere exactly. 0: always exact.

    Returns
    -------
    image_adu : ndarray (ny, nx) float32
        The summed stack in adu.
    saturated : ndarray (ny, nx) bool
        Pixels saturated in at least one sub-exposure.
    """
    if nexp < 1:
        raise ValueError(f"nexp must be >= 1, got {nexp}")
    mu = np.clip(np.asarray(mean_electrons, dtype=np.float32), 0.0, None)
    full = settings.saturation_electrons
    rn = settings.read_noise
    if not noise:
        clipped = np.minimum(mu, np.float32(full))
        return clipped * np.float32(nexp / settings.gain), mu >= full
    flat_mu = mu.reshape(-1)
    var_rn = nexp * rn**2
    # fast path everywhere (float32): a Gaussian with the exact mean and variance of the sum
    lam = flat_mu * np.float32(nexp)
    total = np.sqrt(lam + np.float32(var_rn))
    total *= rng.standard_normal(lam.shape, dtype=np.float32)
    total += lam
    # exact Poisson + Gaussian where the skewness lam / var**1.5 of the sum reaches the
    # limit; since var >= max(lam, var_rn), only lam in [limit var_rn**1.5, limit**-2]
    if skew_limit > 0:
        lo, hi = skew_limit * var_rn**1.5, skew_limit**-2
        cand = np.flatnonzero((lam >= lo) & (lam <= hi))
        lam_c = lam[cand].astype(np.float64)
        exact = cand[lam_c >= skew_limit * (lam_c + var_rn) ** 1.5]
    else:
        exact = np.arange(lam.size)
    lam_e = lam[exact].astype(np.float64)
    total[exact] = rng.poisson(lam_e) + rng.normal(0.0, np.sqrt(var_rn), lam_e.size)
    # pixels that can saturate in a sub-exposure: drawn and clipped one by one
    saturated = np.zeros(lam.shape, dtype=bool)
    cand = np.flatnonzero(flat_mu >= full - SATURATION_SAFETY_SIGMA * np.sqrt(full + rn**2))
    mu_c = flat_mu[cand].astype(np.float64)
    risky = cand[mu_c + SATURATION_SAFETY_SIGMA * np.sqrt(mu_c + rn**2) >= full]
    if risky.size:
        mu_r = flat_mu[risky].astype(np.float64)
        subs = rng.poisson(np.broadcast_to(mu_r, (nexp, mu_r.size))).astype(np.float64)
        subs += rng.normal(0.0, rn, subs.shape)
        saturated[risky] = np.any(subs >= full, axis=0)
        total[risky] = np.minimum(subs, full).sum(axis=0)
    total *= np.float32(1.0 / settings.gain)
    return total.reshape(mu.shape), saturated.reshape(mu.shape)
