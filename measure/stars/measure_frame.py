"""Measure one frame: read it, build the ePSF, fit every star, match to the truth.

This is the engine-independent pipeline behind ``mavispm measure stars``:

1. read and check the ``frames`` product (:func:`read_frame`);
2. starting positions: the truth list (forced photometry, optionally perturbed)
   or detections (blind mode);
3. ePSF from automatically chosen PSF stars, rebuilt ``neighbour_passes`` times
   after subtracting the fitted neighbours;
4. the final fit with the chosen engine;
5. truth cross-match, flags and the per-star Cramér-Rao bound.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.errors import InputError
from mavispm.core.frame import Frame, on_detector
from mavispm.core.products import read_product
from mavispm.measure.stars.accuracy_report import truth_bin_counts
from mavispm.measure.stars.batched_fit import (
    FLAG_CROWDED,
    FLAG_FAILED,
    FLAG_NO_MATCH,
    FLAG_NOT_CONVERGED,
    UNRESOLVED_SEPARATION,
    FitOptions,
    FitResult,
    crowding_flags,
    fit_stars,
)
from mavispm.measure.stars.crlb import crlb
from mavispm.measure.stars.detection import completeness, detect_sources, detection_scores
from mavispm.measure.stars.epsf import (
    EPSFOptions,
    build_field_epsf,
    node_positions,
    node_psf_stars,
    psf_star_pool,
)
from mavispm.measure.stars.epsf_anchor import EarlierAnchor
from mavispm.measure.stars.error_model import (
    ErrorModel,
    epsf_difference_shifts,
    estimate_error_model,
)
from mavispm.measure.stars.halo_shape import HaloShape, prior_halo_shape
from mavispm.measure.stars.measured_table import MEASURED_SPEC
from mavispm.measure.stars.node_centring import (
    centred_on_all_stars,
    centring_summary,
    reference_list_id,
)
from mavispm.measure.stars.photutils_engine import PhotutilsOptions, fit_stars_photutils
from mavispm.measure.stars.psf_reconstruction import build_psfr_epsf, model_transforms, read_prior
from mavispm.measure.stars.rescue import Rescued, RescueOptions, rescue_stars
from mavispm.measure.stars.settings import MeasureSettings
from mavispm.measure.stars.sky_mesh import mesh_sky
from mavispm.measure.stars.start_list import EarlierEpoch, start_from_earlier
from mavispm.measure.stars.truth_match import match_to_truth
from mavispm.measure.stars.variable_psf import VariableEPSF

__all__ = [
    "Frame",
    "FramePSF",
    "MEASURED_SPEC",
    "box_flux",
    "build_psf",
    "measure_frame",
    "neighbour_rating",
    "psfr_grid_for",
    "read_frame",
]


def read_frame(path, require_truth: bool = True) -> Frame:
    """Read and check a ``frames`` product.

    Parameters
    ----------
    path : str or os.PathLike
        The ``frames`` product (HDF5).
    require_truth : bool
        Whether the truth table (the input star list of forced photometry) must be there.

    Returns
    -------
    Frame
        The frame in electrons (:meth:`~mavispm.core.frame.Frame.from_attrs`).

    Raises
    ------
    InputError
        Missing image or attributes, a non-2-D image, a mask of another shape,
        or (when ``require_truth``) a missing or malformed truth table.
    """
    path = Path(path)
    prod = read_product(path, "frames")
    if "image" not in prod.arrays:
        raise InputError("array 'image' missing", path=path)
    truth = prod.tables.get("truth")
    if truth is None and require_truth:
        raise InputError(
            "table 'truth' missing: forced photometry needs the input star list "
            "(use blind mode to detect stars instead)",
            path=path,
        )
    frame = Frame.from_attrs(
        prod.arrays["image"], prod.arrays.get("saturated"), prod.attrs, truth, path=path
    )
    if require_truth and len(frame.truth) == 0:
        raise InputError(
            "table 'truth' is empty: no input stars to measure (forced photometry)", path=path
        )
    _check_usable_image(frame.image, frame.saturated, prod.attrs, path)
    return frame


def _check_usable_image(image: np.ndarray, saturated: np.ndarray, attrs, path) -> None:
    """Refuse frames with nothing measurable, naming the cause (not "no PSF stars").

    Raises
    ------
    InputError
        For an image that is entirely (or mostly) NaN/infinite, constant (all
        zero), or saturated everywhere, and for a non-positive exposure time.
    """
    finite = np.isfinite(image)
    n_bad = image.size - int(np.count_nonzero(finite))
    if n_bad > 0.5 * image.size:
        raise InputError(
            f"array 'image': {n_bad} of {image.size} pixels are NaN or infinite; "
            "expected a measurable frame (bad pixels are a minority)",
            path=path,
        )
    good = image[finite]
    if good.max() == good.min():
        raise InputError(
            f"array 'image' is constant (every finite pixel is {good.min():g}): no stars to measure",
            path=path,
        )
    if np.all(saturated | ~finite):
        raise InputError("array 'image': every pixel is saturated: no stars to measure", path=path)
    exptime = attrs.get("exptime")
    if exptime is not None:
        value = float(exptime.to_value(u.s)) if isinstance(exptime, u.Quantity) else float(exptime)
        if not (np.isfinite(value) and value > 0):
            raise InputError(
                f"attribute 'exptime' must be a positive time in s, got {value}", path=path
            )


#: Square ring [pixel, Chebyshev distance] whose median is a star's local background.
LOCAL_SKY_RING = (6, 8)


def box_flux(
    frame: Frame,
    x: np.ndarray,
    y: np.ndarray,
    half: int = 2,
    ring: tuple[int, int] | None = LOCAL_SKY_RING,
    chunk: int = 4096,
    sky: np.ndarray | None = None,
) -> np.ndarray:
    """Rough flux [electron] in a (2 half + 1)^2 box, minus the star's local background.

    The background of each star is the median of the pixels at Chebyshev
    distance ``ring[0]..ring[1]`` from it (the frame's sky where none is usable;
    ``ring = None``: the frame's sky; ``sky``: given per star, e.g. :func:`mesh_sky`).
    With the frame's global sky instead, the seeing halo and the wings of the
    bright stars in a cluster centre (there ~7 % of the sky, plus the wing
    plateau of every bright star) made faint stars look bright: on the NGC 3201
    frames every star within ~5" of the centre passed the PSF-star SNR cut, the
    central ePSF was built from m = 24-27 stars (box / true flux up to 14) and
    its peak came out 40 % low, leaving the m < 21 stars there ~1 mas off.

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    x, y : ndarray
        Star positions [pixel] (rounded to the nearest pixel).
    half : int
        Half-size of the box [pixel].
    ring : tuple of int or None
        Inner and outer Chebyshev distance of the local-background ring [pixel].
    chunk : int
        Stars processed at once (memory bound only).
    sky : ndarray, optional
        Background per pixel of each star [electron] (``ring`` is then not used).

    Returns
    -------
    ndarray
        Box flux minus background [electron], one per star.
    """
    ny, nx = frame.shape
    x = np.rint(np.nan_to_num(np.asarray(x, float))).astype(int)
    y = np.rint(np.nan_to_num(np.asarray(y, float))).astype(int)
    out = np.zeros(len(x))
    if sky is not None:
        ring = None
    reach = half if ring is None else max(half, ring[1])
    off = np.arange(-reach, reach + 1)
    cheb = np.maximum(np.abs(off)[:, None], np.abs(off)[None, :])
    in_box = cheb <= half
    in_ring = None if ring is None else (cheb >= ring[0]) & (cheb <= ring[1])
    for start in range(0, len(x), chunk):
        sl = slice(start, start + chunk)
        cx, cy = x[sl, None] + off, y[sl, None] + off
        inside = ((cy >= 0) & (cy < ny))[:, :, None] & ((cx >= 0) & (cx < nx))[:, None, :]
        rows, cols = np.clip(cy, 0, ny - 1)[:, :, None], np.clip(cx, 0, nx - 1)[:, None, :]
        cut = frame.image[rows, cols]
        good = inside & ~frame.bad[rows, cols] & np.isfinite(cut)
        local = np.full(len(cut), frame.sky) if sky is None else np.asarray(sky, float)[sl]
        if in_ring is not None:
            with warnings.catch_warnings():  # a ring without usable pixels: the frame's sky
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(np.where(good & in_ring, cut, np.nan).reshape(len(cut), -1), 1)
            local = np.where(np.isfinite(med), med, frame.sky)
        out[sl] = np.sum(np.where(good & in_box, cut - local[:, None, None], 0.0), axis=(1, 2))
    return out


def epsf_options(settings: MeasureSettings) -> EPSFOptions:
    """ePSF building options from the stage settings.

    Parameters
    ----------
    settings : MeasureSettings
        The stage settings.

    Returns
    -------
    EPSFOptions
        The ePSF builder's options.
    """
    return EPSFOptions(
        variation=settings.psf_variation,
        grid=settings.psf_grid,
        poly_order=settings.psf_poly_order,
        size=settings.epsf_size,
        oversampling=settings.oversampling,
        maxiters=settings.epsf_iterations,
        builder=settings.epsf_builder,
        stars_per_node=settings.psf_stars_per_node,
        isolation=settings.psf_star_isolation,
        clean_neighbour_ratio=settings.psf_star_neighbour_ratio,
        min_snr=settings.psf_star_min_snr,
        fit_radius=settings.stamp_radius,
        fit_sky_gradient=settings.sky_gradient,
        max_gradient=settings.psf_star_max_gradient,
    )


def fit_options(settings: MeasureSettings) -> FitOptions:
    """Batched-fitter options from the stage settings.

    Parameters
    ----------
    settings : MeasureSettings
        The stage settings.

    Returns
    -------
    FitOptions
        The fast engine's options.
    """
    return FitOptions(
        radius=settings.stamp_radius,
        iterations=settings.iterations,
        tolerance=settings.tolerance,
        relative_tolerance=settings.relative_tolerance,
        chi2_tolerance=settings.chi2_tolerance,
        flux_refresh=settings.flux_refresh,
        flux_passes=settings.flux_passes,
        check_cut_steps=settings.check_cut_steps,
        bisect_reversals=settings.bisect_reversals,
        crowded_window=int(settings.crowded_window),
        crowded_ratio=settings.crowded_ratio,
        max_shift=settings.max_shift,
        min_snr=settings.min_snr,
        chunk=settings.chunk,
        threads=settings.threads,
        progress=settings.progress,
        sky_gradient=settings.sky_gradient,
        wing_threshold=settings.wing_threshold,
        halo_radius=settings.halo_radius,
        halo_rings=settings.halo_rings,
        halo_stack=settings.halo_stack,
        halo_stack_stars=settings.halo_stack_stars,
        halo_tail=settings.halo_tail,
        halo_background=settings.halo_background,
        halo_saturated=settings.halo_saturated,
        halo_map=settings.halo_map,
        halo_map_block=settings.halo_map_block,
        halo_map_arc=settings.halo_map_arc,
        halo_map_core=settings.halo_map_core,
    )


def psf_star_fit_options(settings: MeasureSettings) -> FitOptions:
    """Fitter options of the PSF stars' short refits inside an ePSF or PSF-R build.

    Four sweeps from the previous positions (at most 1 px away), no SNR cut (PSF stars
    are bright), the stage's stamp radius and sky plane.

    Parameters
    ----------
    settings : MeasureSettings

    Returns
    -------
    FitOptions
    """
    return FitOptions(
        radius=settings.stamp_radius,
        iterations=4,
        max_shift=1.0,
        min_snr=0.0,
        sky_gradient=settings.sky_gradient,
        threads=settings.threads,
    )


def run_engine(
    frame: Frame,
    psf: VariableEPSF,
    x0,
    y0,
    settings: MeasureSettings,
    engine=None,
    return_model: bool = True,
    halo: np.ndarray | None = None,
    halo_shape: HaloShape | None = None,
    return_light: bool = False,
    hold_positions: np.ndarray | None = None,
) -> FitResult:
    """Fit all stars with the selected engine.

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    psf : VariableEPSF
        The ePSF.
    x0, y0 : ndarray
        Start positions [pixel].
    settings : MeasureSettings
        The stage settings.
    engine : {"fast", "photutils"}, optional
        Engine (default: ``settings.engine``).
    return_model : bool
        Whether the fast engine returns its frame-sized model image (needed for neighbour
        subtraction only).
    halo : ndarray, optional
        The frame's halo profile from an earlier fit of the frame
        (:attr:`FitResult.halo_profile`); None: the fast engine measures it.
    halo_shape : HaloShape, optional
        The halo's non-round shape (:attr:`FramePSF.halo_shape`); None: round.
    return_light : bool
        The fast engine also returns all its modelled light
        (:attr:`FitResult.light_image`, for the rescue pass).
    hold_positions : ndarray of bool, optional
        The fast engine holds these stars' positions at their start
        (:func:`~mavispm.measure.stars.batched_fit.fit_stars`); the photutils engine
        refuses them.

    Returns
    -------
    FitResult
        Per-star fit results.

    Raises
    ------
    InputError
        For an unknown engine.
    """
    engine = engine or settings.engine
    common = dict(
        read_noise_var=frame.read_noise_var,
        sky0=frame.sky,
        bad=frame.bad,
        saturated=frame.saturated,
    )
    if engine == "fast":
        return fit_stars(
            frame.image,
            psf,
            x0,
            y0,
            options=fit_options(settings),
            return_model=return_model,
            halo=halo,
            halo_shape=halo_shape,
            return_light=return_light,
            hold_positions=hold_positions,
            **common,
        )
    if engine == "photutils":
        if hold_positions is not None:
            raise InputError("hold_positions needs engine 'fast'; photutils fits every position")
        opt = PhotutilsOptions(
            radius=settings.stamp_radius,
            fitter=settings.photutils_fitter,
            group_separation=settings.group_separation,
            grid=max(settings.psf_grid, 3),
        )
        return fit_stars_photutils(frame.image, psf, x0, y0, options=opt, **common)
    raise InputError(f"unknown engine '{engine}'; expected 'fast' or 'photutils'")


@dataclass
class FramePSF:
    """The frame's ePSF and what the error model needs of its building.

    Parameters
    ----------
    psf : VariableEPSF
        The ePSF from all PSF stars.
    n_psf_stars : int
        PSF stars used.
    halves : tuple of VariableEPSF or None
        ePSFs from the two halves of every node's PSF stars (None when not asked
        for, or with fewer than :data:`MIN_STARS_SPLIT` PSF stars per node).
    psfr_kernels : ndarray (K, 4) or None
        PSF-R model: the fitted corrections per node, kernel ``(cxx, cyy, cxy)`` [mas^2]
        and stretch of the prior.
    halo : ndarray or None
        The frame's halo profile (:attr:`FitResult.halo_profile`) that the building's
        neighbour passes used, or the one it was given; None when no fit measured it.
    centring : tuple of NodeCentring or None
        The node centring on all stars
        (:func:`mavispm.measure.stars.node_centring.centred_on_all_stars`) of the
        ePSF and its halves; None: the nodes are centred on their PSF stars.
    halo_shape : HaloShape or None
        PSF-R model: the non-round shape of the bright stars' light beyond their stamps
        (:func:`~mavispm.measure.stars.halo_shape.prior_halo_shape`), for the fast
        engine; None: round.
    """

    psf: VariableEPSF
    n_psf_stars: int
    halves: tuple[VariableEPSF, VariableEPSF] | None = None
    psfr_kernels: np.ndarray | None = None
    halo: np.ndarray | None = None
    centring: tuple | None = None
    halo_shape: HaloShape | None = None


#: PSF stars per node needed to build the two half-set ePSFs of the error model.
MIN_STARS_SPLIT = 6


def build_psf(frame: Frame, x0, y0, settings: MeasureSettings, anchor=None, halo=None) -> FramePSF:
    """ePSF from the frame, rebuilt after neighbour subtraction ``neighbour_passes`` times.

    With ``settings.error_model == "epsf"`` the last build is repeated with each
    half of the PSF stars (the ePSF model-error estimate). ``anchor`` (observer
    mode: :class:`~mavispm.measure.stars.epsf_anchor.EarlierAnchor`) centres every
    node ePSF of every build on the earlier epoch's ePSF.

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    x0, y0 : ndarray
        Star positions [pixel] from which the PSF stars are chosen.
    settings : MeasureSettings
        The stage settings.
    anchor : EarlierAnchor, optional
        The earlier epoch's ePSF (observer mode); None: no anchoring.
    halo : ndarray, optional
        The frame's halo profile from an earlier fit (:func:`run_engine`); None: the
        first neighbour pass measures it.

    Returns
    -------
    FramePSF
        The ePSF, the number of PSF stars, the half-set ePSFs (or None) and the halo
        profile.
    """
    opts = epsf_options(settings)
    data = frame.image - frame.sky
    noise = frame.sky + frame.read_noise_var
    flux = box_flux(frame, x0, y0)
    upper = neighbour_rating(frame, x0, y0, flux, settings)
    if settings.uses_psfr:
        return replace(build_psfr(frame, x0, y0, settings, flux, upper, data, noise), halo=halo)
    build = dict(image=data, x=x0, y=y0, flux=flux, bad=frame.bad, noise_floor=noise)
    psf, used = build_field_epsf(options=opts, neighbour_flux=upper, anchor=anchor, **build)
    isolation_flux = upper
    opts = replace(opts, oversampling=psf.oversampling)  # "auto" resolved once
    for _ in range(settings.neighbour_passes):
        # an intermediate fit for the neighbour model: the sweeps of before 2026-12-02
        passing = settings.replace(progress=False, iterations=min(settings.iterations, 10))
        fit = run_engine(frame, psf, x0, y0, passing, engine="fast", halo=halo)
        halo = fit.halo_profile
        fitted_flux = np.where(fit.flag & FLAG_FAILED, 0.0, np.nan_to_num(fit.flux))
        build = dict(
            build,
            x=fit.x,
            y=fit.y,
            flux=fitted_flux,
            neighbour_model=fit.model_image,
            previous=psf,
            model_radius=settings.stamp_radius,
            # each node stays centred on its PSF stars' start positions, as in the first
            # build: anchored to the fitted positions, it took over their errors, which
            # the first ePSF's interpolation between nodes had put there (NGC 3201
            # frame: V 17-20 at 3.7 x CRLB, 2.8 x so; docs/measure.md)
            start=(x0, y0),
        )
        psf, used = build_field_epsf(options=opts, anchor=anchor, **build)
        isolation_flux = None
    halves = None
    per_node = min(settings.psf_stars_per_node, len(used))
    if settings.error_model == "epsf" and per_node >= MIN_STARS_SPLIT:
        try:
            halves = tuple(half_epsf(h, build, opts, isolation_flux, anchor) for h in (0, 1))
        except InputError:  # a half too poor for an ePSF: chi^2 terms only
            halves = None
    return FramePSF(psf, len(used), halves, halo=halo)


def neighbour_rating(frame: Frame, x0, y0, flux: np.ndarray, settings: MeasureSettings):
    """The stars' fluxes as neighbours in the PSF stars' isolation test [electron].

    Not below the flux over the frame's background from a mesh of block medians
    (``psf_star_sky_mesh``; :func:`mesh_sky`): a faint star's own local background (its
    6-8 px ring, ``flux``) is raised by the bright candidate next to it, which would
    then pass as isolated. With ``psf_star_sky_mesh = 0``, not below the flux over the
    frame's global sky (before 2026-12-03: on the 1e5-star frame that flux holds the
    unresolved crowd's light, ~7.5 x a V 24-26 star's own, and the isolation test
    emptied the PSF-star pool; docs/measure-scale.md, twentieth pass).

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    x0, y0 : ndarray
        Star positions [pixel].
    flux : ndarray
        Their box fluxes over the local background (:func:`box_flux`) [electron].
    settings : MeasureSettings
        ``psf_star_sky_mesh``.

    Returns
    -------
    ndarray
        The neighbour fluxes [electron].
    """
    mesh = int(round(settings.psf_star_sky_mesh))
    sky = mesh_sky(frame, x0, y0, mesh) if mesh > 0 else None
    return np.maximum(flux, box_flux(frame, x0, y0, ring=None, sky=sky))


#: Finest PSF-R correction grid of ``psfr_grid = "auto"`` and the one it falls back to.
PSFR_AUTO_GRIDS = (5, 3)


def psfr_grid_for(
    setting, x: np.ndarray, y: np.ndarray, pool: np.ndarray, shape, per_node: int
) -> tuple[int, list[np.ndarray], np.ndarray, np.ndarray]:
    """The PSF-R correction grid and each node's PSF stars (``psfr_grid``).

    A grid of ``g x g`` nodes (cell centres) gives each node its
    ``ceil(per_node x (3 / g)^2)`` nearest stars of ``pool`` (the 3 x 3 grid's total).
    "auto": the finest of :data:`PSFR_AUTO_GRIDS` on which every node's stars lie
    within half a node spacing of it (the kernel then describes the PSF at its node,
    not an average over the field; the last one whatever the pool).

    Parameters
    ----------
    setting : int or "auto"
        ``psfr_grid``.
    x, y : ndarray
        All stars [pixel].
    pool : ndarray of int
        The usable PSF stars (:func:`~mavispm.measure.stars.epsf.psf_star_pool`).
    shape : (ny, nx)
    per_node : int
        ``psf_stars_per_node`` (at 3 x 3).

    Returns
    -------
    grid : int
    members : list of ndarray of int
        PSF stars of each node (row-major).
    gx, gy : ndarray
        Node columns / rows [pixel].
    """
    grids = PSFR_AUTO_GRIDS if setting == "auto" else (int(setting),)
    for grid in grids:
        gx, gy = node_positions(shape, grid)
        nodes = np.array([(xi, yi) for yi in gy for xi in gx])
        k = max(int(np.ceil(per_node * 9 / grid**2)), 1)
        members = node_psf_stars(x, y, pool, nodes, k)
        reach = max(np.hypot(x[m] - xn, y[m] - yn).max() for m, (xn, yn) in zip(members, nodes))
        if reach <= 0.5 * min(shape[1] / grid, shape[0] / grid):
            break
    return grid, members, gx, gy


def half_epsf(
    half: int, build: dict, opts: EPSFOptions, neighbour_flux=None, anchor=None
) -> VariableEPSF:
    """The ePSF of one half of every node's PSF stars, built as the full ePSF was.

    Every build starts from, and centres each node on, the PSF stars' start positions
    (the neighbour pass too), so a half repeats the full ePSF's last build with its
    stars only: its node centres carry the mean error of its own stars' start
    positions, which the error model then sees. (Halves built from the full chain's
    fitted positions shared its node-centre errors, and the error model missed them;
    docs/measure.md, "Error model".)

    Parameters
    ----------
    half : {0, 1}
        Which half (:func:`mavispm.measure.stars.epsf.build_field_epsf`).
    build : dict
        The keyword arguments of the full chain's last build.
    opts : EPSFOptions
        Builder options (oversampling resolved).
    neighbour_flux : ndarray, optional
        Neighbour fluxes of the isolation test, as in that build [electron].
    anchor : EarlierAnchor, optional
        Observer mode's centre convention.

    Returns
    -------
    VariableEPSF
    """
    return build_field_epsf(
        options=opts, half=half, neighbour_flux=neighbour_flux, anchor=anchor, **build
    )[0]


#: Oversampling of the PSF-R model ePSF with ``oversampling = "auto"``: the model is
#: noise-free, so the finer sampling costs nothing in accuracy.
PSFR_OVERSAMPLING = 4


def build_psfr(
    frame: Frame,
    x0,
    y0,
    settings: MeasureSettings,
    flux: np.ndarray,
    upper: np.ndarray,
    data: np.ndarray,
    noise,
) -> FramePSF:
    """The PSF-R model (prior x fitted kernels) of the frame (``psf_model = "psfr"``).

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    x0, y0 : ndarray
        Star positions [pixel] from which the PSF stars are chosen.
    settings : MeasureSettings
        The stage settings (``psf_prior``, ``psfr_width_error``, the PSF-star knobs).
    flux, upper : ndarray
        Box fluxes over the local / global sky [electron] (PSF-star selection).
    data : ndarray
        The sky-subtracted frame [electron].
    noise : float or ndarray
        Background variance per pixel [electron^2] (sky plus read noise).

    Returns
    -------
    FramePSF
        The model ePSF and the PSF stars used; with ``error_model = "epsf"`` the two
        models whose kernels were fitted to each half of every node's PSF stars.
    """
    if not settings.psf_prior:
        raise InputError("psf_model = 'psfr' needs psf_prior (a psfgrid product)", path=frame.path)
    # the kernel and position fits of its PSF stars see their stamps only
    opts = replace(epsf_options(settings), isolation=settings.psfr_star_isolation)
    ny, nx = frame.shape
    ax, ay = frame.to_arcsec(np.array([0.0, nx - 1.0]), np.array([0.0, ny - 1.0]))
    prior = read_prior(
        settings.psf_prior,
        (ax.min(), ax.max()),
        (ay.min(), ay.max()),
        settings.psfr_width_error,
        settings.psfr_strehl_error,
    )
    pool = psf_star_pool(data, x0, y0, flux, frame.bad, noise, opts, False, upper)
    _, members, gx, gy = psfr_grid_for(
        settings.psfr_grid, x0, y0, pool, frame.shape, settings.psf_stars_per_node
    )
    os_ = PSFR_OVERSAMPLING if settings.oversampling == "auto" else int(settings.oversampling)
    fit_opt = psf_star_fit_options(settings)

    def fit_positions(psf, idx):
        fit = fit_stars(
            data,
            psf,
            x0[idx],
            y0[idx],
            read_noise_var=noise,
            sky0=0.0,
            flux0=flux[idx],
            bad=frame.bad,
            options=fit_opt,
            return_model=False,
            uncertainties=False,
        )
        ok = (fit.flag & FLAG_FAILED) == 0
        return np.where(ok, fit.x, x0[idx]), np.where(ok, fit.y, y0[idx])

    common = dict(
        prior=prior,
        image=data,
        fit_positions=fit_positions,
        x_all=x0,
        y_all=y0,
        correction_x=gx,
        correction_y=gy,
        to_arcsec=frame.to_arcsec,
        to_pixel=frame.to_pixel,
        bad=frame.bad,
        noise_floor=noise,
        detector_scale=frame.pixel_scale * 1000.0,
        size=opts.size,
        oversampling=os_,
        radius=settings.stamp_radius,
        threads=settings.threads,
    )
    # the prior's transforms at the model nodes, once for the build and its half sets
    common["transforms"] = model_transforms(prior, gx, gy, frame.to_arcsec, frame.to_pixel)
    psf, kernels = build_psfr_epsf(members=members, **common)
    used = np.unique(np.concatenate(members))
    halves = None
    if settings.error_model == "epsf" and min(len(m) for m in members) >= MIN_STARS_SPLIT:
        halves = tuple(
            build_psfr_epsf(members=[m[h::2] for m in members], rounds=1, start=kernels, **common)[
                0
            ]
            for h in (0, 1)
        )
    shape = prior_halo_shape(
        prior, frame.to_pixel, frame.pixel_scale * 1000.0, kernels,
        int(settings.halo_radius), settings.stamp_radius, settings.halo_field_radial,
    )  # fmt: skip
    return FramePSF(psf, len(used), halves, kernels, halo_shape=shape)


def psfr_summary(frame_psf: FramePSF, settings: MeasureSettings) -> str | None:
    """JSON of the PSF-R model (width error, correction grid, kernels [mas^2] and stretches).

    The prior's file is the ``psf_prior`` of the product's ``config`` attribute, a
    path like the product's other path attributes; this attribute holds no path, so
    that the same measurement gives the same attribute in any run directory."""
    if frame_psf.psfr_kernels is None:
        return None
    return json.dumps(
        {
            "width_error": settings.psfr_width_error,
            "strehl_error": settings.psfr_strehl_error,
            "grid": round(np.sqrt(len(frame_psf.psfr_kernels))),
            "kernels": np.round(frame_psf.psfr_kernels, 5).tolist(),
            "kernel_columns": ["cxx", "cyy", "cxy", "stretch"],
        }
    )


def starting_positions(frame: Frame, settings: MeasureSettings, rng: np.random.Generator):
    """Forced starting positions [pixel] from the truth list, optionally perturbed.

    Parameters
    ----------
    frame : Frame
        The frame with its ``truth`` table.
    settings : MeasureSettings
        ``forced_positions`` (``"catalogue"``: the truth's ``x_cat``, ``y_cat`` [arcsec]
        converted to pixels; else ``x_pix``, ``y_pix``) and ``perturbation`` [pixel].
    rng : numpy.random.Generator
        Draws the Gaussian perturbations.

    Returns
    -------
    x0, y0 : ndarray
        Start positions [pixel].
    """
    truth = frame.truth
    if settings.forced_positions == "catalogue":
        if "x_cat" not in truth.colnames or "y_cat" not in truth.colnames:
            raise InputError(
                "forced_positions = 'catalogue' needs truth columns x_cat, y_cat", path=frame.path
            )
        x0, y0 = frame.to_pixel(
            truth["x_cat"].to_value(u.arcsec), truth["y_cat"].to_value(u.arcsec)
        )
    else:
        x0 = np.asarray(truth["x_pix"], float)
        y0 = np.asarray(truth["y_pix"], float)
    if settings.perturbation > 0:
        x0 = x0 + rng.normal(0.0, settings.perturbation, len(x0))
        y0 = y0 + rng.normal(0.0, settings.perturbation, len(y0))
    return x0, y0


def epsf_flux_fraction(fit: FitResult, flux_true: np.ndarray, usable: np.ndarray) -> float:
    """Fraction of the true flux inside the ePSF's normalisation (its footprint).

    A rendered star's light beyond the ePSF footprint (the seeing halo, far
    wings) is not in the fitted flux; the Cramer-Rao bound of the fit must use
    the flux the ePSF model describes. Estimated as the median of fitted / true
    flux of the well-measured stars (flux SNR >= 20, no flags); 1 if none.

    Parameters
    ----------
    fit : FitResult
        The fit of the frame.
    flux_true : ndarray
        True fluxes [electron].
    usable : ndarray of bool
        Stars whose fit did not fail.

    Returns
    -------
    float
        The fraction, clipped to [1e-3, 2].
    """
    with np.errstate(all="ignore"):
        snr = fit.flux / fit.flux_err
        ratio = fit.flux / flux_true
    good = usable & (fit.flag == 0) & np.isfinite(ratio) & (snr >= 20) & (flux_true > 0)
    if not good.any():
        return 1.0
    return float(np.clip(np.median(ratio[good]), 1e-3, 2.0))


def error_terms(
    frame: Frame,
    frame_psf: FramePSF,
    fit: FitResult,
    settings: MeasureSettings,
    inherited: np.ndarray | None = None,
) -> ErrorModel:
    """Error-model terms of every fitted star (:mod:`mavispm.measure.stars.error_model`).

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    frame_psf : FramePSF
        The ePSF and its half-set ePSFs.
    fit : FitResult
        The fit.
    settings : MeasureSettings
        ``error_model`` and the fitter settings.
    inherited : ndarray, optional
        Per-axis error [pixel] of the centre convention a later epoch's nodes were
        centred on (the earlier ePSF's node centring,
        :meth:`~mavispm.measure.stars.epsf_anchor.EarlierAnchor.centring_error`), added
        to the centring's own error; None: none.

    Returns
    -------
    ErrorModel
        Per-star terms (Fisher only when ``error_model = "fisher"``). With nodes centred
        on all stars, ``registration`` is the part shared with every epoch registered
        to the same list: ``inherited`` where given, else the centring's own error.
    """
    n = len(fit.x)
    if settings.error_model == "fisher":
        return ErrorModel.fisher_only(n)
    usable = (fit.flag & FLAG_FAILED) == 0
    shifts = None
    if frame_psf.halves is not None:
        sky = np.where(np.isfinite(fit.sky), fit.sky, frame.sky)
        shifts = epsf_difference_shifts(
            frame_psf.psf,
            *frame_psf.halves,
            np.where(usable, fit.x, np.nan),
            fit.y,
            fit.flux,
            sky,
            frame.read_noise_var,
            settings.stamp_radius,
            settings.chunk,
            sky_gradient=settings.sky_gradient and settings.engine == "fast",
            threads=settings.threads,
        )
    gain = fit.correlated_gain if settings.correlated_misfit else None
    npar = 6 if settings.sky_gradient and settings.engine == "fast" else 4
    dof = (2 * settings.stamp_radius + 1) ** 2 - npar
    grid = 1 if settings.psf_variation == "constant" else settings.psf_grid
    ny, nx = frame.shape
    col = np.clip(np.nan_to_num(fit.x) * grid // nx, 0, grid - 1)
    row = np.clip(np.nan_to_num(fit.y) * grid // ny, 0, grid - 1)
    cells = (row * grid + col).astype(np.intp)
    if frame_psf.psfr_kernels is None:
        # nodes centred on all stars: a bright star's chi^2 grows with its flux (the
        # ePSF's shape misfit) without moving it, as with the PSF-R model; its
        # position error beyond Fisher is the half-set term (within a cell), the
        # node centring's own error (its least-squares covariance) and, at a later
        # epoch, the error of the earlier convention it was centred on
        centred = frame_psf.centring is not None
        model = estimate_error_model(
            fit.flux, fit.chi2, usable, shifts, cells, relative_chi2=centred,
            correlated_gain=gain, halo_share=fit.halo_share, chi2_dof=dof,
            chi2_odd=fit.chi2_odd,
        )  # fmt: skip
        if centred:
            node_err = frame_psf.centring[0].error_at(frame_psf.psf, fit.x, fit.y)
            # the registration to the reference list: the first epoch's own centring,
            # a later epoch's inherited one (its own is against its refined start)
            registration = node_err if inherited is None else inherited
            if inherited is not None:
                node_err = np.hypot(node_err, inherited)
            model = replace(
                model, position=np.hypot(model.position, node_err), registration=registration
            )
        return model
    # PSF-R model: chi^2 against the star's peers, plus the model-error floor
    return estimate_error_model(
        fit.flux,
        fit.chi2,
        usable,
        shifts,
        cells,
        relative_chi2=True,
        floor_fraction=settings.psfr_model_error,
        fisher_position=np.hypot(fit.x_err, fit.y_err) / np.sqrt(2.0),
        crowding=fit.crowding,
        correlated_gain=gain,
        halo_share=fit.halo_share,
        chi2_dof=dof,
        chi2_odd=fit.chi2_odd,
    )


def rescue_options(settings: MeasureSettings) -> RescueOptions:
    """The rescue pass's options from the stage settings (``rescue_radius``, the
    fitter's stamp, ``min_snr`` and ``max_shift``)."""
    return RescueOptions(
        radius=settings.rescue_radius,
        stamp_radius=settings.stamp_radius,
        min_snr=settings.min_snr,
        max_shift=settings.max_shift,
    )


def with_rescued(fit: FitResult, rescued: Rescued) -> FitResult:
    """``fit`` with the rescued stars' rows replaced and their flags 1 and 32 cleared."""
    i = rescued.index
    out = {}
    for name in ("x", "y", "flux", "sky", "x_err", "y_err", "flux_err", "sky_err", "chi2"):
        arr = np.array(getattr(fit, name), float)
        arr[i] = getattr(rescued, name)
        out[name] = arr
    for name in ("chi2_odd", "crowding"):
        if getattr(fit, name) is not None:
            arr = np.array(getattr(fit, name), float)
            arr[i] = getattr(rescued, name)
            out[name] = arr
    flag = np.array(fit.flag)
    flag[i] &= ~(FLAG_NOT_CONVERGED | FLAG_FAILED)
    return replace(fit, flag=flag, **out)


def merge_rows(base: ErrorModel, other: ErrorModel, rows: np.ndarray) -> ErrorModel:
    """``base`` with the per-star rows ``rows`` of every array term taken from ``other``."""
    out = {}
    for name in ("position", "flux", "chi2_ratio", "chi2_inflation", "registration",
                 "correlated", "position_ratio", "position_inflation"):  # fmt: skip
        a, b = getattr(base, name), getattr(other, name)
        if a is None or b is None or np.ndim(a) == 0:
            continue
        a = np.array(a, copy=True)
        a[rows] = b[rows]
        out[name] = a
    return replace(base, **out)


def refined_start(frame: Frame, x0, y0, settings: MeasureSettings, anchor=None):
    """Start positions [pixel] refined by one quick measurement (fast fit); failed
    stars keep their start; and the frame's halo profile that fit measured.

    Carried positions are off by each star's motion since the earlier epoch (a
    few tenths of a pixel); an ePSF built on them is blurred and anchored to
    them, which doubled the bright-star scatter on the NGC 3201 frames. The fit
    uses the earlier epoch's ePSF when ``anchor`` holds it
    (:meth:`~mavispm.measure.stars.epsf_anchor.EarlierAnchor.mapped_psf`), else a
    quick ePSF from the start list (no neighbour passes). An ePSF built on the
    carried positions has pixel-phase errors (it is blurred by the motions); the
    builder of the real ePSF keeps the pixel-phase pattern of its start
    positions (:func:`~mavispm.measure.stars.epsf.build_epsf_fast`), so starts
    measured with it passed those errors on (30-50 uas per star at V < 22 on the
    full NGC 3201 frame, against the truth-forced measurement of the same frame).

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    x0, y0 : ndarray
        Carried start positions [pixel].
    settings : MeasureSettings
        The stage settings.
    anchor : EarlierAnchor, optional
        The earlier epoch's ePSF (observer mode), used for the quick fit; None: a quick
        ePSF from the start list.

    Returns
    -------
    x, y : ndarray
        Refined positions [pixel].
    halo : ndarray or None
        The frame's halo profile (:attr:`FitResult.halo_profile`).
    """
    quick = settings.replace(
        neighbour_passes=0,
        error_model="fisher",
        progress=False,
        iterations=min(settings.iterations, 10),
    )
    if anchor is not None:
        psf = anchor.mapped_psf()
    else:
        psf = build_psf(frame, x0, y0, quick).psf
    fit = run_engine(frame, psf, x0, y0, quick, engine="fast", return_model=False)
    ok = ((fit.flag & FLAG_FAILED) == 0) & np.isfinite(fit.x) & np.isfinite(fit.y)
    return np.where(ok, fit.x, x0), np.where(ok, fit.y, y0), fit.halo_profile


def blind_detection(frame: Frame, settings: MeasureSettings):
    """Blind-mode start list [pixel] and detection attributes (``n_first``, passes).

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    settings : MeasureSettings
        ``detection_method`` (``"daofind"`` or the PSF-based detector), its threshold,
        FWHM (default 2.5 pixels), passes and model error.

    Returns
    -------
    x0, y0 : ndarray
        Detected positions [pixel].
    attrs : dict
        ``first_pass`` and ``passes`` (JSON) for the PSF-based detector; empty for daofind.
    halo : ndarray or None
        The frame's halo profile measured by the detector's first fit (None for daofind).
    """
    fwhm = settings.detection_fwhm or 2.5
    if settings.detection_method == "daofind":
        noise = np.sqrt(frame.sky + frame.read_noise_var)
        x0, y0, _ = detect_sources(
            frame.image, frame.sky, noise, fwhm, settings.detection_threshold, frame.bad
        )
        return x0, y0, {}, None
    from mavispm.measure.stars.psf_detection import DetectionOptions, detect_stars

    opts = DetectionOptions(
        threshold=settings.detection_threshold,
        fwhm=fwhm,
        passes=settings.detection_passes,
        model_error=settings.detection_model_error,
        wing_radius=int(round(settings.detection_wing_radius)),
    )
    x0, y0, info = detect_stars(frame, settings, build_psf, run_engine, opts)
    attrs = {"first_pass": info["n_first"], "passes": json.dumps(info["n_pass"])}
    return x0, y0, attrs, info.get("halo_profile")


def earlier_anchor(
    earlier: list[EarlierEpoch], transforms: list, settings: MeasureSettings
) -> EarlierAnchor | None:
    """The ePSF anchor of an observer-mode epoch: the earliest earlier epoch with an
    ePSF (its centre convention is the input list's), or None (``epsf_anchor =
    "start"``, or no earlier ePSF known).

    Parameters
    ----------
    earlier : list of EarlierEpoch
        The earlier epochs' measurements.
    transforms : list of EpochTransform
        Their affine maps to this frame, in time order of ``earlier``.
    settings : MeasureSettings
        ``epsf_anchor``.

    Returns
    -------
    EarlierAnchor or None
        The anchor.
    """
    if settings.epsf_anchor != "earlier":
        return None
    for ep, tr in zip(sorted(earlier, key=_epoch), transforms):
        if ep.psf is not None:
            return EarlierAnchor(ep.psf, tr.a, tr.b, centring=ep.centring)
    return None


def anchor_summary(anchor: EarlierAnchor | None, pixel_scale: float) -> str:
    """JSON of the ePSF anchoring: ``"start"``, or ``"earlier"`` with the rms node shift
    (x, y) [mas] over all node ePSFs built (quick start refinement, builds, halves).

    Parameters
    ----------
    anchor : EarlierAnchor or None
        The anchor used.
    pixel_scale : float
        Detector pixel [arcsec].

    Returns
    -------
    str
        The JSON text.
    """
    if anchor is None or not anchor.shifts:
        return json.dumps({"anchor": "start"})
    s = np.asarray(anchor.shifts)
    rms = np.sqrt(np.mean(s[:, 2:] ** 2, axis=0)) * pixel_scale * 1000.0
    return json.dumps(
        {"anchor": "earlier", "n_nodes": len(s), "rms_shift_mas": [float(v) for v in rms]}
    )


def carried_truth_ids(earlier: list[EarlierEpoch], ids: np.ndarray) -> np.ndarray:
    """Truth ids (scoring only) of carried stars: each id's ``id_true`` in the latest
    earlier epoch that has it (the id itself where the product has no ``id_true``:
    forced epochs and products written before the column; -1 for an earlier
    detection without a truth match).

    Parameters
    ----------
    earlier : list of EarlierEpoch
        The earlier epochs' measurements.
    ids : ndarray of int
        Ids of the carried stars.

    Returns
    -------
    ndarray of int64
        Truth id per star.
    """
    lookup: dict[int, int] = {}
    for ep in sorted(earlier, key=_epoch):
        true = ep.ids if ep.ids_true is None else ep.ids_true
        lookup.update(zip(ep.ids.tolist(), true.tolist()))
    return np.fromiter((lookup.get(i, i) for i in ids.tolist()), np.int64, len(ids))


def _epoch(e: EarlierEpoch) -> float:
    return e.epoch


def _index_by_id(ids: np.ndarray, truth_ids: np.ndarray) -> np.ndarray:
    """Row of each id in ``truth_ids`` (-1 where absent)."""
    if len(truth_ids) == 0:
        return np.full(len(ids), -1, np.intp)
    order = np.argsort(truth_ids, kind="stable")
    sorted_ids = truth_ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, ids), 0, max(len(sorted_ids) - 1, 0))
    hit = sorted_ids[pos] == ids
    return np.where(hit, order[pos], -1)


def measure_frame(
    frame: Frame,
    settings: MeasureSettings,
    seed: int | None = None,
    earlier: list[EarlierEpoch] | None = None,
):
    """Measure all stars of a frame.

    Parameters
    ----------
    frame : Frame
    settings : MeasureSettings
    seed : int, optional
        Seed of the forced-position perturbation.
    earlier : list of EarlierEpoch, optional
        Earlier epochs' measured stars. With ``settings.later_epochs ==
        "measured"`` (observer mode) the start list is their positions moved
        into this frame (:func:`mavispm.measure.stars.start_list.start_from_earlier`)
        and the truth is used for scoring only (matched by id).

    Returns
    -------
    stars : QTable
        The ``stars`` table of the measured product.
    attrs : dict
        Product attributes (engine, timing, ePSF description, blind-mode scores).
    psf : VariableEPSF
    """
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    truth = frame.truth
    extra: dict = {}
    anchor = None
    carried = bool(earlier) and settings.later_epochs == "measured"
    halo = None  # the frame's halo profile, measured by its first fit and then reused
    if carried:
        ids, x0, y0, transforms = start_from_earlier(earlier, frame.image, frame.sky, frame.bad)
        if len(ids) == 0:
            raise InputError("observer mode: no earlier star falls in this frame", path=frame.path)
        extra["start"] = "measured"
        anchor = earlier_anchor(earlier, transforms, settings)
        if settings.refine_start:
            x0, y0, halo = refined_start(frame, x0, y0, settings, anchor)
        extra["start_transform"] = json.dumps(
            {f"{e.epoch:g}": t.to_dict() for e, t in zip(sorted(earlier, key=_epoch), transforms)}
        )
    elif settings.blind:
        x0, y0, found, halo = blind_detection(frame, settings)
        extra.update(found)
        if len(x0) == 0:
            raise InputError(
                "blind mode: no sources detected (lower detection_threshold?)", path=frame.path
            )
        ids = np.arange(len(x0), dtype=np.int64)  # detection index: all an observer has
    else:
        x0, y0 = starting_positions(frame, settings, rng)
        ids = np.asarray(truth["id"], np.int64)
        extra["start"] = "truth"
    if settings.blind and not carried:
        extra["start"] = "detected"
    frame_psf = build_psf(frame, x0, y0, settings, anchor, halo)
    psf, n_psf = frame_psf.psf, frame_psf.n_psf_stars
    t_psf = time.perf_counter()
    fit = run_engine(
        frame, psf, x0, y0, settings, return_model=False, halo=frame_psf.halo,
        halo_shape=frame_psf.halo_shape,
        return_light=settings.rescue_radius > 0 and settings.engine == "fast",
    )  # fmt: skip
    centring = None
    inherited = None
    registration_reference = None
    # a later epoch's start refined with the earlier ePSF is measured on this frame (the
    # motions are in it): centred on it, the new ePSF keeps the earlier one's convention
    # star by star. A carried start not refined so holds the stars' motions: that epoch
    # keeps its builder's convention (the earlier ePSF's core, or its PSF stars' carried
    # positions with epsf_anchor = "start")
    refined = carried and anchor is not None and settings.refine_start
    if (
        (refined or not carried)
        and settings.epsf_centring == "all"
        and frame_psf.psfr_kernels is None
    ):
        frame_psf, fit = centred_on_all_stars(frame, frame_psf, fit, x0, y0, settings)
        psf, centring = frame_psf.psf, frame_psf.centring
        if centring:
            own = "refined" if carried else extra["start"]
            centring[0].reference_id = reference_list_id(
                own, float(frame.epoch.to_value(u.yr)), ids, x0, y0
            )
            registration_reference = centring[0].reference_id
        if refined and centring:
            inherited = anchor.centring_error(fit.x, fit.y)
            registration_reference = getattr(anchor.centring, "reference_id", None)
    rescued = None
    if fit.light_image is not None:  # refit the failed blends (rescue_radius)
        rescued = rescue_stars(
            frame.image, fit.light_image, psf, fit, x0, y0, frame.read_noise_var, frame.sky,
            frame.bad, frame.saturated, rescue_options(settings),
        )  # fmt: skip
        fit = replace(fit, light_image=None)
    t_fit = time.perf_counter()
    errors = error_terms(frame, frame_psf, fit, settings, inherited)
    fit_before = fit  # every star not rescued keeps what it had
    if rescued is not None and len(rescued.index):
        fit = with_rescued(fit, rescued)
        # the rescued stars' error terms, with them among their peers
        errors = merge_rows(errors, error_terms(frame, frame_psf, fit, settings, inherited),
                            rescued.index)  # fmt: skip
    t_err = time.perf_counter()
    flag = fit.flag.copy()
    crowded = crowding_flags(
        fit_before.x, fit_before.y, fit_before.flux, settings.crowding_radius,
        settings.crowding_ratio,
    )  # fmt: skip
    if rescued is not None and len(rescued.index):
        crowded[rescued.index] = crowding_flags(
            fit.x, fit.y, fit.flux, settings.crowding_radius, settings.crowding_ratio
        )[rescued.index]
    flag[crowded] |= FLAG_CROWDED
    # stars that start at (nearly) one position cannot be told apart by the fit either
    flag[crowding_flags(x0, y0, np.ones(len(x0)), UNRESOLVED_SEPARATION, np.inf)] |= FLAG_CROWDED
    n = len(x0)
    x_true = y_true = mag = flux_true = dist = crlb_x = crlb_y = np.full(n, np.nan)
    if truth is not None:
        tx, ty = np.asarray(truth["x_pix"], float), np.asarray(truth["y_pix"], float)
        if carried:  # scoring only: the carried stars' truth ids (their earlier id_true)
            index = _index_by_id(carried_truth_ids(earlier, ids), np.asarray(truth["id"], np.int64))
            sel = np.maximum(index, 0)
            dist = np.where(index >= 0, np.hypot(fit.x - tx[sel], fit.y - ty[sel]), np.nan)
            ok = (index >= 0) & (dist <= settings.match_radius)
        elif settings.blind:
            index, dist = match_to_truth(fit.x, fit.y, tx, ty, settings.match_radius)
            ok = index >= 0
            extra.update(completeness(fit.x, fit.y, tx, ty, settings.match_radius))
            r_det = np.hypot(*frame.to_arcsec(fit.x, fit.y))
            r_true = np.hypot(*frame.to_arcsec(tx, ty))
            scores = detection_scores(
                fit.x, fit.y, fit.flux, tx, ty, truth["mag"].to_value(u.mag),
                settings.match_radius, r_det, r_true,
            )  # fmt: skip
            extra["false_fraction_v26"] = scores.pop("false_fraction_v26")
            extra["scores"] = json.dumps(scores)
        else:
            index = np.arange(n)
            dist = np.hypot(fit.x - tx, fit.y - ty)
            ok = dist <= settings.match_radius
        flag[~ok] |= FLAG_NO_MATCH
        # forced mode knows each star's identity: keep its truth even when unmatched
        known = index >= 0
        sel = np.maximum(index, 0)
        id_true = np.where(known, np.asarray(truth["id"], np.int64)[sel], -1)
        x_true = np.where(known, truth["x"].to_value(u.arcsec)[sel], np.nan)
        y_true = np.where(known, truth["y"].to_value(u.arcsec)[sel], np.nan)
        mag = np.where(known, truth["mag"].to_value(u.mag)[sel], np.nan)
        flux_true = np.where(known, truth["flux"].to_value(u.electron)[sel], np.nan)
        dist = np.where(known & np.isfinite(dist), dist, np.nan)
        # the input stars the frame can show: true centres on the detector (the rest are
        # rendered for the light they spill in, and fail by design)
        shown = on_detector(tx, ty, frame.shape)
        extra["truth_bin_counts"] = truth_bin_counts(truth["mag"].to_value(u.mag)[shown])
        sky = np.where(np.isfinite(fit.sky), fit.sky, frame.sky)
        fraction = epsf_flux_fraction(fit_before, flux_true, known & ok)
        extra["epsf_flux_fraction"] = fraction
        bound = crlb(
            psf,
            tx[sel],
            ty[sel],
            np.maximum(flux_true * fraction, 0.0),
            sky,
            frame.read_noise_var,
            settings.stamp_radius,
        )
        crlb_x = np.where(known, bound[:, 0], np.nan)
        crlb_y = np.where(known, bound[:, 1], np.nan)
    scale = frame.pixel_scale
    x_as, y_as = frame.to_arcsec(fit.x, fit.y)
    stars = QTable()
    stars["id"] = ids
    if truth is not None:
        stars["id_true"] = id_true.astype(np.int64)
    stars["x_pix"] = fit.x
    stars["y_pix"] = fit.y
    stars["x"] = x_as * u.arcsec
    stars["y"] = y_as * u.arcsec
    stars["x_err"] = errors.position_total(fit.x_err, 0) * scale * u.arcsec
    stars["y_err"] = errors.position_total(fit.y_err, 1) * scale * u.arcsec
    stars["flux"] = fit.flux * u.electron
    stars["flux_err"] = errors.total(fit.flux_err, errors.flux) * u.electron
    stars["sky"] = fit.sky * u.electron
    stars["chi2"] = fit.chi2
    stars["flag"] = flag.astype(np.int64)
    if truth is not None:
        stars["x_true"] = x_true * u.arcsec
        stars["y_true"] = y_true * u.arcsec
        stars["mag"] = mag * u.mag
        stars["match_dist"] = dist * scale * u.arcsec
        stars["flux_true"] = flux_true * u.electron
        stars["crlb_x"] = crlb_x * scale * u.arcsec
        stars["crlb_y"] = crlb_y * scale * u.arcsec
    stars["x_err_fisher"] = fit.x_err * scale * u.arcsec
    stars["y_err_fisher"] = fit.y_err * scale * u.arcsec
    stars["flux_err_fisher"] = fit.flux_err * u.electron
    stars["err_epsf"] = errors.position * scale * u.arcsec
    registration = errors.shared_position()  # as it enters x_err, y_err
    stars["x_err_registration"] = registration * scale * u.arcsec
    stars["y_err_registration"] = registration * scale * u.arcsec
    attrs = {
        "engine": settings.engine,
        "psf_variation": psf.kind,
        "n_psf_stars": int(n_psf),
        "time_epsf": (t_psf - t0) * u.s,
        "time_fit": (t_fit - t_psf) * u.s,
        "time_errors": (t_err - t_fit) * u.s,
        "fit_iterations": int(fit.iterations),
        "rescue_tried": rescued.tried if rescued is not None else 0,
        "rescued": len(rescued.index) if rescued is not None else 0,
        "error_model": errors.kind,
        "epsf_position_error": float(np.nanmedian(errors.position) * scale * 1000.0) * u.mas,
        "blind": bool(settings.blind),
        "start": extra.pop("start"),
        "start_transform": extra.pop("start_transform", None),
        "epsf_anchor": anchor_summary(anchor, frame.pixel_scale),
        "epsf_centring": centring_summary(
            centring,
            frame.pixel_scale,
            "refined" if carried else "start",
            centring[0].reference_id if centring else None,
        ),
        "registration_reference": (
            registration_reference if errors.registration is not None else None
        ),
        "psf_model": "psfr" if frame_psf.psfr_kernels is not None else "epsf",
        "psfr": psfr_summary(frame_psf, settings),
        "truth_bin_counts": extra.pop("truth_bin_counts", None),
        "detector_shape": list(frame.shape),
        "epsf_flux_fraction": extra.pop("epsf_flux_fraction", None),
        **{f"detect_{k}": v for k, v in extra.items()},
    }
    return stars, attrs, psf
