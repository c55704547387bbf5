"""The light of stars beyond their fitting stamps: a radial profile per unit flux.

The batched fitter models each star on a small stamp (11 x 11 px by default). An AO
PSF keeps much of its light outside: on the MAVIS frames 15 % of the ePSF's flux lies
between 5 and 12 px and a seeing halo reaches ~60 px; a V = 17 star's light there is
hundreds of times a V = 24 neighbour's pixel noise. A star's sky plane absorbs the
smooth part of it but not its curvature near a bright neighbour, and faint stars in
the halos of bright ones end with negative fluxes or drift by pixels. The fitter
therefore adds every bright star's light outside its own stamp to the model its
neighbours see, as ``flux * profile(r)``: the profile is measured on the frame around
its brightest stars (:func:`halo_profile`) at every radius outside the stamp. The
ePSF's own azimuthal mean is not used there: beyond the
fitting stamp the ePSF is barely constrained by the fits (on the 1e5-star MAVIS frame
10-25 % below the rendered light at 8-12 px), and splicing it to the measured profile
at the ePSF's footprint left a step that biased faint neighbours' fluxes.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "RING_REFERENCE",
    "grouped_median",
    "halo_excess",
    "halo_profile",
    "halo_tail",
    "deposit_stacked",
    "deposit_tail",
    "tail_ramp",
    "ring_corrections",
    "core_pixels",
    "residual_maps",
    "stacked_residual",
]

#: Radius [pix] where a star's halo is compared with the sky noise to choose the stars
#: that get their own ring corrections (``FitOptions.halo_rings``).
RING_REFERENCE = 20.0
#: Outer radius [pix] of the ring corrections, the rings of their zero point (from
#: ``RING_BACKGROUND`` out) and the raised-cosine taper that fades them out
#: (``RING_TAPER``); chosen on the 1e5-star MAVIS frame, where the measured rings follow
#: each star's own misfit (correlation 0.78-0.86) at 10-16 px but not beyond 25 px
#: (docs/measure-scale.md, eleventh pass).
RING_OUTER = 34.0
RING_BACKGROUND = 28.0
RING_TAPER = (22.0, 30.0)
#: :func:`residual_maps`: width [pix] of the raised-cosine fade at the map's edge.
MAP_TAPER = 10.0


def halo_profile(
    image: np.ndarray,
    bad: np.ndarray | None,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    radii: np.ndarray,
    n_stars: int = 150,
    n_median: int = 40,
    width: float = 10.0,
    min_stars: int = 5,
    significance: float = 3.0,
    eligible: np.ndarray | None = None,
) -> np.ndarray:
    """Light per unit flux around the brightest stars [1/pixel], measured on the frame.

    For each of the ``n_stars`` brightest of the given (``eligible``) stars whose
    surroundings out to ``max(radii) + width`` lie in the frame and hold no brighter
    given star (whose light there would not scale with this star's flux, and in the
    regression over stars of unequal flux pulls the slope down: a synthetic frame
    with 16 bright stars and fainter ones in their halos gave a profile 25-35 %
    low; ``tests/test_measure_halo.py``): the median of the image in 1-px
    annuli centred on ``radii``, less the median in the annulus ``[max(radii),
    max(radii) + width)`` (the local background: the profile is zero there). The
    profile is the median over the ``n_median`` brightest of that excess divided by
    the star's flux, where the excess grows significantly with the flux over all
    ``n_stars`` (:func:`_flux_scaled`; light that does not grow with a star's flux:
    its neighbours', a brighter star's halo, a background gradient), and at most
    that regression's slope; else zero. Under-modelling leaves the neighbours' sky
    planes some light; over-modelling would push faint fluxes negative.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        The frame [electron].
    bad : ndarray of bool or None
        Pixels to ignore.
    x, y, flux : ndarray, shape (N,)
        Stars: positions [pixel] and fitted fluxes [electron].
    radii : ndarray
        Annulus centres [pixel], increasing.
    n_stars : int
        Stars used in the flux regression.
    n_median : int
        The brightest of them, whose median ratio is the profile's value.
    width : float
        Width of the background annulus [pixel].
    min_stars : int
        Fewer usable stars give a zero profile.
    significance : float
        Threshold of a kept value [standard errors].
    eligible : ndarray of bool, shape (N,), optional
        Stars whose surroundings may be measured (e.g. not saturated); the others
        only exclude fainter stars near them. Default: all.

    Returns
    -------
    ndarray
        The profile at ``radii`` (zeros when no star qualifies).
    """
    ny, nx = image.shape
    outer = float(np.max(radii)) + width
    margin = int(np.ceil(outer))
    known = np.isfinite(x) & np.isfinite(y) & np.isfinite(flux) & (flux > 0)
    ok = known & (x >= margin) & (x < nx - 1 - margin) & (y >= margin) & (y < ny - 1 - margin)
    if eligible is not None:
        ok &= np.asarray(eligible, bool)
    cand = np.flatnonzero(ok)
    cand = cand[np.argsort(-flux[cand])][: 3 * n_stars]
    if len(cand):  # no brighter star within the outer radius
        lit = np.flatnonzero(known & (flux > flux[cand[-1]]))
        near = cKDTree(np.column_stack([x[lit], y[lit]])).query_ball_point(
            np.column_stack([x[cand], y[cand]]), outer
        )
        alone = np.array([not np.any(flux[lit[j]] > flux[k]) for k, j in zip(cand, near)])
        cand = cand[alone]
    cand = cand[:n_stars]
    if len(cand) < min_stars:
        return np.zeros(len(radii))
    rows = halo_excess(image, bad, x[cand], y[cand], radii, width) / flux[cand][:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nan_to_num(np.nanmedian(rows[:n_median], axis=0))
    slope = _flux_scaled(rows * flux[cand][:, None], flux[cand], min_stars, significance)
    return np.where(slope > 0, np.maximum(np.minimum(median, slope), 0.0), 0.0)


#: Logarithmic slope of the seeing halo past the AO control radius: the light there is the
#: uncorrected turbulence's, whose phase spectrum (Kolmogorov, von Karman well inside the
#: outer scale) falls as ``f^(-11/3)``, and so does the halo at angles ``lambda f``
#: (the MAVISIM paper, sections 2-3). On the 1e5-star MAVIS frame the light at 60-100 px,
#: measured against the 100-110 px annulus, follows ``r^(-11/3)`` fitted at 48-60 px
#: (6.9 / 1.5e-6 predicted at 70 / 90 px, 7.3 / 1.4e-6 measured; ``r^-3``: 8.8 / 2.2e-6;
#: docs/measure-scale.md, seventeenth pass).
TAIL_SLOPE = 11.0 / 3.0
#: Radii [pix] at the profile's end to which the tail's amplitude is fitted.
TAIL_FIT = 12.0


def halo_tail(profile, r_in, outer, width=10.0):
    """The halo continued past the profile's edge as a seeing halo, ``A r^(-11/3)``.

    :func:`halo_profile` is zero at its last radius by construction (its background is
    the annulus ``[R, R + width)`` just beyond its last radius ``R``), while the halo goes
    on falling past the AO control radius (on the 1e5-star MAVIS frame by ~1e-6 of the
    star's flux per px at 60-70 px). The profile's last ``TAIL_FIT`` px are fitted (least
    squares, amplitude only) by ``A (r^-s - rho^-s)``, ``s = TAIL_SLOPE`` and ``rho`` the
    radius that splits that annulus' area in two (its median for a falling halo); then
    the profile is raised by the light it was measured against, ``A rho^-s``, and
    continued by ``A r^-s`` out to ``outer``, faded to zero by a raised cosine over the
    tail's outer half (no step at its edge); across the last ``TAIL_SEAM`` px of the
    profile the raised profile blends into the power law (:func:`tail_ramp`), so the
    two deposits of :func:`deposit_tail` join smoothly.

    Parameters
    ----------
    profile : ndarray (L,)
        The frame's profile at ``r_in + 0 .. L - 1`` [1/pixel].
    r_in : float
        Its first radius [pixel].
    outer : float
        Outer radius of the tail [pixel].
    width : float
        Width of the profile's background annulus [pixel].

    Returns
    -------
    ndarray
        The profile at ``r_in + 0, 1, ...`` below ``outer``; the given one where the
        tail does not reach past it or its fitted amplitude is not positive.
    """
    profile = np.asarray(profile, float)
    n = len(profile)
    radii = np.arange(r_in, outer, 1.0)
    if len(radii) <= n or n < 2:
        return profile
    last = radii[n - 1]
    edge = last + 0.5
    rho = np.sqrt(0.5 * (edge**2 + (edge + width) ** 2))
    fit = radii[:n] > last - TAIL_FIT
    g = radii[:n][fit] ** -TAIL_SLOPE - rho**-TAIL_SLOPE
    amp = float(np.sum(g * profile[fit]) / np.sum(g * g))
    if not amp > 0:
        return profile
    law = amp * radii**-TAIL_SLOPE
    mid = 0.5 * (last + outer)
    fade = 0.5 + 0.5 * np.cos(np.pi * np.clip((radii - mid) / (outer - mid), 0.0, 1.0))
    w = tail_ramp(radii, last)
    raised = np.concatenate(
        [np.where(profile > 0, profile + amp * rho**-TAIL_SLOPE, 0.0), np.zeros(len(radii) - n)]
    )
    return ((1 - w) * raised + w * law) * fade


#: Width [pix] of the raised-cosine seam between a star's own halo deposit and the tail's
#: FFT deposit (:func:`tail_ramp`): the flux image's bilinear split blurs a sharp seam
#: (3.7 % rms error on a test frame), not a smooth one.
TAIL_SEAM = 10.0


def tail_ramp(r, start):
    """The tail's share of the halo at radius ``r`` [pix]: 0 below ``start - TAIL_SEAM``,
    1 from ``start`` on, a raised cosine between; the star's own deposit takes the rest."""
    t = np.clip((np.asarray(r, float) - (start - TAIL_SEAM)) / TAIL_SEAM, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * t)


#: Rows of the frame per FFT of :func:`deposit_tail`: one FFT of the whole frame
#: (``oaconvolve``) took the 1e5-star stage's peak memory from 1.33 to 2.63 GB; strips of
#: 512 / 1024 / 2048 rows took 2.6 / 1.4 / 1.7 s CPU on a 4000 x 4000 frame with a 150 px
#: tail (each strip is padded by the tail's reach).
TAIL_STRIP = 1024


def deposit_tail(pixels, shape, x, y, flux, profile, r_in, outs):
    """Add every star's ``flux * profile(r)`` (linear in ``r``, samples 1 px apart from
    ``r_in``, zero outside ``[r_in, r_in + len(profile) - 1]``) to the pixels ``pixels``,
    at once: a flux image (each flux split bilinearly over the 4 pixels around its star)
    convolved by FFT with the round kernel, in strips of ``TAIL_STRIP`` rows (cost nearly
    independent of the radius; the split blurs the kernel by a pixel, so it should be
    smooth: :func:`tail_ramp`); into each array of ``outs`` (shape (P,), in place)."""
    from scipy.signal import fftconvolve

    ny, nx = shape
    reach = int(np.floor(r_in + len(profile) - 1))
    if len(x) == 0 or len(profile) < 2 or len(pixels) == 0:
        return
    off = np.arange(-reach, reach + 1)
    r = np.hypot(off[None, :], off[:, None])
    kernel = np.interp(r, r_in + np.arange(len(profile)), profile, left=0.0, right=0.0)
    x, y, flux = np.asarray(x, float), np.asarray(y, float), np.asarray(flux, float)
    ix, iy = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - ix, y - iy
    # the four corners of every star: row, column, share of its flux
    rows = np.concatenate([iy, iy, iy + 1, iy + 1])
    cols = np.concatenate([ix, ix + 1, ix, ix + 1])
    share = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]) * np.tile(
        flux, 4
    )
    keep = (cols >= -reach) & (cols < nx + reach) & (share != 0)
    rows, cols, share = rows[keep], cols[keep], share[keep]
    first = np.searchsorted(pixels, np.arange(0, ny + TAIL_STRIP, TAIL_STRIP) * nx)
    for s, a in enumerate(range(0, ny, TAIL_STRIP)):
        lo, hi = first[s], first[s + 1]
        if lo == hi:
            continue
        b = min(a + TAIL_STRIP, ny)
        near = (rows >= a - reach) & (rows < b + reach)
        grid = np.zeros((b - a + 2 * reach, nx + 2 * reach))
        np.add.at(grid, (rows[near] - a + reach, cols[near] + reach), share[near])
        light = fftconvolve(grid, kernel, mode="valid")  # (b - a, nx)
        pix = pixels[lo:hi]
        add = light[pix // nx - a, pix % nx]
        for out in outs:
            out[lo:hi] += add


def halo_excess(image, bad, x, y, radii, width=10.0):
    """Per star (rows) the image median in the 1-px annuli ``radii`` less the median in
    ``[max(radii), max(radii) + width)`` [electron/pixel]; pixels off the frame or
    ``bad`` ignored (NaN where an annulus has none)."""
    ny, nx = image.shape
    outer = float(np.max(radii)) + width
    margin = int(np.ceil(outer))
    rings = _ring_medians if _unit_spaced(radii) else _ring_medians_direct
    off = np.arange(-margin, margin + 1)
    rows = np.full((len(x), len(radii)), np.nan)
    for k in range(len(x)):
        cx, cy = int(round(x[k])), int(round(y[k]))
        y0, y1 = max(cy - margin, 0), min(cy + margin + 1, ny)
        x0, x1 = max(cx - margin, 0), min(cx + margin + 1, nx)
        if y0 >= y1 or x0 >= x1:
            continue
        cut = np.full((2 * margin + 1,) * 2, np.nan)
        part = np.asarray(image[y0:y1, x0:x1], float)
        if bad is not None:
            part = np.where(bad[y0:y1, x0:x1], np.nan, part)
        cut[y0 - cy + margin : y1 - cy + margin, x0 - cx + margin : x1 - cx + margin] = part
        r = np.hypot(off[None, :] + cx - x[k], off[:, None] + cy - y[k])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            back, ring = rings(cut, r, radii, outer - width, outer)
        rows[k] = ring - back
    return rows


def _unit_spaced(radii: np.ndarray) -> bool:
    """Whether the annulus centres are consecutive 1-px steps from >= 0.5 px."""
    return radii.size > 0 and radii[0] >= 0.5 and np.allclose(np.diff(radii), 1.0)


def _ring_medians_direct(cut, r, radii, back_lo, back_hi):
    """Median of ``cut`` (NaN ignored) in the background annulus ``[back_lo, back_hi)`` and
    in each 1-px annulus ``|r - rc| < 0.5``; one median per annulus (the reference of
    :func:`_ring_medians`)."""
    rings = np.array([np.nanmedian(cut[np.abs(r - rc) < 0.5]) for rc in radii])
    return _background_median(cut, r, back_lo, back_hi), rings


def _background_median(cut, r, back_lo, back_hi):
    """Median of ``cut`` (NaN ignored) in the annulus ``back_lo <= r < back_hi``."""
    return np.nanmedian(cut[(r >= back_lo) & (r < back_hi)])


def _ring_medians(cut, r, radii, back_lo, back_hi):
    """:func:`_ring_medians_direct` for consecutive 1-px annuli, every annulus's median
    from one sort of the window (by value, then stably by annulus); NaN where an annulus
    has no finite pixel. A pixel exactly on an annulus edge (``|r - rc| = 0.5``, measure
    zero for a star off the pixel grid) goes to the outer annulus instead of neither."""
    n = radii.size
    ring = np.floor(r - (radii[0] - 0.5)).astype(np.int64)
    keep = np.isfinite(cut) & (ring >= 0) & (ring < n)
    med = grouped_median(ring[keep], cut[keep], n)
    return _background_median(cut, r, back_lo, back_hi), med


def grouped_median(label: np.ndarray, value: np.ndarray, n: int, min_count: int = 1) -> np.ndarray:
    """Median of ``value`` in each group ``label = 0 .. n - 1``, from one sort.

    Parameters
    ----------
    label : ndarray of int
        Group of each value, in ``[0, n)``.
    value : ndarray of float
        Finite values.
    n : int
        Number of groups.
    min_count : int
        Groups with fewer values get NaN.

    Returns
    -------
    ndarray (n,)
        The groups' medians (the mean of the two middle values for an even count).
    """
    order = np.lexsort((value, label))  # by group, then by value
    value = value[order]
    counts = np.bincount(label, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    med = np.full(n, np.nan)
    some = counts >= max(min_count, 1)
    lo = starts[some] + (counts[some] - 1) // 2
    hi = starts[some] + counts[some] // 2
    med[some] = 0.5 * (value[lo] + value[hi])
    return med


def _flux_scaled(d: np.ndarray, f: np.ndarray, min_stars: int, significance: float) -> np.ndarray:
    """Per annulus (column of ``d``) the slope ``h`` of ``d = a + h f`` over the stars
    (least squares, one 3-sigma clip), where at least ``significance`` standard errors
    above zero, else 0: light around a star that does not grow with its flux (its
    neighbours', a brighter star's halo, a background gradient) goes into ``a``."""
    out = np.zeros(d.shape[1])
    for i in range(d.shape[1]):
        use = np.isfinite(d[:, i])
        coef, cov = np.zeros(2), np.full((2, 2), np.inf)
        for _ in range(2):
            if use.sum() < max(min_stars, 3):
                break
            design = np.column_stack([np.ones(use.sum()), f[use]])
            coef, *_ = np.linalg.lstsq(design, d[use, i], rcond=None)
            resid = d[:, i] - (coef[0] + coef[1] * f)
            dof = max(use.sum() - 2, 1)
            sigma = np.sqrt(np.sum(resid[use] ** 2) / dof)
            cov = sigma**2 * np.linalg.pinv(design.T @ design)
            use_next = use & (np.abs(resid) <= 3 * sigma)
            if use_next.sum() == use.sum():
                break
            use = use_next
        if use.sum() >= max(min_stars, 3) and coef[1] >= significance * np.sqrt(cov[1, 1]):
            out[i] = coef[1]
    return out


def ring_corrections(pixels, shape, values, model, bad, x, y, cx, cy, half, radii):
    """Each given star's own radial misfit: the residual's median in 1-px rings.

    For every star: the median of ``values - model`` over the touched pixels in 1-px
    annuli from the profile's first radius to ``RING_OUTER``, outside the star's own
    stamp, less its median from ``RING_BACKGROUND`` out, faded out by a raised cosine
    over ``RING_TAPER``; zero beyond. Each star's rings are measured on the same
    residual (none sees another's correction).

    Parameters
    ----------
    pixels : ndarray of int (P,)
        Sorted flat indices (``row * nx + column``) of the touched pixels.
    shape : tuple (ny, nx)
        Frame shape [pix].
    values, model : ndarray (P,)
        Image and current model on those pixels [e-].
    bad : ndarray of bool (P,)
        Pixels to leave out.
    x, y : ndarray (N,)
        Star positions [pix].
    cx, cy : ndarray of int (N,)
        Stamp centres [pix].
    half : int
        Stamp half-size [pix]: pixels inside the stamp are not used.
    radii : ndarray
        Radii of the halo profile [pix], 1 px apart.

    Returns
    -------
    list of (ndarray, ndarray)
        Per star with enough rings: the positions in ``pixels`` and the light to add
        there [e-].
    """
    ny, nx = shape
    rr = radii[radii < RING_OUTER]
    nr = len(rr)
    if nr == 0:
        return []
    reach = int(np.ceil(rr[-1] + 0.5))
    lo, hi = RING_TAPER
    taper = 0.5 - 0.5 * np.cos(np.pi * np.clip((hi - rr) / (hi - lo), 0.0, 1.0))
    outer_rings = rr >= RING_BACKGROUND
    adds = []
    for k in range(len(x)):
        cxk, cyk = int(cx[k]), int(cy[k])
        at_box = _box_pixels(pixels, nx, ny, cxk, cyk, reach)
        pix = pixels[at_box]
        px, py = pix % nx, pix // nx
        d = np.hypot(px - x[k], py - y[k])
        ring = np.floor(d - (rr[0] - 0.5)).astype(np.int64)
        keep = (ring >= 0) & (ring < nr) & ((np.abs(px - cxk) > half) | (np.abs(py - cyk) > half))
        sel = np.flatnonzero(keep)
        sel_pix = at_box[sel]
        v = values[sel_pix] - model[sel_pix]
        ok = np.isfinite(v) & ~bad[sel_pix]
        med = grouped_median(ring[sel][ok], v[ok], nr, min_count=5)
        if not np.any(np.isfinite(med[outer_rings])):
            continue
        fix = np.nan_to_num(med - np.nanmedian(med[outer_rings])) * taper
        adds.append((sel_pix, np.interp(d[sel], rr, fix, left=0.0, right=0.0)))
    return adds


def core_pixels(pixels, shape, cx, cy, core):
    """Which touched pixels lie in the ``(2 core + 1)^2`` px box around any star.

    Parameters
    ----------
    pixels : ndarray of int
        Sorted flat indices of the touched pixels.
    shape : tuple of int
        Frame shape ``(ny, nx)``.
    cx, cy : ndarray of int
        The stars' stamp-centre pixels.
    core : int
        Half-width of each box [pix].

    Returns
    -------
    ndarray of bool, shape like ``pixels``
    """
    ny, nx = shape
    offsets = np.arange(-core, core + 1)
    cxs = np.clip(np.asarray(cx)[:, None, None] + offsets[None, None, :], 0, nx - 1)
    cys = np.clip(np.asarray(cy)[:, None, None] + offsets[None, :, None], 0, ny - 1)
    keys = (cys * nx + cxs).ravel().astype(pixels.dtype)
    at = np.searchsorted(pixels, keys)
    hit = at < len(pixels)
    hit[hit] = pixels[at[hit]] == keys[hit]
    inside = np.zeros(len(pixels), dtype=bool)
    inside[at[hit]] = True
    return inside


def residual_maps(pixels, shape, values, model, bad, cx, cy, half, reach, block, arc=0.0):
    """Each given star's own 2-D misfit: block medians of its residual, interpolated.

    For every star: the residual (``values - model``) on the touched pixels within
    ``reach`` of its stamp centre (Euclidean), outside its own stamp, less its median
    beyond ``reach / 2`` (the sky and the crowd's diffuse light); its
    medians in ``block`` x ``block`` px blocks centred on the stamp centre (blocks with
    fewer than half their pixels usable count as zero), interpolated bilinearly between
    the blocks' centres, faded out by a raised cosine over the last ``MAP_TAPER`` px of
    ``reach``. The block median keeps light structured on the scale of a few blocks
    (the fitting stamp's) and drops a faint star's own residual (its core is a few px
    across). Each star's map is measured on the same residual (none sees another's).

    Parameters
    ----------
    pixels, shape, values, model, bad, cx, cy, half
        As :func:`stacked_residual`.
    reach : int
        Radius of the maps [pix].
    block : int
        Side of the median blocks [pix], odd.
    arc : float
        If > 0: polar bins instead of square blocks: the residual's median in 1-px
        annuli (its radial misfit) plus, of the rest, the median in bins ``block`` px
        long in radius and ``arc`` px wide in azimuth (light structured radially, as an
        AO PSF's chromatic speckle spokes, kept; a faint star, a few px across, dropped);
        no interpolation.

    Returns
    -------
    list of (ndarray, ndarray)
        Per star: the positions in ``pixels`` and the light to add there [e-].
    """
    from scipy.ndimage import map_coordinates

    ny, nx = shape
    nb = 2 * ((reach + block // 2) // block) + 1  # blocks per side, one centred
    cb = nb // 2
    adds = []
    for k in range(len(cx)):
        cxk, cyk = int(cx[k]), int(cy[k])
        at = _box_pixels(pixels, nx, ny, cxk, cyk, reach)
        pix = pixels[at]
        ox, oy = pix % nx - cxk, pix // nx - cyk
        d = np.hypot(ox, oy)
        v = values[at] - model[at]
        outside = ((np.abs(ox) > half) | (np.abs(oy) > half)) & (d <= reach)
        keep = outside & np.isfinite(v) & ~bad[at]
        back = keep & (d > 0.5 * reach)
        if np.count_nonzero(back) < 20:
            continue
        v = v - np.median(v[back])
        if arc > 0:
            adds.append((at[outside], _polar_map(ox, oy, d, v, keep, outside, reach, block, arc)))
            continue
        bx = np.floor((ox + block // 2) / block).astype(np.int64) + cb
        by = np.floor((oy + block // 2) / block).astype(np.int64) + cb
        med = grouped_median(by[keep] * nb + bx[keep], v[keep], nb * nb, (block * block + 1) // 2)
        grid = np.nan_to_num(med.reshape(nb, nb))
        where = [oy[outside] / block + cb, ox[outside] / block + cb]  # block centres: integers
        light = map_coordinates(grid, where, order=1, mode="nearest")
        fade = np.clip((reach - d[outside]) / MAP_TAPER, 0.0, 1.0)
        adds.append((at[outside], light * (0.5 - 0.5 * np.cos(np.pi * fade))))
    return adds


def _polar_map(ox, oy, d, v, keep, outside, reach, block, arc):
    """:func:`residual_maps` on polar bins: the light to add on the pixels ``outside``."""
    nring = int(reach) + 2
    d = np.minimum(d, reach + 1.0)  # the box's corners (outside the map) kept in range
    ring = np.floor(d).astype(np.int64)
    radial = grouped_median(ring[keep], v[keep], nring, min_count=5)
    radial = np.nan_to_num(radial)
    rest = v - radial[ring]
    rbin = np.floor(d / block).astype(np.int64)
    nr = int(reach // block) + 2
    nth = np.maximum(np.round(2 * np.pi * (rbin + 0.5) * block / arc), 1).astype(np.int64)
    theta = (np.arctan2(oy, ox) + np.pi) / (2 * np.pi)
    tbin = np.minimum((theta * nth).astype(np.int64), nth - 1)
    width = int(nth.max()) if len(nth) else 1
    label = rbin * width + tbin
    med = np.nan_to_num(grouped_median(label[keep], rest[keep], nr * width, min_count=3))
    fade = np.clip((reach - d[outside]) / MAP_TAPER, 0.0, 1.0)
    light = radial[ring[outside]] + med[label[outside]]
    return light * (0.5 - 0.5 * np.cos(np.pi * fade))


def _box_pixels(pixels, nx, ny, cxk, cyk, reach):
    """Positions in ``pixels`` (sorted flat indices) of the touched pixels of the box of
    half-width ``reach`` around pixel ``(cxk, cyk)``: one range per frame row."""
    band = np.arange(max(cyk - reach, 0), min(cyk + reach + 1, ny)) * nx
    # keys of the pixels' own dtype: int64 keys into int32 pixels cast the whole
    # array on every call (15 ms at 1e5 stars)
    first = np.searchsorted(pixels, (band + max(cxk - reach, 0)).astype(pixels.dtype))
    ends = (band + min(cxk + reach + 1, nx)).astype(pixels.dtype)
    lens = np.searchsorted(pixels, ends) - first
    return np.repeat(first - np.cumsum(lens) + lens, lens) + np.arange(lens.sum())


def stacked_residual(pixels, shape, values, model, bad, cx, cy, flux, half, reach):
    """The bright stars' common non-round misfit: a 2-D median of their residuals.

    For every given star: the residual (``values - model``) on the touched pixels within
    ``reach`` of its stamp centre (in x and y), outside its own stamp, less the star's
    own median in each 1-px annulus (its radial misfit, which :func:`ring_corrections`
    takes star by star), over its flux. Per pixel offset from the stamp centre, the
    median over the stars (where at least 5 saw the pixel); less that map's own mean in
    each 1-px annulus, so that only the non-round part is kept; zero inside the stamp
    and beyond ``reach``. Light that a round halo model and the prior's shape maps both
    miss, the same around every bright star (PSF structure), survives the median; each
    star's own structure and its neighbours' light do not (docs/measure-scale.md,
    sixteenth pass: on the 1e5-star MAVIS frame two random halves of the V < 15 stars
    give maps that correlate 0.94-0.97 at 5-11 px and 0.85-0.91 at 20-45 px, 0.42 at
    45-60 px).

    Parameters
    ----------
    pixels : ndarray of int (P,)
        Sorted flat indices (``row * nx + column``) of the touched pixels.
    shape : tuple (ny, nx)
        Frame shape [pix].
    values, model : ndarray (P,)
        Image and current model on those pixels [e-].
    bad : ndarray of bool (P,)
        Pixels to leave out.
    cx, cy : ndarray of int (N,)
        The stars' stamp centres [pix].
    flux : ndarray (N,)
        Their fluxes [e-], positive.
    half : int
        Stamp half-size [pix].
    reach : int
        Radius of the map [pix].

    Returns
    -------
    ndarray, shape (2 reach + 1, 2 reach + 1)
        Light per unit flux by offset (row, column) from the stamp centre [1/pix].
    """
    ny, nx = shape
    side = 2 * reach + 1
    off = np.arange(-reach, reach + 1)
    dist = np.hypot(off[None, :], off[:, None])
    ring_of = np.rint(dist).astype(np.int64)
    nring = int(ring_of.max()) + 1
    labels, vals = [], []
    for k in range(len(cx)):
        cxk, cyk = int(cx[k]), int(cy[k])
        at = _box_pixels(pixels, nx, ny, cxk, cyk, reach)
        pix = pixels[at]
        ox, oy = pix % nx - cxk, pix // nx - cyk
        v = values[at] - model[at]
        keep = np.isfinite(v) & ~bad[at] & ((np.abs(ox) > half) | (np.abs(oy) > half))
        label = (oy[keep] + reach) * side + (ox[keep] + reach)
        ring = ring_of.ravel()[label]
        v = v[keep]
        v = (v - grouped_median(ring, v, nring)[ring]) / flux[k]
        labels.append(label)
        vals.append(v)
    if not labels:
        return np.zeros((side, side))
    stack = grouped_median(np.concatenate(labels), np.concatenate(vals), side * side, min_count=5)
    stack = stack.reshape(side, side)
    inside = (np.abs(off)[None, :] <= half) & (np.abs(off)[:, None] <= half)
    use = np.isfinite(stack) & ~inside & (dist <= reach)
    mean = np.bincount(ring_of[use], stack[use], nring) / np.maximum(
        np.bincount(ring_of[use], minlength=nring), 1
    )
    return np.where(use, stack - mean[ring_of], 0.0)


def deposit_stacked(pixels, shape, cx, cy, flux, stack, outs):
    """Add ``flux * stack`` (a :func:`stacked_residual` map, centred on each star's stamp
    centre ``(cx, cy)``) to the touched pixels ``pixels``, into each array of ``outs``
    (shape (P,), in place)."""
    ny, nx = shape
    reach = (stack.shape[0] - 1) // 2
    side = stack.shape[0]
    flat = stack.ravel()
    for k in range(len(cx)):
        cxk, cyk = int(cx[k]), int(cy[k])
        at = _box_pixels(pixels, nx, ny, cxk, cyk, reach)
        pix = pixels[at]
        light = flux[k] * flat[(pix // nx - cyk + reach) * side + (pix % nx - cxk + reach)]
        for out in outs:
            out[at] += light
