"""Detector pixel response: intra-pixel sensitivity and the flat-field residual.

Intra-pixel sensitivity (paper tab:astrobudget, "CCD pixel QE inhomogeneity"). A CCD pixel
is less sensitive near its edges, where photo-electrons diffuse into the neighbours and
the gate structure absorbs. mavispm models the response across a pixel of side ``s`` as
separable, ``S(xi, eta) = p(xi) p(eta)`` with

    p(xi) = (1 - a (2 xi / s)^2) / (1 - a / 3),     |xi| <= s / 2,

a parabolic dip of relative depth ``a`` at the edges, normalised to a mean of 1 (so the
total quantum efficiency is unchanged). ``a = 0`` is the uniform box of today's frames.
The renderer integrates each star over its pixels in the Fourier domain, where the pixel
enters as the transform of ``p`` (``sinc(u s)`` for the box): :func:`pixel_transfer`.

Flat-field residual. Pixel-to-pixel QE variations left after flat-fielding, a fixed
pattern of the detector (the same in every epoch): each pixel's response is multiplied by
``1 + r g`` with ``g`` a standard normal deviate drawn once per detector from
``flat_seed`` and ``r`` the RMS residual (:func:`flat_field_residual`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["flat_field_residual", "pixel_transfer"]

#: Gauss-Legendre nodes for the transform of the intra-pixel profile (exact for the
#: polynomial and accurate to 1e-15 for the cosine up to the stamps' highest frequency)
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(48)


def pixel_transfer(frequency: np.ndarray, pixel: float, amplitude: float = 0.0) -> np.ndarray:
    """Fourier transform of the pixel response along one axis.

    Parameters
    ----------
    frequency : array
        Spatial frequency [cycles per unit of ``pixel``].
    pixel : float
        Pixel side (same length unit as ``1 / frequency``).
    amplitude : float
        Relative sensitivity dip ``a`` at the pixel edges (0 <= a < 1).

    Returns
    -------
    numpy.ndarray
        Real transfer function, 1 at zero frequency; ``sinc(frequency * pixel)`` for
        ``amplitude = 0`` (bit for bit).
    """
    frequency = np.asarray(frequency, float)
    if amplitude == 0.0:
        return np.sinc(frequency * pixel)
    if not 0.0 <= amplitude < 1.0:
        raise ValueError(f"intra-pixel amplitude must be in [0, 1), got {amplitude}")
    x = 0.5 * _NODES  # positions across the pixel in units of s, in (-1/2, 1/2)
    profile = (1.0 - amplitude * (2.0 * x) ** 2) / (1.0 - amplitude / 3.0)
    phase = 2.0 * np.pi * np.multiply.outer(frequency * pixel, x)
    return np.cos(phase) @ (0.5 * _WEIGHTS * profile)


def flat_field_residual(shape: tuple[int, int], rms: float, seed: int) -> np.ndarray | None:
    """The fixed multiplicative pixel pattern ``1 + rms g`` (float32), or None for ``rms = 0``.

    ``g`` is standard normal per pixel.

    Parameters
    ----------
    shape : tuple of int
        Detector shape ``(ny, nx)``.
    rms : float
        Relative RMS of the pattern, in [0, 0.2).
    seed : int
        Seed of the pattern (fixed per detector).

    Returns
    -------
    ndarray of float32 or None
        The pattern (dimensionless).

    Raises
    ------
    ValueError
        For ``rms`` outside [0, 0.2).
    """
    if rms == 0.0:
        return None
    if not 0.0 < rms < 0.2:
        raise ValueError(f"flat-field residual must be in [0, 0.2), got {rms}")
    rng = np.random.default_rng(seed)
    pattern = rng.standard_normal(shape, dtype=np.float32)
    pattern *= np.float32(rms)
    pattern += np.float32(1.0)
    return pattern
