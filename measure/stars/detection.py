"""Optional blind mode: detect sources with a photutils finder, score against the truth."""

from __future__ import annotations

import warnings

import numpy as np
from photutils.detection import DAOStarFinder

from mavispm.measure.stars.truth_match import match_to_truth

__all__ = [
    "FALSE_MAG_LIMIT",
    "SCORE_MAG_EDGES",
    "SCORE_RADIUS_EDGES",
    "completeness",
    "detect_sources",
    "detection_scores",
]


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

    Parameters
    ----------
    x, y : ndarray
        Detected positions [pixel].
    x_true, y_true : ndarray
        True positions [pixel].
    radius : float
        Match radius [pixel].

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


#: Magnitude bin edges [mag] of the detection scores.
SCORE_MAG_EDGES = (-np.inf, 18.0, 20.0, 22.0, 24.0, 25.0, 26.0, 27.0, np.inf)
#: Radius bin edges [arcsec] (from the frame centre) of the detection scores.
SCORE_RADIUS_EDGES = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0, np.inf)
#: Detections brighter than this [mag] make the headline false fraction.
FALSE_MAG_LIMIT = 26.0


def _binned(values, edges, selected):
    """Counts of ``values`` per bin, for all and for the ``selected`` entries."""
    out_all, out_sel = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inbin = (values >= lo) & (values < hi)
        out_all.append(int(np.count_nonzero(inbin)))
        out_sel.append(int(np.count_nonzero(inbin & selected)))
    return out_all, out_sel


def detection_scores(
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    x_true: np.ndarray,
    y_true: np.ndarray,
    mag_true: np.ndarray,
    radius: float,
    r_det: np.ndarray,
    r_true: np.ndarray,
) -> dict:
    """Completeness and false-detection rate against magnitude and radius.

    Detections are matched one-to-one to the truth within ``radius`` (pixels).
    A detection's magnitude is calibrated with the median zero point of the
    matched detections (``mag_true + 2.5 log10 flux``), as an observer would with
    standards.

    Parameters
    ----------
    x, y, flux : ndarray
        Detections [pixel], fitted flux [electron].
    x_true, y_true, mag_true : ndarray
        Truth positions [pixel] and magnitudes [mag].
    radius : float
        Match radius [pixel].
    r_det, r_true : ndarray
        Distance from the frame centre [arcsec] of the detections and the truth.

    Returns
    -------
    dict
        ``zero_point``; ``false_fraction_v26``: false among detections with
        calibrated m < 26; ``by_mag`` and ``by_radius``: per bin the edges,
        ``n_true``, ``n_found`` (completeness = found / true), ``n_detected``
        and ``n_false`` (false rate = false / detected).
    """
    index, _ = match_to_truth(x, y, x_true, y_true, radius)
    matched = index >= 0
    found = np.zeros(len(x_true), bool)
    found[index[matched]] = True
    with np.errstate(invalid="ignore", divide="ignore"):
        inst = -2.5 * np.log10(np.where(np.asarray(flux) > 0, flux, np.nan))
    zp_sample = mag_true[index[matched]] - inst[matched]
    zp_sample = zp_sample[np.isfinite(zp_sample)]
    zp = float(np.median(zp_sample)) if zp_sample.size else float("nan")
    mag_det = np.where(np.isfinite(inst), inst + zp, np.inf)  # no flux: fainter than all
    false = ~matched
    out = {"zero_point": zp}
    bright = mag_det < FALSE_MAG_LIMIT
    out["false_fraction_v26"] = (
        float(np.count_nonzero(false & bright) / np.count_nonzero(bright))
        if np.any(bright)
        else float("nan")
    )
    for name, edges, det_value, true_value in (
        ("by_mag", SCORE_MAG_EDGES, mag_det, np.asarray(mag_true, float)),
        ("by_radius", SCORE_RADIUS_EDGES, np.asarray(r_det), np.asarray(r_true)),
    ):
        n_true, n_found = _binned(true_value, edges, found)
        n_det, n_false = _binned(det_value, edges, false)
        out[name] = {
            "edges": [None if not np.isfinite(e) else float(e) for e in edges],
            "n_true": n_true,
            "n_found": n_found,
            "n_detected": n_det,
            "n_false": n_false,
        }
    return out
