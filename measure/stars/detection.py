"""Optional blind mode: detect sources with a photutils finder, score against the truth."""

from __future__ import annotations

import warnings

import numpy as np
from photutils.detection import DAOStarFinder

from mavispm.measure.stars.truth_match import match_to_truth


def detect_sources(
    image: np.ndarray, sky: float, noise: float, fwhm: float, threshold: float, bad: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find point sources with ``DAOStarFinder``.

    Parameters
    ----------
    image : ndarray
        Frame [electron].
    sky : float
        Sky level [electron/pixel].
    noise : float
        Background noise per pixel [electron].
    fwhm : float
        PSF FWHM [pixel].
    threshold : float
        Detection threshold in units of ``noise``.
    bad : ndarray of bool
        Pixels to ignore (saturated pixels are filled with the saturation level so
        saturated stars are still found).

    Returns
    -------
    x, y, flux : ndarray
        Positions [pixel] and rough fluxes [electron] of the detections.
    """
    data = np.nan_to_num(np.asarray(image, float) - sky)
    finder = DAOStarFinder(threshold=threshold * noise, fwhm=fwhm, exclude_border=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        found = finder(data, mask=~np.isfinite(image))
    if found is None or len(found) == 0:
        empty = np.zeros(0)
        return empty, empty.copy(), empty.copy()
    return (
        np.asarray(found["x_centroid"], float),
        np.asarray(found["y_centroid"], float),
        np.asarray(found["flux"], float),
    )


def completeness(
    x: np.ndarray,
    y: np.ndarray,
    x_true: np.ndarray,
    y_true: np.ndarray,
    radius: float,
) -> dict:
    """Completeness and false detections of a source list against the truth.

    Returns
    -------
    dict
        ``n_detected``, ``n_true``, ``n_matched``, ``n_false``, ``completeness``
        (matched / true) and ``false_fraction`` (false / detected).
    """
    index, _ = match_to_truth(x, y, x_true, y_true, radius)
    matched = int(np.count_nonzero(index >= 0))
    n_det, n_true = len(x), len(x_true)
    return {
        "n_detected": n_det,
        "n_true": n_true,
        "n_matched": matched,
        "n_false": n_det - matched,
        "completeness": matched / n_true if n_true else float("nan"),
        "false_fraction": (n_det - matched) / n_det if n_det else float("nan"),
    }
