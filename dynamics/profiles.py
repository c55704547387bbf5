"""Binned proper-motion dispersion profiles with measurement errors deconvolved.

Stars are sorted by projected radius and split into bins of equal count
(default 300; a remainder smaller than half a bin joins the last full bin).
In each bin, for each component (radial ``R``, tangential ``T``, and both
pooled), the intrinsic dispersion ``sigma`` and mean ``mu`` maximise

    ln L = -1/2 sum_i [ (v_i - mu)^2 / (sigma^2 + e_i^2) + ln(sigma^2 + e_i^2) ],

solved by the fixed-point iteration ``sigma^2 = sum w_i^2 ((v_i - mu)^2 - e_i^2) / sum w_i^2``
with ``w_i = 1 / (sigma^2 + e_i^2)`` (``sigma^2`` clipped at 0 when the errors
explain all the scatter). Uncertainties: analytic, from the Fisher information
``I(sigma) = sum 2 sigma^2 / (sigma^2 + e_i^2)^2``, and bootstrap (resampling
the stars of a bin). Dispersions are given in mas/yr and, with a distance, km/s.
"""

from __future__ import annotations

import astropy.units as u
import numpy as np
from astropy.table import QTable
from numpy.typing import ArrayLike

from mavispm.core.errors import InputError
from mavispm.dynamics.jeans import KMS_PER_MASYR_KPC

__all__ = [
    "dispersion_profile",
    "equal_count_bins",
    "fisher_error",
    "ml_dispersion",
    "radial_tangential",
]


def equal_count_bins(n: int, bin_size: int) -> list[slice]:
    """Slices of a sorted array into bins of ``bin_size`` (remainder merged if small).

    Parameters
    ----------
    n : int
        Number of stars.
    bin_size : int
        Stars per bin (>= 2).
    """
    if bin_size < 2:
        raise InputError(f"bin size must be >= 2 stars, got {bin_size}")
    if n < 2:
        return []
    n_full = max(n // bin_size, 1)
    edges = [i * bin_size for i in range(n_full)] + [n]
    remainder = n - n_full * bin_size
    if remainder >= bin_size // 2 and n_full * bin_size < n and n >= bin_size:
        edges = [i * bin_size for i in range(n_full + 1)] + [n]
    return [slice(edges[i], edges[i + 1]) for i in range(len(edges) - 1)]


def ml_dispersion(v: ArrayLike, e: ArrayLike, n_iter: int = 500, tol: float = 1e-10):
    """Maximum-likelihood intrinsic dispersion and mean (vectorised over leading axes).

    Parameters
    ----------
    v, e : ndarray (..., n)
        Values and their Gaussian errors (same unit).
    n_iter : int
        Most fixed-point iterations.
    tol : float
        Relative change of the variance at which the iteration stops.

    Returns
    -------
    sigma, mu : ndarray (...)
    """
    v = np.asarray(v, dtype=float)
    e2 = np.asarray(e, dtype=float) ** 2
    mu = v.mean(axis=-1)
    s2 = np.maximum(v.var(axis=-1) - e2.mean(axis=-1), 0.0)
    floor = 1e-12 * (np.mean(e2) + np.mean(v**2) + 1e-300)
    for _ in range(n_iter):
        w = 1.0 / (s2[..., None] + e2 + floor)
        mu = np.sum(w * v, axis=-1) / np.sum(w, axis=-1)
        d2 = (v - mu[..., None]) ** 2
        new = np.maximum(np.sum(w * w * (d2 - e2), axis=-1) / np.sum(w * w, axis=-1), 0.0)
        done = np.all(np.abs(new - s2) <= tol * (new + floor))
        s2 = new
        if done:
            break
    return np.sqrt(s2), mu


def fisher_error(sigma: float, e: ArrayLike):
    """Analytic 1-sigma error of the ML dispersion (inf when sigma = 0).

    The dispersion maximises ``prod N(v; 0, sigma^2 + e_i^2)``; its Fisher information is
    ``sum 2 sigma^2 / (sigma^2 + e_i^2)^2``.

    Parameters
    ----------
    sigma : float
        ML dispersion.
    e : array_like
        Per-star errors, same unit.

    Returns
    -------
    float
        1-sigma error, same unit.
    """
    s2 = sigma**2
    info = np.sum(2.0 * s2 / (s2 + np.asarray(e) ** 2) ** 2)
    return 1.0 / np.sqrt(info) if info > 0 else np.inf


def dispersion_profile(
    R: u.Quantity,
    v_r: u.Quantity,
    v_t: u.Quantity,
    e_r: u.Quantity,
    e_t: u.Quantity,
    bin_size: int = 300,
    n_bootstrap: int = 200,
    distance: u.Quantity | None = None,
    seed: int = 0,
) -> QTable:
    """Binned radial, tangential and pooled PM dispersion profile.

    Parameters
    ----------
    R : Quantity
        Projected radii (angle).
    v_r, v_t, e_r, e_t : Quantity
        Radial/tangential proper motions and errors (mas/yr).
    bin_size : int
        Stars per bin.
    n_bootstrap : int
        Bootstrap resamples per bin (0 to skip).
    distance : Quantity, optional
        Adds km/s columns.
    seed : int
        Bootstrap random seed.

    Returns
    -------
    QTable
        One row per bin: ``R_mean, R_min, R_max`` [arcsec], ``n``, and for
        ``c`` in ``r, t, pm`` (pooled): ``sigma_c``, ``sigma_c_err``,
        ``sigma_c_err_boot``, ``mean_c`` [mas/yr], plus ``sigma_c_kms`` and
        ``sigma_c_kms_err`` [km/s] with a distance.
    """
    R = u.Quantity(R).to_value(u.arcsec)
    comps = {}
    for name, q in (("v_r", v_r), ("v_t", v_t), ("e_r", e_r), ("e_t", e_t)):
        try:
            comps[name] = u.Quantity(q).to_value(u.mas / u.yr)
        except u.UnitsError:
            raise InputError("expected a proper motion in mas/yr", column=name) from None
        if comps[name].shape != R.shape or not np.all(np.isfinite(comps[name])):
            raise InputError("must be finite and match R in length", column=name)
    if np.any(comps["e_r"] < 0) or np.any(comps["e_t"] < 0):
        raise InputError("negative proper-motion errors", column="e_r/e_t")
    order = np.argsort(R)
    R = R[order]
    c = {k: v[order] for k, v in comps.items()}
    rng = np.random.default_rng(seed)
    rows = []
    for sl in equal_count_bins(R.size, bin_size):
        row = {
            "R_mean": R[sl].mean(),
            "R_min": R[sl].min(),
            "R_max": R[sl].max(),
            "n": sl.stop - sl.start,
        }
        pooled = (
            np.concatenate([c["v_r"][sl], c["v_t"][sl]]),
            np.concatenate([c["e_r"][sl], c["e_t"][sl]]),
        )
        for key, (v, e) in (
            ("r", (c["v_r"][sl], c["e_r"][sl])),
            ("t", (c["v_t"][sl], c["e_t"][sl])),
            ("pm", pooled),
        ):
            sig, mu = ml_dispersion(v, e)
            row[f"sigma_{key}"] = float(sig)
            row[f"sigma_{key}_err"] = float(fisher_error(sig, e))
            row[f"mean_{key}"] = float(mu)
            if n_bootstrap > 0:
                pick = rng.integers(0, v.size, (n_bootstrap, v.size))
                boot, _ = ml_dispersion(v[pick], e[pick])
                row[f"sigma_{key}_err_boot"] = float(np.std(boot, ddof=1))
            else:
                row[f"sigma_{key}_err_boot"] = np.nan
        rows.append(row)
    table = QTable(rows=rows) if rows else QTable(names=["R_mean", "n"], dtype=[float, int])
    pm_unit = u.mas / u.yr
    if len(table):
        for col in ("R_mean", "R_min", "R_max"):
            table[col] = table[col] * u.arcsec
        for key in ("r", "t", "pm"):
            for col in (f"sigma_{key}", f"sigma_{key}_err", f"sigma_{key}_err_boot", f"mean_{key}"):
                table[col] = table[col] * pm_unit
            if distance is not None:
                conv = KMS_PER_MASYR_KPC * u.Quantity(distance).to_value(u.kpc)
                table[f"sigma_{key}_kms"] = table[f"sigma_{key}"].value * conv * u.km / u.s
                table[f"sigma_{key}_kms_err"] = table[f"sigma_{key}_err"].value * conv * u.km / u.s
    return table


def radial_tangential(x: np.ndarray, y: np.ndarray, pm_x: np.ndarray, pm_y: np.ndarray):
    """Rotate proper motions into radial / tangential components about (0, 0).

    Stars exactly at the centre get the x/y components (any direction is radial).

    Parameters
    ----------
    x, y : ndarray
        Positions about the centre [arcsec].
    pm_x, pm_y : ndarray
        Proper motions (any unit, kept).

    Returns
    -------
    R : ndarray
        Projected radius [arcsec].
    v_r, v_t : ndarray
        Radial and tangential components, same unit as the motions.
    """
    R = np.hypot(x, y)
    safe = np.where(R > 0, R, 1.0)
    cx = np.where(R > 0, x / safe, 1.0)
    sy = np.where(R > 0, y / safe, 0.0)
    return R, pm_x * cx + pm_y * sy, -pm_x * sy + pm_y * cx
