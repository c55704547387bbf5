"""Empirical ePSF building from the frame with photutils (EPSFBuilder, extract_stars).

PSF stars are chosen automatically: bright (flux SNR), unsaturated (no
saturated or NaN pixel in the cut-out), away from the edge, and isolated (no
neighbour within the isolation radius brighter than a fraction of the star).
In crowded fields the neighbours are first subtracted with the current model
(:func:`build_field_epsf` with a neighbour model), as DAOPhot does.

Field variability: ePSFs are built at the nodes of a ``grid x grid`` mesh from
the PSF stars nearest to each node (``grid``), and optionally turned into a
DAOPhot-style polynomially variable PSF by a least-squares fit over the nodes
(``polynomial``). See :mod:`mavispm.measure.stars.variable_psf`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from astropy.nddata import NDData
from astropy.table import Table
from photutils.psf import EPSFBuilder, extract_stars
from scipy import ndimage
from scipy.spatial import cKDTree

from mavispm.core.errors import InputError
from mavispm.measure.stars.batched_fit import FitOptions, fit_stars, render_model
from mavispm.measure.stars.variable_psf import (
    StampGeometry,
    VariableEPSF,
    constant_epsf,
    gridded_epsf,
    polynomial_epsf,
)

__all__ = [
    "AUTO_OVERSAMPLING_X4",
    "EPSFOptions",
    "background_gradient",
    "build_epsf",
    "build_epsf_fast",
    "build_epsf_photutils",
    "build_field_epsf",
    "neighbours_subtracted",
    "node_positions",
    "node_psf_stars",
    "psf_star_pool",
    "resolve_oversampling",
    "select_psf_stars",
]


@dataclass(frozen=True)
class EPSFOptions:
    """How the ePSF is built.

    Parameters
    ----------
    variation : str
        "constant", "grid" or "polynomial".
    grid : int
        Nodes per axis of the ePSF grid (also the sampling of the polynomial fit).
    poly_order : int
        Order of the polynomial variation (3 = DAOPhot's cubically variable PSF).
    size : int
        ePSF footprint [pixel] (odd).
    oversampling : int or "auto"
        ePSF oversampling factor ("auto": :func:`resolve_oversampling`).
    maxiters : int
        EPSFBuilder iterations.
    stars_per_node : int
        PSF stars used for each node's ePSF (the nearest ones).
    isolation : float
        Isolation radius [pixel].
    isolation_ratio : float
        Neighbours fainter than this fraction of the star are tolerated (when
        neighbours are subtracted, this is relaxed to ``neighbour_ratio``).
    neighbour_ratio : float
        Tolerated neighbour brightness once neighbours are subtracted, when the
        stars within ``clean_neighbour_ratio`` are too few.
    clean_neighbour_ratio : float
        Tolerated neighbour brightness once neighbours are subtracted, used when it
        leaves at least ``min(stars_per_node, MIN_CLEAN_PER_NODE)`` stars per node:
        a neighbour as bright as the PSF star, subtracted with the previous ePSF,
        leaves a residual that moves the node's ePSF (docs/measure.md, step 1).
    min_snr : float
        Minimum flux SNR of a PSF star.
    builder : str
        "fast" (our vectorised builder) or "photutils" (EPSFBuilder).
    neighbour_mask : float
        Pixels within this distance [pixel] of another star, and closer to it
        than to the PSF star, are not used (fast builder).
    fit_radius : int
        Stamp half-width [pixel] of the star refits while building; use the final
        fit's radius so that the ePSF centre is anchored in the same way.
    fit_sky_gradient : bool
        Fit each star's local sky as a plane in those refits; use the final fit's
        sky model (``sky_gradient``), for the same reason: with a constant sky
        here and a plane in the final fit, the 49-star rendered test frame came
        out offset by +0.047 / +0.060 mas (x / y, noise-free), with the plane in
        both by -0.010 / +0.022 mas (docs/measure.md).
    max_gradient : float
        Largest background gradient across a PSF star's cut-out, relative to its
        flux (:func:`background_gradient`); steeper backgrounds (the wings of a
        much brighter star tens of pixels away) disqualify it. 0 disables the test.
    """

    variation: str = "grid"
    grid: int = 3
    poly_order: int = 2
    size: int = 25
    oversampling: int | str = 4
    maxiters: int = 10
    stars_per_node: int = 150
    isolation: float = 12.0
    isolation_ratio: float = 0.01
    neighbour_ratio: float = 1.0
    clean_neighbour_ratio: float = 0.1
    min_snr: float = 100.0
    builder: str = "fast"
    neighbour_mask: float = 4.0
    fit_radius: int = 5
    fit_sky_gradient: bool = False
    max_gradient: float = 0.01


def select_psf_stars(
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    shape: tuple[int, int],
    bad: np.ndarray,
    size: int,
    isolation: float,
    ratio: float,
    min_flux: float,
    neighbour_flux: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of good PSF stars, brightest first.

    Parameters
    ----------
    x, y : ndarray
        Positions of all known stars [pixel].
    flux : ndarray
        Their flux estimates [electron].
    shape : (ny, nx)
    bad : ndarray of bool
        Saturated / NaN pixels.
    size : int
        Cut-out size [pixel].
    isolation : float
        Radius [pixel] within which no neighbour brighter than ``ratio * flux`` may lie.
    ratio : float
    min_flux : float
        Minimum flux [electron].
    neighbour_flux : ndarray, optional
        Flux estimates [electron] of the stars as neighbours, for the isolation
        test (default ``flux``): an upper bound such as the box flux against the
        frame's global sky, as a faint star's local background is raised by the
        bright PSF-star candidate next to it (which would then pass as isolated).

    Returns
    -------
    ndarray of int
    """
    ny, nx = shape
    half = size // 2
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(flux) & (flux >= min_flux)
    ok &= (x >= half) & (x <= nx - 1 - half) & (y >= half) & (y <= ny - 1 - half)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return idx
    # no bad pixel in the cut-out (gathered per candidate, in chunks: no full-frame pass)
    off = np.arange(-half, half + 1)
    clean = np.ones(len(idx), bool)
    for start in range(0, len(idx), 512):
        part = idx[start : start + 512]
        cx, cy = np.rint(x[part]).astype(int), np.rint(y[part]).astype(int)
        rows = np.clip(cy[:, None] + off, 0, ny - 1)
        cols = np.clip(cx[:, None] + off, 0, nx - 1)
        clean[start : start + 512] = ~bad[rows[:, :, None], cols[:, None, :]].any(axis=(1, 2))
    idx = idx[clean]
    if len(idx) == 0:
        return idx
    good_all = np.isfinite(x) & np.isfinite(y)
    tree = cKDTree(np.column_stack([x[good_all], y[good_all]]))
    as_neighbour = flux if neighbour_flux is None else neighbour_flux
    fall = np.where(np.isfinite(as_neighbour), as_neighbour, 0.0)[good_all]
    isolated = np.ones(len(idx), bool)
    for k, neigh in enumerate(tree.query_ball_point(np.column_stack([x[idx], y[idx]]), isolation)):
        others = [j for j in neigh if fall[j] > ratio * flux[idx[k]]]
        isolated[k] = len(others) <= 1  # itself
    idx = idx[isolated]
    return idx[np.argsort(-flux[idx], kind="stable")]


def background_gradient(image: np.ndarray, x: np.ndarray, y: np.ndarray, size: int) -> np.ndarray:
    """Background gradient across each star's cut-out relative to the star's flux.

    The background level on each side of the ``size x size`` cut-out is the
    median of the outer two rows (columns) of that side, robust to a neighbour
    there; the gradient ``g`` [electron / pixel^2] is the difference of opposite
    sides over their distance. The star's flux ``F`` is the sum of the central
    5 x 5 pixels above the mean side level. Returns ``(size // 2) |g| / F``: the
    change of the background from the centre to the edge in units of the star's
    flux (NaN where the cut-out leaves the frame or ``F <= 0``).

    A star in the wing of a much brighter one (a saturated giant 30-150 pixels
    away) sits on a background that the ePSF builder's constant local sky cannot
    remove; on the NGC 3201 frames 30 such stars among the 150 of the central
    node's PSF stars made its ePSF peak 40 % low (measured: 0.067 against 0.101
    for the true PSF; 0.110 without them, like the other nodes). Their median is
    0.08, that of the other PSF-star candidates 3e-4 (90 % below 0.005); the
    fitted position of a star moves by about this value in pixels.

    Parameters
    ----------
    image : ndarray
        Sky-subtracted frame [electron].
    x, y : ndarray
        Star positions [pixel].
    size : int
        Cut-out side [pixel].

    Returns
    -------
    ndarray
        ``(size // 2) |g| / F`` per star (dimensionless).
    """
    ny, nx = image.shape
    half = size // 2
    xi = np.rint(np.asarray(x, float)).astype(np.intp)
    yi = np.rint(np.asarray(y, float)).astype(np.intp)
    out = np.full(len(xi), np.nan)
    ok = (xi >= half) & (xi < nx - half) & (yi >= half) & (yi < ny - half)
    off = np.arange(-half, half + 1)
    idx = np.flatnonzero(ok)
    for start in range(0, len(idx), 1024):
        k = idx[start : start + 1024]
        cut = image[(yi[k, None] + off)[:, :, None], (xi[k, None] + off)[:, None, :]]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            left = np.nanmedian(cut[:, :, :2].reshape(len(k), -1), axis=1)
            right = np.nanmedian(cut[:, :, -2:].reshape(len(k), -1), axis=1)
            bottom = np.nanmedian(cut[:, :2, :].reshape(len(k), -1), axis=1)
            top = np.nanmedian(cut[:, -2:, :].reshape(len(k), -1), axis=1)
        level = (left + right + bottom + top) / 4
        core = cut[:, half - 2 : half + 3, half - 2 : half + 3]
        flux = np.nansum(core - level[:, None, None], axis=(1, 2))
        grad = np.hypot(right - left, top - bottom) / (2 * half - 1)
        with np.errstate(all="ignore"):
            out[k] = np.where(flux > 0, half * grad / flux, np.nan)
    return out


def build_epsf(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    options: EPSFOptions,
    bad: np.ndarray | None = None,
    noise_floor: float = 1.0,
    others: np.ndarray | None = None,
) -> np.ndarray:
    """One ePSF from stars at ``(x, y)`` with the builder chosen in ``options``.

    ``options.builder == "fast"`` uses :func:`build_epsf_fast` (ours, vectorised,
    ~100x faster), ``"photutils"`` uses :func:`build_epsf_photutils`.

    Parameters
    ----------
    image : ndarray
        Sky- (and neighbour-) subtracted frame [electron].
    x, y : ndarray
        PSF star positions [pixel].
    options : EPSFOptions
        Builder and its settings.
    bad : ndarray of bool, optional
        Unusable pixels (fast builder only).
    noise_floor : float
        Background variance per pixel [electron^2] (fast builder only).
    others : ndarray, shape (M, 2), optional
        Positions [pixel] of all other stars, masked near each PSF star (fast builder only).

    Returns
    -------
    ndarray
        The oversampled ePSF image.

    Raises
    ------
    InputError
        For an unknown builder.
    """
    if options.builder == "photutils":
        return build_epsf_photutils(image, x, y, options)
    if options.builder != "fast":
        raise InputError(f"unknown ePSF builder '{options.builder}'; expected fast or photutils")
    return build_epsf_fast(image, x, y, options, bad, noise_floor, others)


def _near_neighbour(x, y, rows, cols, others, radius):
    """Stamp pixels closer to another star than to their own and within ``radius`` of it.

    Works on the (PSF star, other star) pairs within reach of a stamp only: PSF
    stars are isolated, so there are few.
    """
    n, sy, sx = len(x), rows.shape[1], cols.shape[1]
    near = np.zeros((n, sy, sx), bool)
    reach = np.sqrt(2) * max(sy, sx) / 2 + radius + 1
    lists = cKDTree(others).query_ball_point(np.column_stack([x, y]), reach)
    star = np.repeat(np.arange(n), [len(hits) for hits in lists])
    if len(star) == 0:
        return near
    other = np.concatenate([np.asarray(hits, np.intp) for hits in lists])
    ox, oy = others[other, 0], others[other, 1]
    keep = np.hypot(ox - x[star], oy - y[star]) >= 0.5  # the star itself
    star, ox, oy = star[keep], ox[keep], oy[keep]
    for start in range(0, len(star), 2048):
        sl = slice(start, start + 2048)
        k = star[sl]
        px, py = cols[k][:, None, :], rows[k][:, :, None]
        d_other = np.hypot(px - ox[sl, None, None], py - oy[sl, None, None])
        d_self = np.hypot(px - x[k, None, None], py - y[k, None, None])
        np.logical_or.at(near, k, (d_other < radius) & (d_other < d_self))
    return near


def _smoothing_kernel(wide: bool = False) -> np.ndarray:
    """Binomial kernel (3 x 3, or 5 x 5 if ``wide``) for the normalised convolution."""
    k = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) if wide else np.array([1.0, 2.0, 1.0])
    k = np.outer(k, k)
    return k / k.sum()


#: Fewer PSF stars than this keep their input positions while the ePSF is built.
_MIN_STARS_REFIT = 12


def _remove_phase_error(start: np.ndarray, fitted: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Remove the pixel-phase-periodic part of the position corrections.

    A pixel-periodic error of the ePSF and a pixel-phase-dependent shift of the
    star positions are degenerate; refitting positions with an imperfect ePSF
    would lock the error in. The corrections ``fitted - start`` are regressed on
    the first two harmonics of the pixel phase of ``fitted`` and that periodic
    part is removed, keeping the random per-star corrections. The mean
    correction is removed too, which anchors the ePSF centre to the input
    positions (the forced catalogue), node by node.
    """
    phase = 2 * np.pi * (fitted - np.rint(fitted))
    design = np.column_stack(
        [np.ones_like(phase), np.sin(phase), np.cos(phase), np.sin(2 * phase), np.cos(2 * phase)]
    )
    delta = fitted - start
    coef, *_ = np.linalg.lstsq(design[good], delta[good], rcond=None)
    return fitted - design @ coef


def build_epsf_fast(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    options: EPSFOptions,
    bad: np.ndarray | None = None,
    noise_floor: float = 1.0,
    others: np.ndarray | None = None,
) -> np.ndarray:
    """One ePSF by iterative residual stacking (Anderson & King 2000 style), vectorised.

    Each iteration bins the normalised residuals ``(data - b) / F - ePSF(dx, dy)``
    of all PSF-star pixels onto the oversampled grid (``b`` the star's local
    background: the median of the stamp border, then the fitted local sky; the
    neighbours' wings and halos otherwise leak into the ePSF as an off-centre
    pedestal that shifts every fitted position), weighted by their inverse
    variance ``F^2 / (F ePSF + b + noise)`` within each bin (an unweighted mean
    lets the noisy wings of faint PSF stars dominate), smooths the bin means with
    a binomial kernel and weights ``sqrt(samples)`` (normalised convolution, so
    sparse bins are filled), adds the mean residual to the ePSF, renormalises and
    recentres it (core centroid at the array centre), then refits the stars'
    positions and fluxes with the batched fitter. Pixels deviating by more than
    4 sigma from the model (cosmic rays, residual neighbours) are rejected.

    Parameters
    ----------
    image : ndarray
        Sky- (and neighbour-) subtracted frame [electron].
    x, y : ndarray
        PSF star positions [pixel].
    options : EPSFOptions
    bad : ndarray of bool, optional
        Unusable pixels.
    noise_floor : float
        Background variance per pixel [electron^2].
    others : ndarray, shape (M, 2), optional
        Positions [pixel] of all other stars: pixels closer to another star than
        to the PSF star, and within ``options.neighbour_mask`` of it, are ignored.

    Returns
    -------
    ndarray, shape (size * oversampling + 1,) * 2
        The ePSF, normalised so that its samples at integer pixel offsets sum to 1.
    """
    x = np.asarray(x, float).copy()
    y = np.asarray(y, float).copy()
    if len(x) < 1:
        raise InputError("no PSF stars available to build an ePSF (relax the PSF-star criteria)")
    os_ = int(options.oversampling)
    half = options.size // 2
    n_os = options.size * os_ + 1
    c = (n_os - 1) / 2.0
    ny, nx = image.shape
    badpix = np.zeros(image.shape, bool) if bad is None else np.asarray(bad, bool)
    badpix = badpix | ~np.isfinite(image)
    off = np.arange(-half, half + 1)
    cx, cy = np.rint(x).astype(int), np.rint(y).astype(int)
    cols = cx[:, None] + off
    rows = cy[:, None] + off
    inside = ((rows >= 0) & (rows < ny))[:, :, None] & ((cols >= 0) & (cols < nx))[:, None, :]
    r_c, c_c = np.clip(rows, 0, ny - 1), np.clip(cols, 0, nx - 1)
    stamps = np.nan_to_num(image[r_c[:, :, None], c_c[:, None, :]])
    valid = inside & ~badpix[r_c[:, :, None], c_c[:, None, :]]
    if others is not None and len(others) > 1:
        valid &= ~_near_neighbour(
            x, y, rows, cols, np.asarray(others, float), options.neighbour_mask
        )
    # local background (neighbours' wings and halos): the median of the stamp's border
    ring = np.maximum(np.abs(off)[:, None], np.abs(off)[None, :]) >= half - 1
    border = np.where(valid & ring, stamps, np.nan)
    with np.errstate(all="ignore"):
        sky = np.nan_to_num(np.nanmedian(border.reshape(len(x), -1), axis=1))
    flux = np.sum(np.where(valid, stamps - sky[:, None, None], 0.0), axis=(1, 2))
    keep = flux > 0
    # the fitted sky planes of the refits (zero slopes with a constant sky)
    slope = np.zeros((len(x), 2))
    plane_x, plane_y = np.meshgrid(off, off)  # column, row offsets from the stamp centre
    x0, y0 = x.copy(), y.copy()
    epsf = np.zeros((n_os, n_os))
    fit_opt = FitOptions(
        radius=min(half, options.fit_radius),
        iterations=4,
        max_shift=1.0,
        min_snr=0.0,
        sky_gradient=options.fit_sky_gradient,
    )
    for it in range(int(options.maxiters)):
        u = (cols[:, None, :] - x[:, None, None]) * os_ + c
        v = (rows[:, :, None] - y[:, None, None]) * os_ + c
        iu, iv = np.rint(u).astype(int), np.rint(v).astype(int)
        on = valid & keep[:, None, None] & (iu >= 0) & (iu < n_os) & (iv >= 0) & (iv < n_os)
        f = np.where(keep, flux, 1.0)[:, None, None]
        back = sky[:, None, None] + slope[:, :1, None] * plane_x + slope[:, 1:, None] * plane_y
        norm = (stamps - back) / f
        if it == 0:
            model = np.zeros_like(norm)
            var = np.abs(stamps) + noise_floor
        else:
            geom = StampGeometry(cx, cy, half)
            model = constant_epsf(epsf, os_).evaluate(x, y, geom, derivatives=False)
            var = np.abs(model * f + back) + noise_floor
            on &= np.abs(norm - model) < 4 * np.sqrt(var) / f
        resid = norm - model
        # inverse-variance weighted mean residual per oversampled bin (bright stars
        # count most); the smoothing then weights the bins by the square root of
        # their number of samples, so that one bright star does not fill the
        # neighbouring pixel phases (better on both test frames than either the
        # plain weighted sums or unweighted means)
        weight = (f**2 / var)[on]
        node = (iv * n_os + iu)[on]
        w_sum = np.bincount(node, weights=weight, minlength=n_os * n_os)
        r_sum = np.bincount(node, weights=resid[on] * weight, minlength=n_os * n_os)
        mean = np.where(w_sum > 0, r_sum / np.where(w_sum > 0, w_sum, 1.0), 0.0)
        counts = np.sqrt(np.bincount(node, minlength=n_os * n_os)).reshape(n_os, n_os)
        sums = mean.reshape(n_os, n_os) * counts
        # the 3 x 3 kernel converges faster on isolated stars but follows the noise
        # of perturbed positions in crowded fields; 5 x 5 measured better there
        kernel = _smoothing_kernel(wide=True)
        s_sum = ndimage.convolve(sums, kernel, mode="constant")
        s_cnt = ndimage.convolve(counts, kernel, mode="constant")
        delta = np.where(s_cnt > 1e-3, s_sum / np.maximum(s_cnt, 1e-3), 0.0)
        epsf = epsf + delta
        if len(x) < _MIN_STARS_REFIT:
            epsf = _recentre(epsf, os_)
        total = epsf.sum() / os_**2
        if not np.isfinite(total) or total <= 0:
            raise InputError("the ePSF built from the PSF stars has no positive flux")
        epsf /= total
        if it < options.maxiters - 1:
            fit = fit_stars(
                image,
                constant_epsf(epsf, os_),
                x,
                y,
                read_noise_var=noise_floor,
                sky0=0.0,
                flux0=flux,
                bad=badpix,
                options=fit_opt,
                return_model=False,
                uncertainties=False,
            )
            good = (fit.flag & 32) == 0
            if good.sum() >= _MIN_STARS_REFIT:
                x = np.where(good, _remove_phase_error(x0, fit.x, good), x)
                y = np.where(good, _remove_phase_error(y0, fit.y, good), y)
            flux = np.where(good, fit.flux, flux)
            sky = np.where(good & np.isfinite(fit.sky), fit.sky, sky)
            if fit.sky_slope is not None:
                slope = np.where((good & np.isfinite(fit.sky))[:, None], fit.sky_slope, slope)
            keep &= good & (flux > 0)
    return epsf


def _recentre(epsf: np.ndarray, oversampling: int, radius: float = 1.5) -> np.ndarray:
    """Shift an ePSF so that the centroid of its core (``radius`` pixels) is at the centre."""
    n = epsf.shape[0]
    c = (n - 1) / 2.0
    yy, xx = np.mgrid[:n, :n] - c
    core = np.hypot(xx, yy) <= radius * oversampling
    w = np.where(core, np.clip(epsf, 0, None), 0.0)
    tot = w.sum()
    if tot <= 0:
        return epsf
    sx, sy = (w * xx).sum() / tot, (w * yy).sum() / tot
    if abs(sx) < 1e-4 and abs(sy) < 1e-4:
        return epsf
    return ndimage.shift(epsf, (-sy, -sx), order=3, mode="constant")


def build_epsf_photutils(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, options: EPSFOptions
) -> np.ndarray:
    """One ePSF from stars at ``(x, y)`` with photutils ``EPSFBuilder`` (cross-check path).

    Parameters
    ----------
    image : ndarray
        Sky-subtracted (and optionally neighbour-subtracted) frame [electron].
    x, y : ndarray
        PSF star positions [pixel].
    options : EPSFOptions

    Returns
    -------
    ndarray, shape (size * oversampling + 1,) * 2
        The ePSF, normalised so that its samples at integer pixel offsets sum to 1.
    """
    if len(x) < 1:
        raise InputError("no PSF stars available to build an ePSF (relax the PSF-star criteria)")
    table = Table({"x": np.asarray(x, float), "y": np.asarray(y, float)})
    n = options.size * options.oversampling + 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stars = extract_stars(NDData(np.asarray(image, float)), table, size=options.size)
        builder = EPSFBuilder(
            oversampling=options.oversampling,
            shape=(n, n),
            maxiters=options.maxiters,
            progress_bar=False,
            recentering_maxiters=10,
        )
        result = builder(stars)
    epsf = getattr(result, "epsf", result[0] if isinstance(result, tuple) else result)
    data = np.asarray(epsf.data, float)
    total = data.sum() / options.oversampling**2
    if not np.isfinite(total) or total <= 0:
        raise InputError("the ePSF built from the PSF stars has no positive flux")
    return data / total


def node_positions(shape: tuple[int, int], grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Centres of a ``grid x grid`` mesh of cells over the frame [pixel].

    Parameters
    ----------
    shape : tuple of int
        Frame shape ``(ny, nx)``.
    grid : int
        Cells per side.

    Returns
    -------
    gx, gy : ndarray
        Cell centres along x and y [pixel] (pixel centres at integers).
    """
    ny, nx = shape
    gx = (np.arange(grid) + 0.5) * nx / grid - 0.5
    gy = (np.arange(grid) + 0.5) * ny / grid - 0.5
    return gx, gy


def build_field_epsf(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    bad: np.ndarray,
    noise_floor: float,
    options: EPSFOptions,
    neighbour_model: np.ndarray | None = None,
    previous: VariableEPSF | None = None,
    model_radius: int = 5,
    half: int | None = None,
    neighbour_flux: np.ndarray | None = None,
    anchor: Callable[[np.ndarray, float, float, int], np.ndarray] | None = None,
    start: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[VariableEPSF, np.ndarray]:
    """Build a (field-variable) ePSF from the frame.

    Parameters
    ----------
    image : ndarray
        Sky-subtracted frame [electron].
    x, y, flux : ndarray
        All known stars [pixel, pixel, electron] (the forced list or detections).
    bad : ndarray of bool
        Saturated / NaN pixels.
    noise_floor : float
        Background variance per pixel (sky + read noise) [electron^2], for the SNR cut.
    options : EPSFOptions
    neighbour_model : ndarray, optional
        Model image of all fitted stars [electron] (``flux`` then holds the
        fitted fluxes); when given, every PSF star's neighbours are subtracted
        and the isolation criterion relaxed.
    previous : VariableEPSF, optional
        The ePSF that made ``neighbour_model`` (needed with it).
    model_radius : int
        Stamp radius [pixel] of the stars in ``neighbour_model``.
    neighbour_flux : ndarray, optional
        Flux estimates of the stars as neighbours in the isolation test
        (:func:`select_psf_stars`; default ``flux``).
    half : {0, 1}, optional
        Build from every other PSF star of each node only (0: the brightest,
        third, ...; 1: the second, fourth, ...): two disjoint halves for the ePSF
        error estimate (:mod:`mavispm.measure.stars.error_model`). The oversampling
        is resolved from the full set.
    anchor : callable, optional
        ``anchor(epsf, x, y, oversampling) -> epsf``: moves each node's ePSF
        (built at field position ``(x, y)`` [pixel]) onto another centre
        convention; observer mode anchors a later epoch to the earlier epoch's
        ePSF (:class:`mavispm.measure.stars.epsf_anchor.EarlierAnchor`). Without
        it each node is centred on the mean start position of its PSF stars.
    start : tuple of ndarray, optional
        ``(x, y)`` [pixel] of all stars from which the builder starts and to whose
        mean each node is anchored (default ``x, y``). The half-set ePSFs of the error
        model start from the stage's start positions, as the first build did, while
        ``x, y`` (the fitted positions) place the neighbour model: the full ePSF's
        centre inherits the start positions' errors through the fitted positions,
        and each half then carries its own share of them.

    Returns
    -------
    psf : VariableEPSF
    psf_stars : ndarray of int
        Indices of the stars used.
    """
    if options.variation not in ("constant", "grid", "polynomial"):
        raise InputError(
            f"unknown PSF variation '{options.variation}'; expected constant, grid or polynomial"
        )
    shape = image.shape
    members, gx, gy, nodes, n_chosen = choose_node_stars(
        image, x, y, flux, bad, noise_floor, options, neighbour_model is not None, neighbour_flux
    )
    used_per_node = min(n_chosen / len(nodes), float(options.stars_per_node))
    oversampling = resolve_oversampling(options.oversampling, used_per_node)
    options = replace(options, oversampling=oversampling)
    if half is not None:
        members = [m[half::2] for m in members]
        if min(len(m) for m in members) < 1:
            raise InputError("too few PSF stars per node to build half-set ePSFs")
    used = np.unique(np.concatenate(members))
    work = np.nan_to_num(np.where(bad, 0.0, image))
    others = np.column_stack([x, y])[np.isfinite(x) & np.isfinite(y)]
    if neighbour_model is not None:
        if previous is None:
            raise InputError("neighbour subtraction needs the ePSF of the neighbour model")
        work = neighbours_subtracted(
            work, neighbour_model, previous, x[used], y[used], flux[used], model_radius
        )
    sx, sy = (x, y) if start is None else (np.asarray(start[0], float), np.asarray(start[1], float))
    epsfs = np.asarray(
        [
            build_epsf(work, sx[near], sy[near], options, bad, noise_floor, others)
            for near in members
        ]
    )
    if options.variation == "polynomial":  # the ePSFs sample the field at their stars
        nodes = np.array([(np.mean(x[near]), np.mean(y[near])) for near in members])
    if anchor is not None:
        epsfs = np.asarray([anchor(e, xn, yn, oversampling) for e, (xn, yn) in zip(epsfs, nodes)])
    if options.variation == "constant":
        return constant_epsf(epsfs[0], oversampling), used
    if options.variation == "grid":
        return gridded_epsf(epsfs, gx, gy, oversampling), used
    return (
        polynomial_epsf(epsfs, nodes[:, 0], nodes[:, 1], options.poly_order, shape, oversampling),
        used,
    )


def neighbours_subtracted(image, neighbour_model, previous, x, y, flux, model_radius):
    """The image less the neighbour model, except the light of the stars ``x, y``.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        The frame [electron].
    neighbour_model : ndarray, shape (ny, nx)
        Model image of all fitted stars [electron].
    previous : VariableEPSF
        The ePSF the model was made with.
    x, y, flux : ndarray
        The stars whose own light stays (PSF stars) [pixel, pixel, electron].
    model_radius : int
        Stamp half-width of the model [pixel].

    Returns
    -------
    ndarray
        ``image - (neighbour_model - own)``, ``own`` the stars' model light.
    """
    own = render_model(image.shape, previous, x, y, flux, model_radius)
    return image - (neighbour_model - own)


#: PSF stars per node (or ``stars_per_node`` if fewer) that the clean selection of a
#: neighbour-subtracted rebuild must supply; below it the relaxed ratio is used (the
#: 2 x 2-node crowded test frame: 16 clean stars per node, 0.27 mas at m < 20 against
#: 0.22 with the relaxed ratio's 25; the 3 x 3-node peer frames, 81-168 clean stars
#: per node: 1.9-1.8 x CRLB at V 16-18 against 2.5-3.6 x).
MIN_CLEAN_PER_NODE = 50


def choose_node_stars(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    bad: np.ndarray,
    noise_floor: float,
    options: EPSFOptions,
    neighbours_subtracted: bool = False,
    neighbour_flux: np.ndarray | None = None,
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray, int]:
    """The PSF stars of every ePSF node (the selection of :func:`build_field_epsf`).

    Parameters
    ----------
    image : ndarray
        Sky-subtracted frame [electron].
    x, y, flux : ndarray
        All known stars [pixel, pixel, electron].
    bad : ndarray of bool
        Unusable pixels.
    noise_floor : float
        Background variance per pixel [electron^2].
    options : EPSFOptions
    neighbours_subtracted : bool
        Whether the neighbours were subtracted (relaxed isolation ratio).
    neighbour_flux : ndarray, optional
        Flux estimates of the stars as neighbours in the isolation test.

    Returns
    -------
    members : list of ndarray of int
        PSF stars of each node (nearest ``stars_per_node``).
    gx, gy : ndarray
        Node columns and rows [pixel].
    nodes : ndarray (K, 2)
        Node positions [pixel], row-major.
    n_chosen : int
        Usable PSF stars before the per-node cap.
    """
    shape = image.shape
    n_nodes = 1 if options.variation == "constant" else options.grid**2
    chosen = psf_star_pool(
        image, x, y, flux, bad, noise_floor, options, neighbours_subtracted, neighbour_flux,
        n_nodes,
    )  # fmt: skip
    if options.variation == "constant":
        gx, gy = np.array([(shape[1] - 1) / 2.0]), np.array([(shape[0] - 1) / 2.0])
    else:
        gx, gy = node_positions(shape, options.grid)
    nodes = np.array([(xi, yi) for yi in gy for xi in gx])
    members = node_psf_stars(x, y, chosen, nodes, options.stars_per_node)
    return members, gx, gy, nodes, len(chosen)


def psf_star_pool(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    bad: np.ndarray,
    noise_floor: float,
    options: EPSFOptions,
    neighbours_subtracted: bool = False,
    neighbour_flux: np.ndarray | None = None,
    n_nodes: int = 1,
) -> np.ndarray:
    """All usable PSF stars, brightest first (the selection of :func:`choose_node_stars`).

    Parameters
    ----------
    image, x, y, flux, bad, noise_floor, options, neighbours_subtracted, neighbour_flux
        As :func:`choose_node_stars`.
    n_nodes : int
        Nodes to fill (with ``neighbours_subtracted``: the relaxed ratio is used where
        the clean selection leaves fewer than ``min(stars_per_node, 50)`` per node).

    Returns
    -------
    ndarray of int
        Indices of the PSF stars.
    """
    shape = image.shape
    # flux SNR of a star in a ~ 10-pixel footprint over the background
    min_flux = options.min_snr**2 / 2 * (1 + np.sqrt(1 + 4 * 10 * noise_floor / options.min_snr**2))
    ratio = options.isolation_ratio
    if neighbours_subtracted:
        ratio = min(options.clean_neighbour_ratio, options.neighbour_ratio)
    chosen = select_psf_stars(
        x, y, flux, shape, bad, options.size, options.isolation, ratio, min_flux, neighbour_flux
    )
    wanted = min(options.stars_per_node, MIN_CLEAN_PER_NODE) * n_nodes
    if neighbours_subtracted and len(chosen) < wanted and ratio < options.neighbour_ratio:
        chosen = select_psf_stars(
            x, y, flux, shape, bad, options.size, options.isolation, options.neighbour_ratio,
            min_flux, neighbour_flux,
        )  # fmt: skip
    if options.max_gradient > 0 and len(chosen):
        flat = background_gradient(image, x[chosen], y[chosen], options.size)
        chosen = chosen[flat <= options.max_gradient]
    if len(chosen) < 3:
        chosen = select_psf_stars(
            x, y, flux, shape, bad, options.size, options.isolation / 2, 1.0, min_flux / 10
        )
    if len(chosen) < 1:
        raise InputError(
            "no usable PSF stars (bright, unsaturated, isolated, inside the frame) found"
        )
    return chosen


def node_psf_stars(
    x: np.ndarray, y: np.ndarray, chosen: np.ndarray, nodes: np.ndarray, per_node: int
) -> list[np.ndarray]:
    """PSF stars of each ePSF node: the ``per_node`` chosen stars nearest to it.

    The nearest stars (not the brightest of the node's cell) describe the PSF
    at the node: on the NGC 3201 frames (3 x 3 grid, 150 per node) the brightest
    of each cell gave 0.22-0.25 mas per-epoch scatter for m < 22, the nearest
    0.15 mas (the PSF varies across a cell).

    Parameters
    ----------
    x, y : ndarray
        Positions of all stars [pixel].
    chosen : ndarray of int
        Indices of the usable PSF stars (:func:`select_psf_stars`).
    nodes : ndarray, shape (K, 2)
        Node positions [pixel].
    per_node : int
        Cap on the PSF stars of one node: an ePSF needs some tens to a few
        hundred stars, not thousands (the build time grows with their number).

    Returns
    -------
    list of ndarray of int
        For each node, indices into ``x`` of its PSF stars.
    """
    tree = cKDTree(np.column_stack([x[chosen], y[chosen]]))
    k = min(int(per_node), len(chosen))
    return [chosen[np.atleast_1d(tree.query(node, k=k)[1])] for node in nodes]


#: PSF stars used per node (after the ``stars_per_node`` cap) from which an ePSF is
#: oversampled 4 times in ``"auto"`` mode: x4 has 16 pixel phases to fill where x2 has 4,
#: so it needs four times the stars for the same samples per phase.
AUTO_OVERSAMPLING_X4 = 600


def resolve_oversampling(setting: int | str, stars_per_node: float) -> int:
    """The ePSF oversampling factor: the setting, or chosen from the PSF-star count.

    An ``oversampling``-times oversampled ePSF has ``oversampling^2`` pixel
    phases per detector pixel to fill with PSF-star samples; with too few stars
    the phases are noisy and the bright stars' astrometry is limited by the ePSF
    (docs/measure.md). ``"auto"``: 4 with at least :data:`AUTO_OVERSAMPLING_X4`
    PSF stars *used* per node, else 2. The rule counted the usable stars before
    the ``stars_per_node`` cap (x4 from 200): the full NGC 3201 frames (3,500
    stars, 150 used per node of 3 x 3) then got x4, and their bright stars (V < 22)
    scattered 30-50 uas per epoch; with x2, 8-14 uas (baseline scene) and 15-29
    (tip-tilt scene), at the Cramér-Rao bound fainter than V = 22.

    Parameters
    ----------
    setting : int or "auto"
    stars_per_node : float
        PSF stars used per ePSF node.
    """
    if setting == "auto":
        return 4 if stars_per_node >= AUTO_OVERSAMPLING_X4 else 2
    return int(setting)
