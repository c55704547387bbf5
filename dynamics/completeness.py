"""Completeness of the proper-motion sample against radius and magnitude (artificial stars).

The star-count term of the likelihood needs the fraction ``c(R)`` of the tracer
population that made it into the fitted sample at projected radius ``R``
(crowding lowers it toward the centre). An observer measures it with an
artificial-star test: stars of known position and magnitude are injected into the
frames, measured like the real ones, and counted where they are recovered. In a
simulation every star was injected, so the input catalogue *is* that test: a
catalogue star is *recovered* when it is in the fitted sample (measured at every
epoch, unflagged, with a finite proper motion, inside the field).

The tracer population is every luminous catalogue star brighter than the sample's
magnitude limit; ``c(R)`` is the recovered fraction per radial bin, i.e. ``c(R, m)``
averaged over the luminosity function of the population, which is what the
star-count normalisation needs. ``c(R, m)`` itself is tabulated too (for the
report and the docs). Radial bins hold equal numbers of injected stars; the 68%
binomial (Wilson) interval of each fraction comes from :func:`astropy.stats.binom_conf_interval`.
"""

from __future__ import annotations

import astropy.units as u
import numpy as np
from astropy.stats import binom_conf_interval
from astropy.table import QTable, vstack

from mavispm.core.errors import InputError

__all__ = [
    "completeness_by_radius",
    "completeness_by_radius_and_magnitude",
    "completeness_points",
    "radial_bin_edges",
]

#: Fewest injected stars per radial bin (sets the number of bins).
MIN_PER_BIN = 40
#: Most radial bins.
MAX_BINS = 10


def radial_bin_edges(radius, field_radius, min_per_bin=MIN_PER_BIN, max_bins=MAX_BINS):
    """Radial bin edges holding equal numbers of injected stars.

    Parameters
    ----------
    radius : array_like
        Projected radii of the injected stars inside the field [arcsec].
    field_radius : float
        Radius of the field [arcsec]: the last edge (the first is 0).
    min_per_bin, max_bins : int
        Fewest stars per bin, most bins (at least one bin).

    Returns
    -------
    ndarray
        Increasing edges [arcsec], from 0 to ``field_radius``.
    """
    r = np.asarray(radius, dtype=float)
    n_bins = int(np.clip(r.size // max(int(min_per_bin), 1), 1, max_bins))
    inner = np.quantile(r, np.arange(1, n_bins) / n_bins) if n_bins > 1 else np.empty(0)
    edges = np.unique(np.concatenate([[0.0], inner, [float(field_radius)]]))
    return edges


def _fractions(radius, recovered, edges) -> QTable:
    """Recovered fraction of the injected stars per radial bin (one row per bin)."""
    r = np.asarray(radius, dtype=float)
    rec = np.asarray(recovered, dtype=bool)
    index = np.clip(np.searchsorted(edges, r, side="right") - 1, 0, edges.size - 2)
    n_in = np.bincount(index, minlength=edges.size - 1)
    n_rec = np.bincount(index, weights=rec, minlength=edges.size - 1).astype(np.int64)
    mid = np.array(
        [
            np.median(r[index == k]) if n_in[k] else 0.5 * (edges[k] + edges[k + 1])
            for k in range(n_in.size)
        ]
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(n_in > 0, n_rec / np.maximum(n_in, 1), np.nan)
    lo, hi = np.full(n_in.size, np.nan), np.full(n_in.size, np.nan)
    ok = n_in > 0
    if np.any(ok):
        lo[ok], hi[ok] = binom_conf_interval(n_rec[ok], n_in[ok], 0.6827, interval="wilson")
    return QTable(
        {
            "radius_lo": edges[:-1] * u.arcsec,
            "radius_hi": edges[1:] * u.arcsec,
            "radius": mid * u.arcsec,
            "n_injected": n_in.astype(np.int64),
            "n_recovered": n_rec,
            "completeness": frac,
            "completeness_lo68": lo,
            "completeness_hi68": hi,
        }
    )


def _check(radius, mag, recovered, field_radius):
    r = np.asarray(radius, dtype=float)
    m = np.asarray(mag, dtype=float)
    rec = np.asarray(recovered, dtype=bool)
    if not (r.shape == m.shape == rec.shape and r.ndim == 1):
        raise InputError(
            f"radius, mag and recovered must be 1-D of one length, got {r.shape}, {m.shape}, "
            f"{rec.shape}",
            column="radius/mag",
        )
    if not (np.isfinite(field_radius) and field_radius > 0):
        raise InputError(f"field radius must be > 0 arcsec, got {field_radius}")
    inside = np.isfinite(r) & (r <= field_radius) & np.isfinite(m)
    return r, m, rec, inside


def completeness_by_radius(
    radius,
    mag,
    recovered,
    field_radius: float,
    mag_limit: float,
    min_per_bin: int = MIN_PER_BIN,
    max_bins: int = MAX_BINS,
) -> QTable:
    """Recovered fraction of the injected stars brighter than ``mag_limit`` per radial bin.

    Parameters
    ----------
    radius : array_like
        Projected radius of every injected (catalogue) star about the field centre [arcsec].
    mag : array_like
        Its magnitude [mag].
    recovered : array_like of bool
        Whether it is in the fitted sample.
    field_radius : float
        Radius of the field [arcsec]; stars outside are not counted.
    mag_limit : float
        Faintest magnitude of the tracer population [mag].
    min_per_bin, max_bins : int
        Equal-count radial bins: fewest injected stars per bin, most bins.

    Returns
    -------
    astropy.table.QTable
        One row per radial bin: ``radius_lo``, ``radius_hi``, ``radius`` (median radius of
        its injected stars) [arcsec], ``n_injected``, ``n_recovered``, ``completeness``
        and its 68% Wilson interval ``completeness_lo68``, ``completeness_hi68``.

    Raises
    ------
    InputError
        Mismatched inputs, a bad field radius, or no injected star in the population.
    """
    r, m, rec, inside = _check(radius, mag, recovered, field_radius)
    pop = inside & (m <= mag_limit)
    if not np.any(pop):
        raise InputError(
            f"no injected star brighter than {mag_limit:.3g} mag inside {field_radius:.3g} arcsec"
        )
    edges = radial_bin_edges(r[pop], field_radius, min_per_bin, max_bins)
    table = _fractions(r[pop], rec[pop], edges)
    table.meta["mag_limit"] = float(mag_limit)
    return table


def completeness_by_radius_and_magnitude(
    radius,
    mag,
    recovered,
    field_radius: float,
    mag_edges,
    radius_edges,
) -> QTable:
    """Recovered fraction ``c(R, m)`` on a grid of radial and magnitude bins.

    Parameters
    ----------
    radius, mag, recovered, field_radius
        As in :func:`completeness_by_radius`.
    mag_edges : array_like
        Increasing magnitude bin edges [mag].
    radius_edges : array_like
        Increasing radial bin edges [arcsec] (e.g. those of :func:`completeness_by_radius`).

    Returns
    -------
    astropy.table.QTable
        One row per (magnitude, radius) bin: ``mag_lo``, ``mag_hi`` [mag] and the columns
        of :func:`completeness_by_radius` (NaN fractions in empty bins).
    """
    r, m, rec, inside = _check(radius, mag, recovered, field_radius)
    edges = np.asarray(radius_edges, dtype=float)
    mags = np.asarray(mag_edges, dtype=float)
    if mags.size < 2 or np.any(np.diff(mags) <= 0) or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise InputError("magnitude and radius bin edges must increase (>= 2 each)")
    rows = []
    for lo, hi in zip(mags[:-1], mags[1:]):
        sel = inside & (m >= lo) & (m < hi)
        t = _fractions(r[sel], rec[sel], edges)
        t["mag_lo"] = np.full(len(t), lo) * u.mag
        t["mag_hi"] = np.full(len(t), hi) * u.mag
        rows.append(t)
    out = vstack(rows)
    return out[["mag_lo", "mag_hi", *[c for c in out.colnames if not c.startswith("mag_")]]]


def completeness_points(table: QTable) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The likelihood's completeness table from :func:`completeness_by_radius`.

    Radii are the bins' median radii [arcsec]; fractions are clipped to
    ``[0.5 / n_injected, 1]`` so that a bin with no recovered star keeps a positive
    (upper-limit) completeness. Empty bins are dropped; a single bin gives a flat table.

    Parameters
    ----------
    table : astropy.table.QTable
        Output of :func:`completeness_by_radius`.

    Returns
    -------
    radius, completeness : tuple of float
        Increasing radii [arcsec] and completeness in (0, 1] (at least two points).
    """
    n = np.asarray(table["n_injected"], dtype=float)
    ok = n > 0
    r = np.asarray(table["radius"].to_value(u.arcsec))[ok]
    c = np.clip(np.asarray(table["completeness"], dtype=float)[ok], 0.5 / n[ok], 1.0)
    if r.size == 1:
        hi = float(np.asarray(table["radius_hi"].to_value(u.arcsec))[ok][0])
        r, c = np.array([r[0], max(hi, r[0] * 1.01 + 1e-6)]), np.array([c[0], c[0]])
    keep = np.concatenate([[True], np.diff(r) > 0])
    return tuple(float(v) for v in r[keep]), tuple(float(v) for v in c[keep])
