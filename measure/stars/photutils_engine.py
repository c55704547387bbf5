"""Reference engine: photutils ``PSFPhotometry`` with forced starting positions.

The ePSF (constant, gridded or polynomial) is handed to photutils as an
``ImagePSF`` (constant) or a ``GriddedPSFModel`` (field-variable; a polynomial
ePSF is sampled on a grid of nodes first). Stars closer than
``group_separation`` pixels are fitted simultaneously (``SourceGrouper``), the
local sky is taken from an annulus (``LocalBackground``) and subtracted, and the
fitter is astropy's ``LevMarLSQFitter`` (3x faster than photutils' default
``TRFLSQFitter`` with identical results) or the default. Pixel errors are
``sqrt(sky + max(data - sky, 0) + RN^2)`` (photutils weights by the data).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from astropy.modeling.fitting import LevMarLSQFitter, TRFLSQFitter
from astropy.nddata import NDData
from astropy.table import QTable
from photutils.background import LocalBackground, MMMBackground
from photutils.psf import GriddedPSFModel, ImagePSF, PSFPhotometry, SourceGrouper

from mavispm.core.errors import InputError
from mavispm.core.frame import on_detector
from mavispm.measure.stars.batched_fit import (
    FLAG_EDGE,
    FLAG_FAILED,
    FLAG_NOT_CONVERGED,
    FLAG_SATURATED,
    FitResult,
)
from mavispm.measure.stars.epsf import node_positions
from mavispm.measure.stars.variable_psf import VariableEPSF

__all__ = [
    "PhotutilsOptions",
    "fit_stars_photutils",
    "to_photutils_model",
]


@dataclass(frozen=True)
class PhotutilsOptions:
    """Settings of the photutils reference engine.

    Parameters
    ----------
    radius : int
        Fit stamp half-width [pixel] (``fit_shape = 2 radius + 1``).
    fitter : str
        "levmar" (astropy LevMarLSQFitter) or "default" (photutils' TRFLSQFitter).
    group_separation : float
        Stars closer than this [pixel] are fitted together.
    maxiters : int
        Fitter iterations.
    sky_annulus : tuple of float
        Inner and outer radius [pixel] of the local-sky annulus.
    grid : int
        Nodes per axis used to sample a polynomial ePSF for photutils.
    """

    radius: int = 5
    fitter: str = "levmar"
    group_separation: float = 8.0
    maxiters: int = 100
    sky_annulus: tuple[float, float] = (8.0, 12.0)
    grid: int = 5


def to_photutils_model(psf: VariableEPSF, shape: tuple[int, int], grid: int = 5):
    """The photutils model of an ePSF (``ImagePSF`` or ``GriddedPSFModel``).

    Parameters
    ----------
    psf : VariableEPSF
        The ePSF.
    shape : tuple of int
        Frame shape ``(ny, nx)``.
    grid : int
        Nodes per side of the ``GriddedPSFModel`` for a polynomial ePSF (a grid ePSF keeps
        its own nodes).

    Returns
    -------
    photutils.psf.ImagePSF or photutils.psf.GriddedPSFModel
        ``ImagePSF`` for a constant ePSF, else the ePSF sampled at the nodes.
    """
    if psf.kind == "constant":
        return ImagePSF(psf.basis[0], oversampling=psf.oversampling)
    if psf.kind == "grid":
        gx, gy = np.asarray(psf.meta["nodes_x"]), np.asarray(psf.meta["nodes_y"])
    else:
        gx, gy = node_positions(shape, grid)
    xy = [(xi, yi) for yi in gy for xi in gx]
    data = np.array([psf.epsf_at(xi, yi) for xi, yi in xy])
    if len(xy) == 1:
        return ImagePSF(data[0], oversampling=psf.oversampling)
    nd = NDData(data, meta={"grid_xypos": xy, "oversampling": psf.oversampling})
    return GriddedPSFModel(nd)


def fit_stars_photutils(
    image: np.ndarray,
    psf: VariableEPSF,
    x0: np.ndarray,
    y0: np.ndarray,
    *,
    read_noise_var: float,
    sky0: float,
    flux0: np.ndarray | None = None,
    bad: np.ndarray | None = None,
    saturated: np.ndarray | None = None,
    options: PhotutilsOptions | None = None,
) -> FitResult:
    """Fit all stars with photutils ``PSFPhotometry`` (same call as the batched fitter).

    Parameters are those of :func:`mavispm.measure.stars.batched_fit.fit_stars`;
    ``sky0`` is only used for the pixel errors (the local sky comes from an
    annulus around each star).

    Parameters
    ----------
    image : ndarray
        The frame [electron].
    psf : VariableEPSF
        The ePSF.
    x0, y0 : ndarray
        Start positions [pixel].
    read_noise_var : float
        Read-noise variance per pixel [electron^2].
    sky0 : float
        Sky [electron/pixel] for the pixel errors.
    flux0 : ndarray, optional
        Start fluxes [electron].
    bad, saturated : ndarray of bool, optional
        Unusable and saturated pixels.
    options : PhotutilsOptions, optional
        Fitter, grouping and stamp settings.

    Returns
    -------
    FitResult
        Per-star fit results, as from the batched fitter.
    """
    opt = options or PhotutilsOptions()
    if opt.fitter not in ("levmar", "default"):
        raise InputError(f"unknown photutils fitter '{opt.fitter}'; expected levmar or default")
    image = np.asarray(image, float)
    ny, nx = image.shape
    x0 = np.atleast_1d(np.asarray(x0, float))
    y0 = np.atleast_1d(np.asarray(y0, float))
    n = len(x0)
    sat = np.zeros(image.shape, bool) if saturated is None else np.asarray(saturated, bool)
    mask = (
        ~np.isfinite(image) | sat | (np.zeros_like(sat) if bad is None else np.asarray(bad, bool))
    )
    data = np.where(mask, 0.0, image)
    err = np.sqrt(np.maximum(data, sky0) + read_noise_var)
    usable = on_detector(x0, y0, (ny, nx))
    init = QTable({"id": np.arange(1, n + 1)[usable], "x": x0[usable], "y": y0[usable]})
    if flux0 is not None:
        init["flux"] = np.maximum(np.nan_to_num(np.asarray(flux0, float)[usable]), 1.0)
    fitter = LevMarLSQFitter() if opt.fitter == "levmar" else TRFLSQFitter()
    size = 2 * int(opt.radius) + 1
    phot = PSFPhotometry(
        to_photutils_model(psf, image.shape, opt.grid),
        (size, size),
        grouper=SourceGrouper(min_separation=opt.group_separation),
        fitter=fitter,
        fitter_maxiters=opt.maxiters,
        aperture_radius=max(1.5, opt.radius / 2),
        local_bkg_estimator=LocalBackground(*opt.sky_annulus, bkg_estimator=MMMBackground()),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = phot(data, mask=mask, error=err, init_params=init)
    out = {
        k: np.full(n, np.nan)
        for k in ("x", "y", "flux", "sky", "x_err", "y_err", "flux_err", "chi2")
    }
    pos = np.flatnonzero(usable)
    out["x"][pos] = np.asarray(table["x_fit"], float)
    out["y"][pos] = np.asarray(table["y_fit"], float)
    out["flux"][pos] = np.asarray(table["flux_fit"], float)
    out["sky"][pos] = np.asarray(table["local_bkg"], float)
    for k in ("x_err", "y_err", "flux_err"):
        if k in table.colnames:
            out[k][pos] = np.asarray(np.ma.filled(table[k], np.nan), float)
    if "reduced_chi2" in table.colnames:
        out["chi2"][pos] = np.asarray(table["reduced_chi2"], float)
    pflags = np.zeros(n, dtype=np.int64)
    pflags[pos] = np.asarray(table["flags"], np.int64)
    flag = np.zeros(n, dtype=np.int64)
    flag[(pflags & 1) != 0] |= FLAG_EDGE
    flag[(pflags & 2) != 0] |= FLAG_EDGE | FLAG_FAILED
    flag[(pflags & 4) != 0] |= FLAG_FAILED
    flag[(pflags & 8) != 0] |= FLAG_NOT_CONVERGED
    flag[(pflags & 16) != 0] |= FLAG_FAILED
    flag[~usable] |= FLAG_FAILED | FLAG_EDGE
    half = int(opt.radius)
    for i in pos:
        cx, cy = int(np.rint(x0[i])), int(np.rint(y0[i]))
        box = sat[max(cy - half, 0) : cy + half + 1, max(cx - half, 0) : cx + half + 1]
        if box.any():
            flag[i] |= FLAG_SATURATED
    bad_fit = ~np.isfinite(out["x"]) | ~np.isfinite(out["flux"]) | ~(out["flux"] > 0)
    flag[bad_fit] |= FLAG_FAILED
    out["x"] = np.where(np.isfinite(out["x"]), out["x"], x0)
    out["y"] = np.where(np.isfinite(out["y"]), out["y"], y0)
    for k in ("x_err", "y_err", "flux_err"):
        out[k][(flag & FLAG_FAILED) != 0] = np.nan
    return FitResult(
        x=out["x"],
        y=out["y"],
        flux=out["flux"],
        sky=out["sky"],
        x_err=out["x_err"],
        y_err=out["y_err"],
        flux_err=out["flux_err"],
        sky_err=np.full(n, np.nan),
        chi2=out["chi2"],
        flag=flag,
        iterations=opt.maxiters,
        model_image=np.asarray(phot.make_model_image(image.shape), float)
        if hasattr(phot, "make_model_image")
        else np.zeros(image.shape),
    )
