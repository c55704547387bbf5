"""Simple PSF figures of merit: FWHM, Strehl from the peak, encircled energy."""

from __future__ import annotations

import numpy as np

__all__ = [
    "encircled_energy",
    "fwhm",
    "peak_strehl",
]


def fwhm(psf: np.ndarray, pixel_scale: float) -> float:
    """Equivalent-circle FWHM: diameter of the disc with the area above half maximum.

    The area is counted with a linear sub-pixel weight for pixels between 0.4
    and 0.6 of the peak, which removes most of the pixel quantisation.

    Parameters
    ----------
    psf : ndarray
        PSF stamp.
    pixel_scale : float
        Pixel size (any angular unit; the FWHM is returned in the same unit).
    """
    rel = np.asarray(psf, float) / np.max(psf)
    weight = np.clip((rel - 0.4) / 0.2, 0.0, 1.0)
    area = weight.sum() * pixel_scale**2
    return float(2 * np.sqrt(area / np.pi))


def peak_strehl(psf: np.ndarray, reference: np.ndarray) -> float:
    """Strehl ratio as the peak of ``psf`` over the peak of the diffraction-limited
    ``reference`` (both normalised to the same total flux).

    Parameters
    ----------
    psf : ndarray
        The PSF stamp.
    reference : ndarray
        The diffraction-limited PSF on the same pixels, same total.

    Returns
    -------
    float
        Strehl ratio (dimensionless).
    """
    return float(np.max(psf) / np.max(reference))


def encircled_energy(psf: np.ndarray, pixel_scale: float, radius: float) -> float:
    """Fraction of the stamp's flux within ``radius`` of the centre pixel.

    Parameters
    ----------
    psf : ndarray, shape (n, n)
        The PSF stamp (odd size, centred).
    pixel_scale : float
        Pixel size, in the unit of ``radius`` (e.g. [mas]).
    radius : float
        Radius, same unit.

    Returns
    -------
    float
        Encircled fraction of the stamp's total.
    """
    n = psf.shape[0]
    c = (n - 1) / 2
    y, x = np.indices(psf.shape)
    return float(psf[np.hypot(x - c, y - c) * pixel_scale <= radius].sum() / psf.sum())
