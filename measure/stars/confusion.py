"""Confusion state of stars against a truth list (diagnosis of crowded frames).

For every target star: the distance to its nearest *comparable* neighbour, one at most
``dmag`` magnitudes fainter than itself (``mag_nb < mag + dmag``; ``dmag = 0`` means
strictly brighter), and the summed flux of all neighbours within a radius. On a uniform
field whose stars are a Poisson process of surface density ``n(<m)`` the nearest
comparable neighbour of a star of magnitude ``m`` lies within ``r`` with probability
``1 - exp(-pi r^2 n(<m + dmag))`` (:func:`poisson_within`): the analytic check of the
classification (tests/test_measure_confusion.py). docs/measure-scale.md, tenth pass.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["effective_fwhm", "nearest_comparable", "poisson_within"]


def nearest_comparable(
    x: np.ndarray,
    y: np.ndarray,
    mag: np.ndarray,
    radius: float,
    dmag: float = 1.0,
    flux_radius: float | None = None,
    flux: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest comparable neighbour and summed neighbour flux of every star.

    Parameters
    ----------
    x, y : ndarray, shape (N,)
        Positions [pixel] (the truth of a frame).
    mag : ndarray, shape (N,)
        Magnitudes.
    radius : float
        Search radius [pixel]; stars with no comparable neighbour within it get ``inf``.
    dmag : float
        A neighbour is comparable when ``mag_nb < mag + dmag``.
    flux_radius : float, optional
        Radius [pixel] of the summed neighbour flux (at most ``radius``); default ``radius``.
    flux : ndarray, shape (N,), optional
        Fluxes for the sum; default ``10**(-0.4 mag)``.

    Returns
    -------
    distance : ndarray, shape (N,)
        Distance [pixel] to the nearest comparable neighbour (``inf`` if none within
        ``radius``).
    neighbour_flux : ndarray, shape (N,)
        Summed flux of all other stars within ``flux_radius`` (any magnitude).
    """
    x, y, mag = (np.asarray(a, dtype=float) for a in (x, y, mag))
    flux = 10 ** (-0.4 * mag) if flux is None else np.asarray(flux, dtype=float)
    flux_radius = radius if flux_radius is None else float(flux_radius)
    if flux_radius > radius:
        raise ValueError("flux_radius must not exceed radius")
    n = len(x)
    distance = np.full(n, np.inf)
    neighbour_flux = np.zeros(n)
    if n < 2:
        return distance, neighbour_flux
    pairs = cKDTree(np.column_stack([x, y])).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return distance, neighbour_flux
    # both directions: star i with neighbour j
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    d = np.hypot(x[i] - x[j], y[i] - y[j])
    comparable = mag[j] < mag[i] + dmag
    np.minimum.at(distance, i[comparable], d[comparable])
    near = d <= flux_radius
    np.add.at(neighbour_flux, i[near], flux[j[near]])
    return distance, neighbour_flux


def poisson_within(radius: float | np.ndarray, density: float | np.ndarray) -> np.ndarray:
    """Probability that a Poisson process of ``density`` has a point within ``radius``.

    Parameters
    ----------
    radius : float or ndarray
        Radius [pixel].
    density : float or ndarray
        Surface density [1/pixel^2] of the neighbours that count.

    Returns
    -------
    ndarray
        ``1 - exp(-pi radius^2 density)``.
    """
    return -np.expm1(-np.pi * np.square(radius) * np.asarray(density, dtype=float))


def effective_fwhm(epsf: np.ndarray, oversampling: int) -> tuple[float, float, float]:
    """FWHM [pixel] of an oversampled ePSF image (pixel-integrated PSF).

    Parameters
    ----------
    epsf : ndarray, shape (ny, nx)
        ePSF on its oversampled grid, centre at the array centre.
    oversampling : int
        Grid points per detector pixel.

    Returns
    -------
    equivalent : float
        ``2 sqrt(A / pi)``, ``A`` the area above half the peak.
    fwhm_x, fwhm_y : float
        Widths at half the peak of the profiles through the peak along x and y
        (linear interpolation between grid points).
    """
    img = np.asarray(epsf, dtype=float)
    peak = img.max()
    half = 0.5 * peak
    equivalent = 2.0 * np.sqrt(np.count_nonzero(img >= half) / np.pi) / oversampling
    r, c = np.unravel_index(np.argmax(img), img.shape)

    def width(profile, k):
        lo = k
        while lo > 0 and profile[lo - 1] >= half:
            lo -= 1
        hi = k
        while hi < len(profile) - 1 and profile[hi + 1] >= half:
            hi += 1
        # interpolated crossings on both sides
        left = lo - (profile[lo] - half) / (profile[lo] - profile[lo - 1]) if lo > 0 else lo
        right = (
            hi + (profile[hi] - half) / (profile[hi] - profile[hi + 1])
            if hi < len(profile) - 1
            else hi
        )
        return (right - left) / oversampling

    return equivalent, width(img[r, :], c), width(img[:, c], r)
