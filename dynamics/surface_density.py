"""The tracer's scale radius (and King62 concentration) from an observed surface-density profile.

An observer knows a cluster's light or star-count profile from wide-field photometry
(e.g. Trager, King & Djorgovski 1995; de Boer et al. 2019), far beyond the small MCAO
field. This module fits the fit's tracer law to such a profile, a table of radius,
surface density and error, and returns the Gaussian prior of ``log_scale_radius``
(and, for King62, the concentration) that the dynamics fit then uses instead of
anything from the generator:

    Sigma(R) = Sigma_0 * s(R / a) / s(0) + background

with ``s`` the tracer's projected profile (:mod:`mavispm.dynamics.tracers`: Plummer
``(1 + X^2)^-2``, King62's closed form with free concentration, Dehnen with its fixed
slope) and a constant background. Weighted least squares
(:func:`scipy.optimize.curve_fit`, ``absolute_sigma=True``) in ``log10 a``; the
prior's width is the fit's standard error times ``sqrt(chi^2 / dof)`` when the
profile scatters more than its errors say (the law does not describe the cluster
exactly).
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np
from astropy.table import QTable, Table
from scipy.optimize import curve_fit

from mavispm.core.errors import InputError
from mavispm.dynamics.tracers import make_tracer

__all__ = [
    "SurfaceDensityFit",
    "fit_surface_density",
    "read_surface_density",
]


@dataclass(frozen=True)
class SurfaceDensityFit:
    """Result of :func:`fit_surface_density`.

    Parameters
    ----------
    tracer : str
        Tracer law fitted.
    log_scale_radius, log_scale_radius_err : float
        log10 of the scale (Plummer, Dehnen) or core (King62) radius [log10 arcsec] and
        its standard error (inflated by ``sqrt(chi^2/dof)`` when above 1).
    concentration, concentration_err : float
        King62 ``log10(r_t / r_c)`` and its error (NaN for other laws).
    central_density, background : float
        ``Sigma_0`` and the constant background, in the profile's density unit.
    chi2 : float
        chi^2 of the best fit.
    dof : int
        Degrees of freedom.
    """

    tracer: str
    log_scale_radius: float
    log_scale_radius_err: float
    concentration: float
    concentration_err: float
    central_density: float
    background: float
    chi2: float
    dof: int

    @property
    def prior(self) -> tuple[float, float]:
        """``(mean, sd)`` of the Gaussian ``log_scale_radius`` prior [log10 arcsec]."""
        return (self.log_scale_radius, self.log_scale_radius_err)


def _shape(tracer: str, X, concentration=1.5, gamma=1.0):
    law = make_tracer(tracer, gamma=gamma, concentration=concentration)
    return law.surface_density(X) / law.surface_density(np.zeros(1))[0]


def fit_surface_density(
    radius, density, error, tracer: str = "plummer", dehnen_gamma: float = 1.0
) -> SurfaceDensityFit:
    """Fit the tracer law to a surface-density profile.

    Parameters
    ----------
    radius : array_like
        Projected radii [arcsec] (> 0).
    density, error : array_like
        Surface density and its 1-sigma error (> 0), any one unit.
    tracer : {"plummer", "king62", "dehnen"}
        The dynamics fit's tracer law.
    dehnen_gamma : float
        Fixed inner slope of the Dehnen law.

    Returns
    -------
    SurfaceDensityFit

    Raises
    ------
    InputError
        Fewer points than parameters + 1, non-positive radii or errors, non-finite
        values, or a fit that does not converge.
    """
    R, S, E = (np.asarray(v, dtype=float) for v in (radius, density, error))
    if not (R.shape == S.shape == E.shape and R.ndim == 1):
        raise InputError("radius, density and error must be 1-D of one length", column="radius")
    for name, v in (("radius", R), ("density", S), ("density_err", E)):
        if not np.all(np.isfinite(v)):
            raise InputError("non-finite values", column=name)
    if np.any(R <= 0) or np.any(E <= 0):
        raise InputError("radii and errors must be > 0", column="radius/density_err")
    king = tracer == "king62"
    n_par = 4 if king else 3
    if R.size < n_par + 1:
        raise InputError(f"{R.size} profile points; the {tracer} fit needs >= {n_par + 1}")

    def model(r, log_a, s0, bg, c=None):
        X = r / 10.0**log_a
        if king:
            return s0 * _shape("king62", X, concentration=c) + bg
        return s0 * _shape(tracer, X, gamma=dehnen_gamma) + bg

    order = np.argsort(R)
    # start: half the central density at the core; background from the outermost points
    s0 = float(np.max(S[order[:3]]))
    half = R[order][np.argmax(S[order] < 0.5 * s0)] if np.any(S < 0.5 * s0) else R.max()
    p0 = [np.log10(half), s0, max(float(np.min(S)), 0.0) * 0.1]
    lo, hi = [-2.0, 0.0, -np.inf], [5.0, np.inf, np.inf]
    if king:
        p0.append(1.5)
        lo.append(0.31)
        hi.append(3.0)
    try:
        popt, pcov = curve_fit(
            model, R, S, p0=p0, sigma=E, absolute_sigma=True, bounds=(lo, hi), maxfev=20000
        )
    except (RuntimeError, ValueError) as err:
        raise InputError(f"the {tracer} surface-density fit did not converge ({err})") from None
    chi2 = float(np.sum(((S - model(R, *popt)) / E) ** 2))
    dof = int(R.size - n_par)
    inflate = max(1.0, np.sqrt(chi2 / dof)) if dof > 0 else 1.0
    err = np.sqrt(np.clip(np.diag(pcov), 0.0, np.inf)) * inflate
    if not np.all(np.isfinite(err)):
        raise InputError(f"the {tracer} surface-density fit is degenerate (singular covariance)")
    return SurfaceDensityFit(
        tracer=tracer,
        log_scale_radius=float(popt[0]),
        log_scale_radius_err=float(err[0]),
        concentration=float(popt[3]) if king else float("nan"),
        concentration_err=float(err[3]) if king else float("nan"),
        central_density=float(popt[1]),
        background=float(popt[2]),
        chi2=chi2,
        dof=dof,
    )


def read_surface_density(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a surface-density profile table (ECSV, FITS, CSV or anything astropy reads).

    Columns ``radius`` (with a unit of angle; arcsec when unitless), ``density`` and
    ``density_err`` (one unit, any).

    Parameters
    ----------
    path : str or os.PathLike
        The table.

    Returns
    -------
    radius, density, density_err : ndarray
        Radii [arcsec], densities and errors.

    Raises
    ------
    InputError
        Unreadable file, a missing column, or a radius unit that is not an angle.
    """
    try:
        t = QTable(Table.read(path))
    except Exception as err:  # any reader failure is one line naming the file
        raise InputError(f"cannot read the surface-density profile ({err})", path=path) from None
    for col in ("radius", "density", "density_err"):
        if col not in t.colnames:
            raise InputError(
                "missing column; expected radius [arcsec], density, density_err",
                path=path,
                column=col,
            )
    r = t["radius"]
    if getattr(r, "unit", None) in (None, u.dimensionless_unscaled):
        radius = np.asarray(r, dtype=float)
    else:
        try:
            radius = r.to_value(u.arcsec)
        except u.UnitConversionError:
            raise InputError(
                f"radius unit {r.unit} is not an angle", path=path, column="radius"
            ) from None
    d, e = t["density"], t["density_err"]
    unit = getattr(d, "unit", None)
    if unit is not None and getattr(e, "unit", None) is not None:
        try:
            e = e.to(unit)
        except u.UnitConversionError:
            raise InputError(
                f"density_err unit {e.unit} differs from the density's {unit}",
                path=path,
                column="density_err",
            ) from None
    density, error = (np.asarray(getattr(c, "value", c), dtype=float) for c in (d, e))
    return np.asarray(radius, dtype=float), density, error
