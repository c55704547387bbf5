"""Broadband PSFs: monochromatic PSF slices weighted by a star's spectrum and shifted by DAR.

Through a filter a star's image is the sum over wavelength of monochromatic images,
each weighted by the star's detected photons at that wavelength and displaced by that
wavelength's differential atmospheric refraction (after the ADC) along the zenith
direction::

    K(r) = integral w(lambda) P_lambda(r - d(lambda) e) dlambda,

``w`` the black-body photon fractions of the star's ``teff`` through the band,
``d = adc_residual (R(lambda) - R(reference_wavelength))`` (see
:mod:`mavispm.simulate.optics.refraction`) and ``e`` the unit vector towards the zenith.

The band is cut into ``slices`` sub-bands holding equal shares of the band's response;
each is represented by one monochromatic PSF ``P_k`` at its response-weighted mean
wavelength ``lambda_k``, weighted by the star's photon fraction ``w_k`` in it and
shifted by the photon-weighted mean refraction ``d_k`` within it. The spread of the
refraction inside each sub-band, ``sum_k w_k var_k``, is added as a Gaussian along the
zenith. The kernel's centroid is then exactly the photon-weighted mean refraction of
the whole band (``sum_k w_k d_k``) and its second moment along the zenith exactly the
monochromatic one plus the in-band refraction variance (law of total variance); only
the shape inside each sub-band is approximated.

Stars share a kernel within ``colour_bins`` equal-count bins of effective temperature
(the mean refraction is monotonic in it; the renderer mixes the slice transforms once
per bin); each star keeps its own exact mean
shift and in-sub-band variance. ``slices = 1`` is the monochromatic PSF at the grid
wavelength with the mean shift only, i.e. the renderer as it was.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavispm.simulate.optics.refraction import (
    RefractionSettings,
    at_epoch,
    band_response,
    photon_weights,
    refraction,
)

#: Stars per block of the (stars x band wavelengths) arrays (~40 MB each).
_CHUNK = 10000

__all__ = [
    "BroadbandSettings",
    "SliceSpectrum",
    "broadband_psf",
    "colour_bins",
    "slice_groups",
    "slice_spectrum",
    "slice_wavelengths",
]


@dataclass(frozen=True)
class BroadbandSettings:
    """Broadband PSF slicing (TOML table ``[scene.optics.broadband]``).

    Parameters
    ----------
    slices : int
        Monochromatic PSF slices across the band of ``[scene.optics.refraction]``
        (1: the monochromatic PSF at ``psf.wavelength``, as without this table).
    colour_bins : int
        Equal-count bins of stars (by effective temperature) sharing one broadband kernel.
    """

    slices: int = 1
    colour_bins: int = 8

    def __post_init__(self):
        if not 1 <= self.slices <= 16:
            raise ValueError(f"slices must be 1 to 16, got {self.slices}")
        if not 1 <= self.colour_bins <= 64:
            raise ValueError(f"colour_bins must be 1 to 64, got {self.colour_bins}")


@dataclass(frozen=True)
class SliceSpectrum:
    """Per-star slice weights and DAR shifts.

    Parameters
    ----------
    weights : numpy.ndarray (N, K)
        Photon fraction of each star in each sub-band (rows sum to 1).
    shifts : numpy.ndarray (N, K)
        Mean DAR shift within each sub-band along the zenith, after the ADC and
        relative to the reference wavelength [arcsec].
    variance : numpy.ndarray (N,)
        Photon-weighted variance of the shift inside the sub-bands [arcsec^2].
    direction : tuple of float
        Unit vector towards the zenith on the detector ``(cos, sin)``.
    """

    weights: np.ndarray
    shifts: np.ndarray
    variance: np.ndarray
    direction: tuple[float, float]

    @property
    def mean(self) -> np.ndarray:
        """Photon-weighted mean shift of each star [arcsec] (its centroid shift)."""
        return np.sum(self.weights * self.shifts, axis=1)

    @property
    def total_variance(self) -> np.ndarray:
        """In-band variance of each star's shift [arcsec^2] (between + within sub-bands)."""
        between = np.sum(self.weights * (self.shifts - self.mean[:, None]) ** 2, axis=1)
        return between + self.variance


def slice_groups(settings: RefractionSettings, n_slices: int) -> np.ndarray:
    """Sub-band index of every wavelength of :func:`band_response`: equal response shares.

    Parameters
    ----------
    settings : RefractionSettings
        The band.
    n_slices : int

    Returns
    -------
    numpy.ndarray (L,) int
        0 to ``n_slices - 1``, non-decreasing in wavelength.
    """
    lam, response = band_response(settings)
    if n_slices > 1 and len(lam) == 1:
        raise ValueError(
            "scene.optics.broadband.slices > 1 needs a band: refraction.band is 'monochromatic'"
        )
    cum = np.cumsum(response) - 0.5 * response
    frac = cum / max(float(response.sum()), 1e-300)
    return np.clip(np.floor(frac * n_slices).astype(np.int64), 0, n_slices - 1)


def slice_wavelengths(settings: RefractionSettings, n_slices: int) -> np.ndarray:
    """Response-weighted mean wavelength of each sub-band [nm] (where its PSF is computed).

    Parameters
    ----------
    settings : RefractionSettings
        The band (``band``, its limits) of ``[scene.optics.refraction]``.
    n_slices : int
        Number of sub-bands.

    Returns
    -------
    ndarray, shape (n_slices,)
        Wavelengths [nm].
    """
    lam, response = band_response(settings)
    group = slice_groups(settings, n_slices)
    num = np.bincount(group, response * lam, n_slices)
    den = np.bincount(group, response, n_slices)
    return num / den


def slice_spectrum(
    teff, settings: RefractionSettings, n_slices: int, epoch: float | None = None
) -> SliceSpectrum:
    """Photon weights and DAR shifts of each star in each sub-band.

    With refraction disabled the shifts and variances are zero (the weights still
    follow the star's colour).

    Parameters
    ----------
    teff : float or array
        Effective temperature [K] (NaN takes ``settings.default_teff``).
    settings : RefractionSettings
        Band, atmosphere, ADC and pointing.
    n_slices : int
    epoch : float, optional
        Epoch [yr] selecting a per-epoch pointing.

    Returns
    -------
    SliceSpectrum
        ``mean`` equals :func:`~mavispm.simulate.optics.refraction.star_displacement`
        along the zenith.
    """
    settings = at_epoch(settings, epoch)
    teff = np.atleast_1d(np.asarray(teff, float))
    teff = np.where(np.isfinite(teff), teff, settings.default_teff)
    group = slice_groups(settings, n_slices)
    lam, _ = band_response(settings)
    onehot = np.zeros((len(lam), n_slices))
    onehot[np.arange(len(lam)), group] = 1.0
    d = settings.adc_residual * (refraction(lam, settings) - refraction(
        settings.reference_wavelength, settings
    ))  # fmt: skip
    weights = np.empty((teff.size, n_slices))
    shifts = np.zeros((teff.size, n_slices))
    variance = np.zeros(teff.size)
    for a in range(0, teff.size, _CHUNK):  # (stars x wavelengths) work arrays, bounded
        part = slice(a, a + _CHUNK)
        w = photon_weights(teff[part], settings)[1]
        weights[part] = w @ onehot
        if settings.enabled:
            safe = np.where(weights[part] > 0, weights[part], 1.0)
            shifts[part] = (w * d) @ onehot / safe
            second = (w * d**2) @ onehot / safe
            within = np.maximum(second - shifts[part] ** 2, 0.0)
            variance[part] = np.sum(weights[part] * within, axis=1)
    theta = np.radians(settings.zenith_direction)
    return SliceSpectrum(weights, shifts, variance, (np.cos(theta), np.sin(theta)))


def colour_bins(mean_shift, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Bins of stars by mean shift, equal in number, and each bin's representative star.

    Parameters
    ----------
    mean_shift : array (N,)
        Any scalar colour measure (the renderer uses the effective temperature).
    n_bins : int

    Returns
    -------
    index : numpy.ndarray (N,) int
        Bin of each star.
    representative : numpy.ndarray (B,) int
        A star of each (non-empty) bin, its median member; bins are renumbered 0..B-1.
    """
    v = np.asarray(mean_shift, float)
    if v.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(v, kind="stable")
    rank = np.empty(v.size, dtype=np.int64)
    rank[order] = np.arange(v.size)
    index = rank * min(n_bins, v.size) // v.size
    used, index = np.unique(index, return_inverse=True)
    rep = np.empty(len(used), dtype=np.int64)
    for b in range(len(used)):
        members = order[index[order] == b]
        rep[b] = members[len(members) // 2]
    return index.astype(np.int64), rep


def broadband_psf(
    monochromatic, pixel_scale: float, weights, shifts, spread_cov=None
) -> np.ndarray:
    """The broadband PSF image: weighted, shifted monochromatic slices (Fourier shift).

    Parameters
    ----------
    monochromatic : array (K, n, n)
        Monochromatic PSF images (same sampling, optical axis at the central pixel).
    pixel_scale : float
        Their pixel [mas].
    weights : array (K,)
        Photon fractions.
    shifts : array (K, 2)
        Shift of each slice ``(dx, dy)`` [mas].
    spread_cov : array (2, 2), optional
        Covariance of a Gaussian the sum is convolved with [mas^2] (the in-sub-band
        spread ``variance e e^T``).

    Returns
    -------
    numpy.ndarray (n, n)
        The broadband PSF, periodic on the stamp (a band-limited, Nyquist-sampled
        input is shifted exactly). One slice with zero shift and no spread returns the
        monochromatic PSF unchanged.
    """
    mono = np.asarray(monochromatic, float)
    weights = np.asarray(weights, float)
    shifts = np.asarray(shifts, float).reshape(len(mono), 2)
    if len(mono) == 1 and not np.any(shifts) and spread_cov is None:
        return mono[0] * weights[0]
    n_y, n_x = mono.shape[-2:]
    fy = np.fft.fftfreq(n_y, pixel_scale)[:, None]
    fx = np.fft.rfftfreq(n_x, pixel_scale)[None, :]
    # the optical axis at the central pixel: transform about it
    centred = np.fft.ifftshift(mono, axes=(-2, -1))
    spec = np.fft.rfft2(centred, axes=(-2, -1))
    phase = np.exp(
        -2j * np.pi * (fx[None] * shifts[:, 0, None, None] + fy[None] * shifts[:, 1, None, None])
    )
    total = np.einsum("k,kij->ij", weights, spec * phase)
    if spread_cov is not None:
        c = np.asarray(spread_cov, float)
        total = total * np.exp(
            -2 * np.pi**2 * (c[0, 0] * fx**2 + 2 * c[0, 1] * fx * fy + c[1, 1] * fy**2)
        )
    out = np.fft.irfft2(total, s=(n_y, n_x))
    return np.fft.fftshift(out)
