"""Batched forced-position PSF fitting of all stars at once (the default engine).

Every star is fitted on a small square stamp for ``(x, y, flux, local sky)``
with the field-variable ePSF. Neighbours are subtracted from the *current*
model: a model image (sum of all stars' stamps) is kept up to date, and each
star sees its data minus everyone else's model. Stars whose stamps overlap are
put in different *colours* (greedy graph colouring) and the colours are
updated in alternating passes (block Gauss-Seidel), so close pairs do not
oscillate. Within a colour all stars take one damped Gauss-Newton
(Levenberg-Marquardt) step together, vectorised with numpy in chunks.

Optionally (``joint_radius``) stars closer than a few pixels step jointly
(:mod:`~mavispm.measure.stars.joint_step`). With ``wing_threshold`` the light of bright
stars outside their stamps (a radial profile, :mod:`~mavispm.measure.stars.halo`) is
in the model their neighbours see, fixed after the first (fixed-position) pass.

Weights come from the model, ``1 / (sky + model + RN^2)``, never from the noisy
data (data weights bias faint fluxes low). Saturated, NaN and off-frame pixels
get zero weight; the star is kept and flagged.

Flag bits (see ``docs/formats.md``): 1 not converged, 2 saturated pixels masked,
4 near edge, 8 crowded, 32 failed / zero flux.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from mavispm.core.errors import InputError
from mavispm.core.frame import on_detector
from mavispm.measure.stars.chunk_pool import ChunkPool, resolve_threads
from mavispm.measure.stars.crlb import jacobian, safe_inverse, sky_plane_basis
from mavispm.measure.stars.halo import (
    RING_REFERENCE,
    core_pixels,
    deposit_stacked,
    deposit_tail,
    halo_profile,
    halo_tail,
    residual_maps,
    stacked_residual,
    tail_ramp,
)
from mavispm.measure.stars.halo import ring_corrections as halo_ring_corrections
from mavispm.measure.stars.halo_shape import HaloShape, deposit_shaped
from mavispm.measure.stars.joint_step import coupled_groups, cross_blocks, solve_groups
from mavispm.measure.stars.odd_residual import odd_chi2
from mavispm.measure.stars.stamp_kernel import deposit_radial
from mavispm.measure.stars.stamp_kernel import normal_equations as fused_normal_equations
from mavispm.measure.stars.variable_psf import StampGeometry, VariableEPSF

__all__ = [
    "FitOptions",
    "FitResult",
    "UNRESOLVED_SEPARATION",
    "colour_graph",
    "colour_stars",
    "crowding_flags",
    "fit_stars",
    "halo_radii",
    "marginalise_neighbours",
    "overlap_pairs",
    "render_model",
]

FLAG_NOT_CONVERGED = 1
FLAG_SATURATED = 2
FLAG_EDGE = 4
FLAG_CROWDED = 8
FLAG_NO_MATCH = 16
FLAG_FAILED = 32

#: Cosine between a star's position step and its last below which the step reverses it
#: (``FitOptions.bisect_reversals``).
REVERSAL_COSINE = -0.8


@dataclass(frozen=True)
class FitOptions:
    """Knobs of the batched fitter.

    Parameters
    ----------
    radius : int
        Stamp half-width [pixel].
    iterations : int
        Maximum number of Gauss-Seidel sweeps.
    tolerance : float
        Convergence: every position step below this [pixel] ...
    relative_tolerance : float
        ... or below this fraction of the star's position uncertainty.
    chi2_tolerance : bool
        The position uncertainty of ``relative_tolerance`` is the Fisher error times
        ``sqrt(1 + (chi2 - 1) q)`` (at least 1) at that step, with ``chi2`` the reduced
        chi^2 of the star's stamp and ``q`` the neighbours' share of the model light on
        it (:func:`_neighbour_misfit`): the error that its neighbours' mis-modelled light
        implies, instead of the Fisher error alone. In a crowd a faint star kept taking
        steps "above tolerance" as it slid towards that light (on the 1e5-star MAVIS
        frame 4.7 % of the V < 25 stars ended > 1 px from the truth while flagged
        converged, and 3.7 % were unconverged; docs/measure-scale.md).
    flux_refresh : bool
        After the last sweep, one more pass (positions held) refits every star's flux
        and sky against its neighbours' final models: a star that came to rest early
        keeps the flux it had while its neighbours were still moving otherwise.
    flux_passes : int
        Without starting fluxes (``flux0``), at most this many passes at fixed positions
        fit the fluxes and skies before the first position step: after the first, every
        star again, then only those whose flux step exceeded ``relative_tolerance`` times
        its flux error (at fixed positions) and their overlapping neighbours, until none
        does. In the first pass the stars of the first colours see their neighbours'
        fluxes still at zero, and nobody sees the halos (``wing_threshold``,
        ``halo_rings``: added after it); the first position step is linearised at the
        star's flux (its position derivatives scale with it), so a wrong flux makes a
        wrong step. On the 1e5-star MAVIS frame 10 % of the V 24-25 stars left the first
        pass with a flux below -1.3 x the truth, and their first step, cut to
        ``max_step``, left 2.4 % of the V < 25 stars unconverged 0.5 px from their start
        (docs/measure-scale.md, twelfth pass). 1: one pass (the fitter before
        2026-12-03).
    max_shift : float
        Largest allowed distance from the starting position [pixel].
    max_step : float
        Largest position step per iteration [pixel] (trust region).
    crowded_window : int
        Half-width [pixel] of the fitting window of a *crowded* star (below
        ``stamp radius``; 0: none): one whose own model light on its stamp outside that
        window is below ``crowded_ratio`` times its neighbours' there (stars and halos,
        after the first pass). Only its fit uses the smaller window; its model still
        covers the whole stamp for its neighbours. In a crowd the outer stamp of a faint
        star holds mostly its neighbours' light, whose model errors bias its flux and
        position more than that light informs them (docs/measure-scale.md).
    crowded_ratio : float
        The own / neighbours' light ratio below which ``crowded_window`` applies.
    check_cut_steps : bool
        A star whose last position step was cut to ``max_step`` counts as converged only
        if the Gauss-Newton step it would take at the solution is below its tolerance
        there too (the tolerance of the cut step came from the state before it, and can
        exceed ``max_step``: a fixed-pass flux and the start's misfit). A last step held
        back by ``max_shift`` (the star rests at the clamp) counts as cut. Flags only;
        the sweeps are unchanged. Needs the uncertainties.
    damping : float
        Levenberg-Marquardt damping (fraction of the diagonal).
    min_snr : float
        Positions of stars with flux SNR below this are held fixed in that step. A star
        whose position has never been fitted is stepped again in every sweep (while any
        star still moves), and one never fitted at the end is flagged failed (32) even
        when the last flux pass raises its SNR above this (before 2026-12-03 such a star
        rested as converged after its first step and kept flag 0 at its start position:
        5.8 % of the V < 25 stars of the 1e5-star frame; docs/measure-scale.md, tenth
        pass).
    chunk : int
        Stars evaluated at once (memory ~ chunk * S^2 * 16 * 8 bytes * mixing terms).
    progress : bool
        Show a tqdm progress bar over iterations.
    blend_radius : float
        Neighbours closer than this [pixel] are marginalised in the reported
        errors (:func:`marginalise_neighbours`).
    sky_gradient : bool
        Fit each star's local sky as a plane (level and two slopes) instead of a
        constant: the wings and halo of a much brighter star tens of pixels away
        tilt the background of the stamp, which a constant sky leaves in the
        positions. The slopes are marginalised in the reported errors.
    joint_radius : float
        Stars closer than this [pixel] (and their chains) take their Gauss-Newton
        steps jointly (:mod:`~mavispm.measure.stars.joint_step`); 0: every star alone.
    joint_max : int
        Largest such group; a larger chain is stepped star by star.
    joint_trust : float
        A group's joint step is shortened to at most this many times the length
        of its stars' single steps (in their own Fisher metrics); 0: no limit.
    wing_threshold : float
        Stars whose light outside their fitting stamp peaks above this many times
        the sky's pixel noise have it in the model their neighbours see, as a
        radial profile measured on the frame around its brightest stars
        (:func:`~mavispm.measure.stars.halo.halo_profile`), at the positions and
        fluxes of the first (fixed-position) pass; 0: none (that light is left to
        the neighbours' sky planes).
    halo_radius : float
        Outer radius of that light [pixel].
    halo_rings : float
        Stars whose halo at 20 px (the frame's profile times their flux) exceeds this
        many times the sky's pixel noise also get their own radial misfit added to the
        model, once, with the halos: the median of the residual (image less every star
        model and halo) in 1-px annuli from the stamp edge to 34 px, outside the star's
        stamp, less its median at 28-34 px, tapered from 22 to 30 px; 0: none. On the
        1e5-star MAVIS frame the frame's one profile misses each V < 15 star's own
        radial light by up to 2 faint-star fluxes at 12-20 px (docs/measure-scale.md,
        eleventh pass).
    halo_stack : float
        With ``halo_rings``: half-width [pixel] of a 2-D map of those stars' common
        non-round misfit (:func:`~mavispm.measure.stars.halo.stacked_residual`: the
        median over them of the residual per unit flux by pixel offset, each star's
        ring medians and the map's own ring means taken out), measured with the rings
        and added, times its flux, around the stars of ``halo_stack_stars``; 0 (or at most
        ``radius``): none (docs/measure-scale.md, sixteenth pass).
    halo_stack_stars : float
        The map goes onto the stars whose halo at 20 px exceeds this many times the
        sky's pixel noise (0: every star with a halo)
    halo_tail : float
        Beyond ``halo_radius`` the halo goes on to this radius [pixel] as a seeing halo,
        ``A r^(-11/3)`` fitted to the profile's last 12 px (the profile inside raised by
        the light it was measured against; :func:`~mavispm.measure.stars.halo.halo_tail`),
        added around the same stars at once by FFT
        (:func:`~mavispm.measure.stars.halo.deposit_tail`); 0 (or at most
        ``halo_radius``): none (docs/measure-scale.md, seventeenth pass).
    halo_background : float
        The profile is measured out to this radius [pixel] (:func:`halo_radii`), its
        zero point the median of the annulus ``[halo_background, halo_background + 10)``;
        each star's own deposit uses it out to ``halo_radius``, the tail's fit all of it;
        at most ``halo_radius`` (0): the annulus just past ``halo_radius``; with a tail,
        below ``halo_tail``. Where fewer than 5 stars have that annulus in the frame, the
        annulus just past ``halo_radius`` (docs/measure-scale.md, twenty-sixth pass).
    halo_saturated : bool
        The profile is also measured around saturated stars (their saturated pixels
        left out); False: around unsaturated ones only.
    halo_map : float
        With ``halo_rings``: radius [pixel] of each ring star's own 2-D misfit map
        (:func:`~mavispm.measure.stars.halo.residual_maps`: block medians of its
        residual after the rings and the stacked map, interpolated), added to the model
        once with them; 0 (or at most ``radius``): none (docs/measure-scale.md,
        twenty-seventh pass).
    halo_map_block : int
        Side [pixel] of the median blocks of ``halo_map`` (odd); with ``halo_map_arc``
        the polar bins' radial length.
    halo_map_arc : float
        If > 0: ``halo_map`` on polar bins this many px wide in azimuth (its 1-px
        annuli's medians and, of the rest, the bins' medians) instead of square blocks.
    halo_map_core : int
        If > 0: the ``(2 halo_map_core + 1)^2`` px around every star's stamp centre are
        left out of the residual the maps are measured on.
    fixed_full_system : bool
        Reference path (tests): the fixed-position steps solve the full system (the
        position rows frozen) with freshly evaluated stamps and derivatives, instead of
        the flux and sky rows alone on stamps kept from the first evaluation (the
        default; the same numbers to round-off, ~9 s less fit at 1e5 stars,
        docs/measure-scale.md, fifteenth pass).
    bisect_reversals : bool
        A position step that turns back on the star's last one (cosine below
        :data:`REVERSAL_COSINE`) is held to half that last step's length, and the star's
        trust radius (``max_step`` at first) keeps that limit, doubling again with each
        step that keeps its direction and is cut by it. Such a step brackets the minimum
        along the line between the last two positions: it counts as converged when it is
        below the star's tolerance and (with ``check_cut_steps``) the Gauss-Newton step
        at the solution across that line is too, instead of being judged as a cut step.
        A step cut by a trust radius below ``max_step`` brackets it the same way. Without
        it a star whose chi^2 is far from quadratic over ``max_step`` (a faint star
        beside a mis-modelled neighbour) stepped back and forth between two positions in
        every sweep: on the 1e5-star MAVIS frame 152 of the V < 25 stars left flagged 1
        were in exact two-sweep cycles, and their neighbours moved with them
        (docs/measure-scale.md, twenty-ninth pass).
    threads : int
        Threads the chunks of one colour (and of the uncertainties at the solution) are
        stepped on (:class:`~mavispm.measure.stars.chunk_pool.ChunkPool`); 0: every core
        this process may use. Within a colour every chunk reads the model as the colour
        found it and the chunks' new models are deposited after all of them, in chunk
        order: the results are the same bit for bit on any number of threads. (Before
        2026-12-03 each chunk deposited before the next was stepped; the stamps of a
        colour's stars can share corner pixels, the colouring separating them by
        ``2 radius + 1`` px in distance, so a later chunk saw those pixels' update.)
    """

    radius: int = 5
    iterations: int = 10
    tolerance: float = 1e-4
    relative_tolerance: float = 0.05
    chi2_tolerance: bool = False
    flux_refresh: bool = False
    flux_passes: int = 1
    fixed_full_system: bool = False
    max_shift: float = 2.0
    max_step: float = 0.5
    check_cut_steps: bool = False
    crowded_window: int = 0
    crowded_ratio: float = 0.05
    damping: float = 1e-3
    min_snr: float = 3.0
    chunk: int = 512
    progress: bool = False
    blend_radius: float = 5.0
    sky_gradient: bool = False
    joint_radius: float = 0.0
    joint_max: int = 16
    joint_trust: float = 10.0
    wing_threshold: float = 0.0
    halo_radius: float = 60.0
    halo_rings: float = 0.0
    halo_stack: float = 0.0
    halo_stack_stars: float = 0.0
    halo_tail: float = 0.0
    halo_background: float = 0.0
    halo_saturated: bool = False
    halo_map: float = 0.0
    halo_map_block: int = 5
    halo_map_arc: float = 0.0
    halo_map_core: int = 0
    threads: int = 1
    bisect_reversals: bool = False


@dataclass
class FitResult:
    """Per-star results of a fit (arrays of length N).

    Parameters
    ----------
    x, y : ndarray
        Fitted positions [pixel].
    flux, sky : ndarray
        Flux [electron] and local sky [electron/pixel].
    x_err, y_err, flux_err, sky_err : ndarray
        1-sigma uncertainties from the Fisher matrix at the solution (NaN for
        failed stars).
    chi2 : ndarray
        Reduced chi^2 of the stamp with model weights.
    flag : ndarray of int
        Bitmask (see module docstring).
    iterations : int
        Sweeps performed.
    model_image : ndarray or None
        Sum of the fitted star models (no sky) [electron], frame shaped (None
        when not asked for).
    sky_slope : ndarray, shape (N, 2)
        Fitted sky slopes d sky / d column, d sky / d row [electron / pixel] about
        the stamp centre (the nearest pixel to the start position); zeros
        without ``sky_gradient``.
    halo_profile : ndarray or None
        The frame's halo profile per unit flux [1/pixel] that the fit used
        (:func:`~mavispm.measure.stars.halo.halo_profile`, at the annuli
        :func:`halo_radii`): measured by this fit or passed to it (``halo``); None
        when the fit models no light outside the stamps.
    crowding : ndarray or None
        The stamp's misfit that the neighbours' light explains at the solution,
        ``1 + (chi2 - 1) q`` with ``q`` the neighbours' share of the model light on the
        stamp (:func:`_neighbour_misfit`; NaN where no uncertainties were computed;
        None from other engines): the error model's crowding term.
    correlated_gain : ndarray, shape (N, 2) or None
        Position variance [pixel^2] per axis per unit excess reduced chi^2 of a residual
        field at the PSF's scale on the stamp (:func:`_correlated_gain`; NaN where no
        uncertainties were computed and where no halo light falls on the stamp): the
        error model's correlated-misfit term.
    halo_share : ndarray, shape (N,) or None
        The bright stars' halo light (outside their stamps, with the ring corrections)
        over all the model light on the stamp (the star's own included), 0-1 (zeros
        without a halo).
    chi2_odd : ndarray or None
        Reduced chi^2 of the stamp residual's part odd about the star.
    light_image : ndarray or None
        All the modelled light the stars see at the solution (every star's stamp model,
        the halos and their tail; no sky) [electron], frame shaped, NaN off the stamps
        (where the fit modelled nothing)
        (None unless ``return_light``): the post-fit rescue
        (:mod:`~mavispm.measure.stars.rescue`) subtracts it.
    """

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    sky: np.ndarray
    x_err: np.ndarray
    y_err: np.ndarray
    flux_err: np.ndarray
    sky_err: np.ndarray
    chi2: np.ndarray
    flag: np.ndarray
    iterations: int
    model_image: np.ndarray | None
    sky_slope: np.ndarray | None = None
    halo_profile: np.ndarray | None = None
    crowding: np.ndarray | None = None
    correlated_gain: np.ndarray | None = None
    halo_share: np.ndarray | None = None
    chi2_odd: np.ndarray | None = None
    light_image: np.ndarray | None = None


def residual_correlation(psf: VariableEPSF, nx: int, ny: int, radius: int) -> np.ndarray:
    """Correlation matrix of a residual field made of PSF-shaped structure, on a stamp.

    Unmodelled light (a bright star's halo misfit, its speckles and ring residuals, a
    neighbour's ePSF error) is structure at the scale of the PSF: a field of PSF-shaped
    blobs at random places, whose correlation is the PSF's autocorrelation. Taken from
    the ePSF at the frame centre, sampled on the pixels, normalised to 1 at zero lag.

    Parameters
    ----------
    psf : VariableEPSF
    nx, ny : int
        Frame size [pixel].
    radius : int
        Fit stamp half-width [pixel].

    Returns
    -------
    ndarray, shape (S*S, S*S)
        ``R[i, j]`` between stamp pixels i and j (row-major), ``S = 2 radius + 1``.
    """
    big = 2 * int(radius)
    cx, cy = (nx - 1) // 2, (ny - 1) // 2
    geom = StampGeometry(np.array([cx], np.intp), np.array([cy], np.intp), big)
    p = np.asarray(
        psf.evaluate(np.array([float(cx)]), np.array([float(cy)]), geom, derivatives=False)
    )[0]
    p = np.nan_to_num(p)
    m = 2 * big + 1
    pad = np.zeros((2 * m, 2 * m))
    pad[:m, :m] = p
    spec = np.fft.rfft2(pad)
    ac = np.fft.irfft2(spec * np.conj(spec), pad.shape)
    ac = np.fft.fftshift(ac)  # zero lag at (m, m)
    ac /= max(ac[m, m], 1e-300)
    s = 2 * int(radius) + 1
    off = np.arange(s)
    row = np.repeat(off, s)
    col = np.tile(off, s)
    return ac[m + row[:, None] - row[None, :], m + col[:, None] - col[None, :]]


def halo_radii(options: FitOptions) -> np.ndarray:
    """Centres [pixel] of the 1-px annuli of the frame's measured halo profile.

    Parameters
    ----------
    options : FitOptions
        ``radius``, ``halo_radius`` and ``halo_background``.

    Returns
    -------
    ndarray
        ``radius + 0.5, radius + 1.5, ...`` below ``max(halo_radius, halo_background) +
        0.5`` (each star's own deposit uses those below ``halo_radius + 0.5``).
    """
    outer = max(options.halo_radius, options.halo_background)
    return np.arange(int(options.radius) + 0.5, outer + 0.5)


def colour_stars(x: np.ndarray, y: np.ndarray, distance: float) -> np.ndarray:
    """Greedy colouring so that stars closer than ``distance`` differ in colour.

    Parameters
    ----------
    x, y : ndarray, shape (N,)
        Positions [pixel].
    distance : float
        Conflict distance [pixel] (stamps overlap below ``2 radius + 1``).

    Returns
    -------
    ndarray of int, shape (N,)
        Colour of each star, 0 .. n_colours - 1.
    """
    n = len(x)
    colour = np.zeros(n, dtype=np.intp)
    if n < 2:
        return colour
    pairs = cKDTree(np.column_stack([x, y])).query_pairs(distance, output_type="ndarray")
    return colour_graph(n, pairs)


def colour_graph(n: int, pairs: np.ndarray) -> np.ndarray:
    """Greedy colouring of a graph: nodes joined by a pair differ in colour.

    Parameters
    ----------
    n : int
        Number of nodes.
    pairs : ndarray of int, shape (P, 2)
        Edges (each once, no self-edges).

    Returns
    -------
    ndarray of int, shape (N,)
        Colour of each node, highest degree first, each the lowest colour free.
    """
    colour = np.zeros(n, dtype=np.intp)
    if n < 2 or len(pairs) == 0:
        return colour
    # adjacency lists in CSR form, each list in the order the pairs were found
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    degree = np.bincount(both[:, 0], minlength=n)
    indptr = np.concatenate([[0], np.cumsum(degree)])
    order = np.argsort(-degree, kind="stable")
    return _greedy_colours(
        order.astype(np.intp), indptr.astype(np.intp), both[:, 1].astype(np.intp)
    )


@numba.njit(nogil=True, cache=True)
def _greedy_colours(order, indptr, neighbours):
    """Greedy colouring in ``order``: each star takes the lowest colour none of its
    already coloured neighbours has (O(sum of degrees))."""
    n = len(order)
    colour = np.full(n, -1, dtype=np.intp)
    used = np.full(int(np.max(indptr[1:] - indptr[:-1])) + 2, -1, dtype=np.intp)
    for i in order:
        for k in range(indptr[i], indptr[i + 1]):
            c = colour[neighbours[k]]
            if c >= 0:
                used[c] = i  # marks colour c as taken for star i
        c = 0
        while used[c] == i:
            c += 1
        colour[i] = c
    return colour


#: Separation [pixel] below which two stars are one blob to any fit: both are flagged
#: crowded whatever their fluxes (the fit shares their light arbitrarily).
UNRESOLVED_SEPARATION = 1.0


def crowding_flags(
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    radius: float,
    ratio: float,
    min_separation: float = UNRESOLVED_SEPARATION,
) -> np.ndarray:
    """True for stars with a neighbour within ``radius`` at least ``ratio`` times as bright,
    and for both stars of every pair closer than ``min_separation`` [pixel].

    Parameters
    ----------
    x, y : ndarray
        Positions [pixel]; stars with non-finite positions are never flagged.
    flux : ndarray
        Fluxes [electron].
    radius : float
        Neighbour search radius [pixel].
    ratio : float
        Brightness ratio of a neighbour that flags a star.
    min_separation : float
        Pairs closer than this are flagged both [pixel].

    Returns
    -------
    ndarray of bool
        One flag per star.
    """
    n = len(x)
    crowded = np.zeros(n, dtype=bool)
    good = np.isfinite(x) & np.isfinite(y)
    if n < 2 or good.sum() < 2:
        return crowded
    idx = np.flatnonzero(good)
    pairs = cKDTree(np.column_stack([x[idx], y[idx]])).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return crowded
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    f = np.where(np.isfinite(flux), flux, 0.0)
    crowded[i[f[j] >= ratio * f[i]]] = True
    crowded[j[f[i] >= ratio * f[j]]] = True
    close = np.hypot(x[i] - x[j], y[i] - y[j]) < min_separation
    crowded[i[close]] = True
    crowded[j[close]] = True
    return crowded


def render_model(
    shape: tuple[int, int],
    psf: VariableEPSF,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    radius: int,
    chunk: int = 512,
) -> np.ndarray:
    """Image [electron] of stars on stamps of half-width ``radius`` (no sky).

    Parameters
    ----------
    shape : (ny, nx)
    psf : VariableEPSF
    x, y : ndarray
        Positions [pixel] (non-finite entries are skipped).
    flux : ndarray
        Fluxes [electron].
    radius : int
        Stamp half-width [pixel].
    chunk : int
        Stars evaluated at once.
    """
    ny, nx = shape
    out = np.zeros(ny * nx)
    x, y, flux = (np.atleast_1d(np.asarray(a, float)) for a in (x, y, flux))
    keep = np.flatnonzero(np.isfinite(x) & np.isfinite(y) & np.isfinite(flux))
    for idx in _chunks(keep, chunk):
        geom = StampGeometry(
            np.rint(x[idx]).astype(np.intp), np.rint(y[idx]).astype(np.intp), radius
        )
        rows, cols = geom.rows(), geom.columns()
        inside = ((rows >= 0) & (rows < ny))[:, :, None] & ((cols >= 0) & (cols < nx))[:, None, :]
        flat = np.clip(rows, 0, ny - 1)[:, :, None] * nx + np.clip(cols, 0, nx - 1)[:, None, :]
        val = flux[idx, None, None] * psf.evaluate(x[idx], y[idx], geom, derivatives=False)
        np.add.at(out, flat[inside], val[inside])
    return out.reshape(shape)


def overlap_pairs(x: np.ndarray, y: np.ndarray, keep: np.ndarray, distance: float) -> np.ndarray:
    """Pairs of the kept stars closer than ``distance``: the stamps that overlap.

    Only the kept stars are searched. The fitter parks the stars off the frame at one
    position; searched with the others, those ``K`` stars formed a clique of ``K^2 / 2``
    pairs and ``K`` colours (on the 1e5-star MAVIS frame 4,953 stars off the frame:
    12.3 million of the 12.4 million pairs and 4,955 colours where the stars on the frame
    need 8), every sweep looped over those colours and pairs, and the fit's cost grew as
    ``N^2`` (docs/measure-scale.md).

    Parameters
    ----------
    x, y : ndarray, shape (N,)
        Positions [pixel].
    keep : ndarray of bool, shape (N,)
        Stars that take part.
    distance : float
        Pair distance [pixel].

    Returns
    -------
    ndarray of int, shape (P, 2)
        Indices into ``x`` of each pair (each once, the lower index first).
    """
    idx = np.flatnonzero(keep)
    if len(idx) < 2:
        return np.zeros((0, 2), dtype=np.intp)
    pairs = cKDTree(np.column_stack([x[idx], y[idx]])).query_pairs(distance, output_type="ndarray")
    return idx[pairs]


@numba.njit(nogil=True, cache=True)
def _deposit_change(model, flat, inside, own, idx, new):
    """``model[flat[i]] += new - own[i]`` on each star ``i`` of ``idx``'s pixels inside the
    frame, element by element in order (as ``np.add.at``), then ``own[idx] = new``."""
    for k in range(idx.shape[0]):
        i = idx[k]
        for p in range(new.shape[1]):
            if inside[i, p]:
                model[flat[i, p]] += new[k, p] - own[i, p]
            own[i, p] = new[k, p]


def _chunks(index: np.ndarray, size: int):
    for start in range(0, len(index), size):
        yield index[start : start + size]


def fit_stars(
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
    options: FitOptions | None = None,
    return_model: bool = True,
    uncertainties: bool = True,
    halo: np.ndarray | None = None,
    halo_shape: HaloShape | None = None,
    return_light: bool = False,
    hold_positions: np.ndarray | None = None,
) -> FitResult:
    """Fit positions, fluxes and local skies of all stars simultaneously.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        The frame [electron].
    psf : VariableEPSF
        Field-variable ePSF.
    x0, y0 : ndarray, shape (N,)
        Starting (forced) positions [pixel].
    read_noise_var : float
        Read-noise variance per pixel of the frame [electron^2].
    sky0 : float
        Starting sky level [electron/pixel].
    flux0 : ndarray, optional
        Starting fluxes [electron]; by default a linear fit at fixed positions.
    bad : ndarray of bool, optional
        Pixels to ignore (NaN pixels are always ignored).
    saturated : ndarray of bool, optional
        Saturated pixels (ignored, and the star flagged 2).
    options : FitOptions, optional
    return_model : bool
        Also return the frame-sized model image (the ePSF builder's many small
        fits do not need it).
    uncertainties : bool
        Compute the Fisher errors and chi^2 at the solution (otherwise NaN, and
        only non-positive fluxes count as failed).
    halo : ndarray, optional
        With ``options.wing_threshold > 0``: the frame's halo profile per unit flux
        [1/pixel] at the annuli :func:`halo_radii`, as an earlier fit of the same
        frame returned it (:attr:`FitResult.halo_profile`): the profile is a property
        of the frame, and measuring it (:func:`~mavispm.measure.stars.halo.halo_profile`)
        costs ~0.3 s per fit at 3,500 stars. None (default): measured from the
        image around this fit's brightest stars.
    halo_shape : HaloShape, optional
        The non-round shape of the halo (:mod:`~mavispm.measure.stars.halo_shape`, from
        the PSF-R prior): each bright star's light outside its stamp is the radial
        profile times this modulation. None (default): round.
    return_light : bool
        Also return :attr:`FitResult.light_image` (the model with the halos).
    hold_positions : ndarray of bool, shape (N,), optional
        Stars whose positions stay at their start (forced photometry: their flux and
        local sky are fitted, their light is in their neighbours' model). They count
        as converged, are flagged failed (32) only for their flux (non-positive or
        below ``min_snr``), and their position errors are NaN (not measured). None
        (default): every position is fitted.

    Returns
    -------
    FitResult
    """
    opt = options or FitOptions()
    with ChunkPool(resolve_threads(opt.threads)) as pool:
        return _fit_stars(
            image, psf, x0, y0, read_noise_var, sky0, flux0, bad, saturated, opt,
            return_model, uncertainties, halo, halo_shape, pool, return_light,
            hold_positions,
        )  # fmt: skip


def _fit_stars(
    image, psf, x0, y0, read_noise_var, sky0, flux0, bad, saturated, opt, return_model,
    uncertainties, halo, halo_shape, pool, return_light=False, hold_positions=None,
):  # fmt: skip
    """:func:`fit_stars` with its options resolved, the chunks on ``pool``."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise InputError(f"image must be 2-D, got shape {image.shape}")
    ny, nx = image.shape
    x0 = np.atleast_1d(np.asarray(x0, dtype=float)).copy()
    y0 = np.atleast_1d(np.asarray(y0, dtype=float)).copy()
    if x0.shape != y0.shape or x0.ndim != 1:
        raise InputError(f"x0 and y0 must be 1-D of equal length, got {x0.shape} and {y0.shape}")
    n = len(x0)
    hold = np.zeros(n, bool) if hold_positions is None else np.asarray(hold_positions, bool)
    if hold.shape != (n,):
        raise InputError(f"hold_positions has shape {hold.shape}; expected ({n},), one per star")
    for name, m in (("bad", bad), ("saturated", saturated)):
        if m is not None and np.shape(m) != image.shape:
            raise InputError(
                f"{name} mask shape {np.shape(m)} differs from image shape {image.shape}"
            )
    flag = np.zeros(n, dtype=np.int64)
    usable = on_detector(x0, y0, (ny, nx))
    flag[~usable] |= FLAG_FAILED | FLAG_EDGE
    on_frame = usable.copy()  # the others are parked at (0, 0) and have no neighbours
    x = np.where(usable, x0, 0.0)
    y = np.where(usable, y0, 0.0)
    start_x, start_y = x.copy(), y.copy()

    r = int(opt.radius)
    geom = StampGeometry(np.rint(x).astype(np.intp), np.rint(y).astype(np.intp), r)
    s = geom.size
    rows, cols = geom.rows(), geom.columns()
    inside = ((rows >= 0) & (rows < ny))[:, :, None] & ((cols >= 0) & (cols < nx))[:, None, :]
    # work on the pixels the stamps touch only (compact index), never on full-frame
    # arrays: the ePSF builder fits a few hundred stars of a 4k x 4k frame many times
    # 32-bit pixel indices where the frame allows (half the memory of the N x S^2 index
    # arrays: ~100 MB each at 1e5 stars)
    itype = np.int32 if ny * nx < 2**31 else np.intp
    frame_index = (
        np.clip(rows, 0, ny - 1).astype(itype)[:, :, None] * itype(nx)
        + np.clip(cols, 0, nx - 1).astype(itype)[:, None, :]
    ).reshape(n, -1)
    pixels, flat = np.unique(frame_index, return_inverse=True)
    del frame_index
    flat = flat.reshape(n, -1).astype(itype)
    values = np.asarray(image.reshape(-1)[pixels], dtype=float)
    sat_pix = (
        np.zeros(len(pixels), bool)
        if saturated is None
        else np.asarray(saturated, bool).reshape(-1)[pixels]
    )
    bad_pix = ~np.isfinite(values) | sat_pix
    if bad is not None:
        bad_pix |= np.asarray(bad, bool).reshape(-1)[pixels]
    inside = inside.reshape(n, -1) & usable[:, None]
    data = np.where(inside, np.nan_to_num(values[flat]), 0.0)
    valid = inside & ~bad_pix[flat]
    flag[np.any(~inside, axis=1) & usable] |= FLAG_EDGE
    flag[np.any(inside & sat_pix[flat], axis=1)] |= FLAG_SATURATED
    npix_valid = valid.sum(axis=1)
    usable &= npix_valid > 4
    flag[~usable] |= FLAG_FAILED

    mix = psf.mixing(x, y)
    sky = np.full(n, float(sky0))
    # sky plane: slopes [electron / pixel^2] on the stamp offsets from its centre
    npar = 6 if opt.sky_gradient else 4
    slope = np.zeros((n, 2))
    plane_basis = sky_plane_basis(s)
    flux = np.zeros(n) if flux0 is None else np.nan_to_num(np.asarray(flux0, float)).copy()
    own = np.zeros((n, s * s))  # each star's current contribution to the model image
    model = np.zeros(len(pixels))  # sum of all star models on the touched pixels
    pairs = overlap_pairs(x, y, on_frame, 2 * r + 1.0)
    # tightly coupled stars step jointly (joint_step); the groups are coloured so that
    # no two groups stepped together overlap (a star alone is a group of one)
    label, colour = _coloured_groups(x, y, usable, pairs, opt)
    gsize = np.bincount(label)
    # each colour in bands of rows, left to right: consecutive stars then read the same
    # few basis ePSFs (the evaluation is bound by memory reads; 27 -> 18 us per star
    # with an 11 x 11 grid). Groups of one colour do not overlap: the order changes
    # nothing but rounding. A group's stars are consecutive.
    gx, gy = np.bincount(label, x) / gsize, np.bincount(label, y) / gsize
    key = (label, gx[label], np.floor(gy[label] / 64.0))
    order = np.lexsort(key)
    order = order[usable[order]]
    groups = [order[colour[order] == c] for c in range(colour.max() + 1)]
    active = usable.copy()  # stars (re)fitted in the next sweep

    def deposit(idx, new):
        # scatter-add of the change, element by element in order (as np.add.at did; a
        # bincount over all touched pixels cost O(N) per chunk, O(N^2) per sweep: 177 s
        # of fit for 1e5 stars), compiled: 3.9 -> ~0.3 s at 1e5 stars, on one thread
        _deposit_change(model, flat, inside, own, idx, new)

    def step_colour(work):
        """Step the chunks ``work`` (``(idx, fixed, together)`` each) of one colour on
        the pool: all read the model as the colour found it; their new models are
        deposited after all of them, in chunk order (the same on any thread count)."""
        news = pool.map(lambda w: step_stars(*w), work)
        for (idx, _, _), new in zip(work, news):
            deposit(idx, new)

    def evaluate(idx, derivatives=True):
        sub = (mix[0][idx], mix[1][idx])
        stamps = StampGeometry(geom.cx[idx], geom.cy[idx], r)
        return psf.evaluate(x[idx], y[idx], stamps, mix=sub, derivatives=derivatives)

    # each star's ePSF stamp at its start position, kept while the positions are held
    # (the fixed-position passes before the first position step: the initial flux fit
    # and ``flux_passes``); None once a position sweep begins
    held = {"v": np.zeros((n, s * s)), "have": np.zeros(n, bool)} if flux0 is None else None

    def held_stamps(idx):
        """The unit-flux ePSF of the stars ``idx`` at their (held) positions."""
        if held is None:
            return evaluate(idx, derivatives=False).reshape(len(idx), -1)
        new = idx[~held["have"][idx]]
        if len(new):
            held["v"][new] = evaluate(new, derivatives=False).reshape(len(new), -1)
            held["have"][new] = True
        return held["v"][idx]

    def normal_equations(idx, positions=True):
        if positions:
            v, dvx, dvy = (a.reshape(len(idx), -1) for a in evaluate(idx))
        else:  # fixed positions: the flux and sky rows only, no derivatives
            v, dvx, dvy = held_stamps(idx), None, None
        a, b, w, resid = fused_normal_equations(
            v,
            dvx,
            dvy,
            data[idx],
            model[flat[idx]],
            own[idx],
            valid[idx],
            flux[idx],
            sky[idx],
            slope[idx] if opt.sky_gradient else None,
            plane_basis,
            read_noise_var,
            positions,
        )
        return v, dvx, dvy, a, b, w, resid

    def flux_step(idx):
        """:func:`step_stars` at fixed positions for stars stepped alone: the linear
        flux and sky (and slopes) solve only, on the held ePSF stamps. The same
        numbers as the full system with the position rows frozen (identity rows, no
        right-hand side, decoupled from the rest): tested against it."""
        v, _, _, a, b, _, _ = normal_equations(idx, positions=False)
        a_d = _damped(a[:, 2:, 2:], opt.damping)
        step = _solve(a_d, b[:, 2:])
        if opt.flux_passes > 1:
            flux_moved[idx] = _step_over_error(a_d, step, 0)
        flux[idx] += step[:, 0]
        sky[idx] += step[:, 1]
        if opt.sky_gradient:
            slope[idx] += step[:, 2:]
        steps[idx] = 0.0
        return flux[idx, None] * v

    def step_stars(idx, fixed, together):
        """One damped Gauss-Newton step of the stars ``idx``; ``together`` (their group
        labels, each group's stars consecutive) couples the stars of a group. Returns
        their new models (to :func:`deposit`)."""
        if fixed and together is None and not opt.fixed_full_system:
            return flux_step(idx)
        v, dvx, dvy, a, b, w, resid = normal_equations(idx)
        a_d = _damped(a, opt.damping)
        if fixed:
            frozen = np.ones(len(idx), bool)
        else:
            cov, ok = safe_inverse(a)
            snr = flux[idx] / np.sqrt(np.abs(cov[:, 2, 2]))
            misfit = (
                _neighbour_misfit(
                    w * resid**2, others_on(flat[idx], own[idx]), own[idx], valid[idx], npar
                )
                if opt.chi2_tolerance
                else None
            )
            thresh[idx] = _position_tolerance(cov, misfit, opt)
            frozen = ~ok | ~(snr > opt.min_snr)
            pinned = hold[idx]
            fitted[idx[~frozen | pinned]] = True
            frozen |= pinned
        # positions of frozen stars held: identity rows, no right-hand side
        a_d[frozen, :2, :] = 0.0
        a_d[frozen, :, :2] = 0.0
        a_d[frozen, 0, 0] = a_d[frozen, 1, 1] = 1.0
        b = b.copy()
        b[frozen, :2] = 0.0
        step = None
        rows, cols = _group_pairs(together) if together is not None else ((), ())
        if len(rows):  # a chunk without a pair within joint_radius steps on its own
            geom_i = StampGeometry(geom.cx[idx[rows]], geom.cy[idx[rows]], r)
            j = idx[cols]
            other = psf.evaluate(x[j], y[j], geom_i, mix=(mix[0][j], mix[1][j]))
            jac = jacobian(
                flux[idx], *(e.reshape(len(idx), s, s) for e in (v, dvx, dvy)), opt.sky_gradient
            )
            cross = cross_blocks(
                flux[j], *(e.reshape(len(j), -1) for e in other), jac[rows], w[rows]
            )
            cross[frozen[rows], :2, :] = 0.0
            cross[frozen[cols], :, :2] = 0.0
            step = solve_groups(a_d, b, rows, cols, cross)
        single = _solve(a_d, b)
        if step is None:
            step = single
        elif opt.joint_trust > 0:
            step = _limit_group_steps(step, single, a_d, together, opt.joint_trust)
        if not fixed:
            length = np.hypot(step[:, 0], step[:, 1])
            limit = np.full(len(idx), opt.max_step)
            if opt.bisect_reversals:
                limit, reverse = _bisected_limit(step, last_step[idx], trust[idx], opt)
            shrink = np.minimum(1.0, limit / np.maximum(length, 1e-300))
            step[:, :2] *= shrink[:, None]
            cut[idx] = shrink < 1.0
            if opt.bisect_reversals:
                # a step held to half the reversed last one brackets the minimum: it is
                # judged by its length (and the solution's step across it), not as cut
                bracketed[idx] = cut[idx] & (reverse | (limit < opt.max_step))
                cut[idx] &= ~bracketed[idx]
                # the trust radius regrows while the star keeps its direction
                regrown = np.minimum(opt.max_step, np.where(shrink < 1.0, 2.0 * limit, limit))
                trust[idx] = np.where(reverse, limit, regrown)
        elif opt.flux_passes > 1:
            # the flux step over the flux error at fixed positions (flux_passes)
            flux_moved[idx] = _step_over_error(a_d, step, 2)
        dx, dy = step[:, 0], step[:, 1]
        x[idx] += dx
        y[idx] += dy
        flux[idx] += step[:, 2]
        sky[idx] += step[:, 3]
        if opt.sky_gradient:
            slope[idx] += step[:, 4:]
        # keep within max_shift of the start
        off_x, off_y = x[idx] - start_x[idx], y[idx] - start_y[idx]
        dist = np.hypot(off_x, off_y)
        pull = np.minimum(1.0, opt.max_shift / np.maximum(dist, 1e-300))
        x[idx] = start_x[idx] + off_x * pull
        y[idx] = start_y[idx] + off_y * pull
        dx = dx - off_x * (1 - pull)
        dy = dy - off_y * (1 - pull)
        if not fixed and opt.check_cut_steps:
            # a step stopped by max_shift is cut too: its length says nothing about the
            # free optimum (on the 1e5-star frame 1 % of the V < 25 stars rested at the
            # clamp, called converged; docs/measure-scale.md, thirteenth pass)
            cut[idx] |= pull < 1.0
        steps[idx] = np.hypot(dx, dy)
        if not fixed:
            last_step[idx, 0], last_step[idx, 1] = dx, dy
        return flux[idx, None] * (
            v.reshape(len(idx), -1)
            + dvx.reshape(len(idx), -1) * dx[:, None]
            + dvy.reshape(len(idx), -1) * dy[:, None]
        )

    if (
        opt.halo_radius < opt.halo_background
        and opt.halo_radius < opt.halo_tail <= opt.halo_background
    ):
        raise InputError(
            f"halo_background ({opt.halo_background}) must lie inside halo_tail ({opt.halo_tail}):"
            " the tail is fitted to the profile's last 12 px"
        )
    measure_radii = halo_radii(opt)
    # each star's own deposit: the annuli below halo_radius
    radii = measure_radii[measure_radii < opt.halo_radius + 0.5]
    if halo is not None:
        halo = np.asarray(halo, dtype=float)
        if halo.shape != measure_radii.shape:
            raise InputError(
                f"halo profile has shape {halo.shape}; expected ({len(measure_radii)},), one "
                f"value per 1-px annulus from radius + 0.5 = {measure_radii[0]} to "
                "max(halo_radius, halo_background)"
            )
    measured = halo

    def add_halo():
        """Add the bright stars' light outside their stamps to the model (once)."""
        nonlocal measured
        if measured is None:
            mask = bad if saturated is None else (saturated if bad is None else bad | saturated)
            args = (image, mask, x[usable], y[usable], flux[usable])
            eligible = None if opt.halo_saturated else (flag[usable] & FLAG_SATURATED) == 0
            measured = halo_profile(*args, measure_radii, eligible=eligible)
            if len(measure_radii) > len(radii) and not np.any(measured):
                # too few stars hold the far background annulus in the frame: the
                # annulus just past halo_radius, the profile continued beyond as the tail
                near = halo_profile(*args, radii, eligible=eligible)
                measured = halo_tail(near, radii[0], 2.0 * measure_radii[-1])
                measured = np.pad(measured, (0, len(measure_radii)))[: len(measure_radii)]
        # the frame's light at every radius, also inside the ePSF's footprint: the ePSF
        # beyond its fitting stamp is barely constrained (on the 1e5-star MAVIS frame its
        # azimuthal mean was 10-25 % below the rendered light at 8-12 px, and splicing it
        # to the measured profile left a step at the footprint's edge that drove faint
        # neighbours' fluxes negative; docs/measure-scale.md)
        profile = measured[: len(radii)]
        limit = opt.wing_threshold * np.sqrt(max(sky0 + read_noise_var, 1e-300))
        bright = np.flatnonzero(usable & (flux * np.max(profile) > limit))
        # into the model (kept apart too for the returned star-model image): deposited
        # once, into halo_light (still zero) where it is kept, then added (one deposit,
        # 2.3 s at 1e5 stars, instead of one into each; the same to round-off)
        out = halo_light if len(halo_light) else model
        args = (pixels, (ny, nx), x[bright], y[bright], geom.cx[bright], geom.cy[bright], r)
        inner = profile
        if opt.halo_tail > opt.halo_radius:
            # the halo past halo_radius as a seeing halo; the profile inside raised by
            # the light it was measured against (the selections keep the frame's profile)
            full = halo_tail(measured, radii[0], opt.halo_tail)
            if len(full) > len(measured):  # else no tail (its amplitude not positive)
                # each star's own deposit fades out over the profile's last TAIL_SEAM px,
                # where the FFT's (smooth: the bilinear flux split blurs a step) fades in
                seam = tail_ramp(radii[0] + np.arange(len(full)), radii[-1])
                inner = full[: len(profile)] * (1.0 - seam[: len(profile)])
                # into the model, kept apart (tail_light): the returned star-model image,
                # the neighbours' light of the crowding measures and the halo share that
                # sizes the correlated-misfit error term (halo_light) leave it out
                deposit_tail(
                    pixels, (ny, nx), x[bright], y[bright], flux[bright], full * seam, radii[0],
                    (tail_light,),
                )  # fmt: skip
                model[:] += tail_light
        if halo_shape is None:
            deposit_radial(*args, flux[bright], inner, radii[0], out=out)
        else:
            deposit_shaped(*args, flux[bright], inner, radii[0], halo_shape, out)
        if len(halo_light):
            model[:] += halo_light
        if opt.halo_rings > 0:
            ring_corrections(bright, profile)

    def ring_corrections(bright, profile):
        """Add each very bright star's own radial misfit to the model (``halo_rings``):
        :func:`~mavispm.measure.stars.halo.ring_corrections` for the stars whose halo at
        ``RING_REFERENCE`` px exceeds ``halo_rings`` times the sky's pixel noise."""
        at = min(int(round(RING_REFERENCE - radii[0])), len(profile) - 1)
        noise = np.sqrt(max(sky0 + read_noise_var, 1e-300))
        big = bright[flux[bright] * profile[at] > opt.halo_rings * noise]
        adds = halo_ring_corrections(
            pixels, (ny, nx), values, model, bad_pix, x[big], y[big], geom.cx[big], geom.cy[big], r, radii
        )  # fmt: skip
        reach = int(opt.halo_stack)
        outs = (model, halo_light) if len(halo_light) else (model,)
        if reach > r and len(big) >= 5:
            # their common non-round misfit, per unit flux, onto the stars whose halo
            # at RING_REFERENCE exceeds halo_stack_stars times the sky's pixel noise
            stack = stacked_residual(
                pixels, (ny, nx), values, model, bad_pix, geom.cx[big], geom.cy[big],
                flux[big], r, reach,
            )  # fmt: skip
            onto = bright[flux[bright] * profile[at] > opt.halo_stack_stars * noise]
            deposit_stacked(pixels, (ny, nx), geom.cx[onto], geom.cy[onto], flux[onto], stack, outs)
        for where, light in adds:  # after all are measured: none sees another's
            for out in outs:
                out[where] += light
        if int(opt.halo_map) > r and len(big):
            # each one's own 2-D misfit left after its rings and the common map
            skip = bad_pix
            if opt.halo_map_core > 0:  # the stars' cores left out of that residual
                skip = bad_pix | core_pixels(
                    pixels, (ny, nx), geom.cx[usable], geom.cy[usable], opt.halo_map_core
                )
            maps = residual_maps(
                pixels, (ny, nx), values, model, skip, geom.cx[big], geom.cy[big], r,
                int(opt.halo_map), int(opt.halo_map_block), opt.halo_map_arc,
            )  # fmt: skip
            for where, light in maps:
                for out in outs:
                    out[where] += light

    models_halo = opt.wing_threshold > 0 and opt.halo_radius > r + 1
    halo_pending = models_halo
    # kept apart for the returned star-model image and the error model's halo share
    halo_light = np.zeros(len(pixels) if halo_pending and (return_model or uncertainties) else 0)
    # kept apart always: a smooth light, absorbed by the sky planes, is no neighbour's
    # light in the crowding measures (others_on)
    tail_light = np.zeros(len(pixels) if halo_pending and opt.halo_tail > opt.halo_radius else 0)

    def others_on(where, mine):
        """The neighbours' model light (stars and halos, not the halos' smooth tail) on
        the pixels ``where`` of stamps whose own model is ``mine`` [e-]."""
        if len(tail_light):
            return model[where] - tail_light[where] - mine
        return model[where] - mine

    if halo_pending and flux0 is not None:
        add_halo()
        halo_pending = False

    window_pending = 0 < opt.crowded_window < r

    def narrow_windows():
        """Fit the crowded stars on the central window only (``crowded_window``)."""
        off = np.abs(np.arange(s) - r)
        inner = (
            (off[:, None] <= opt.crowded_window) & (off[None, :] <= opt.crowded_window)
        ).ravel()
        for idx in _chunks(np.flatnonzero(usable), opt.chunk):
            mine = own[idx][:, ~inner]
            others = np.maximum(others_on(flat[idx][:, ~inner], mine), 0.0)
            outer = valid[idx][:, ~inner]
            ratio = np.sum(np.abs(mine) * outer, 1) / np.maximum(np.sum(others * outer, 1), 1e-300)
            narrow = (ratio < opt.crowded_ratio) & (np.sum(valid[idx][:, inner], 1) > 2 * npar)
            valid[idx[narrow]] &= inner

    flux_moved = np.zeros(n)  # the last fixed pass's flux step over the flux error

    def more_flux_passes():
        """Fixed-position passes after the first (``flux_passes``): every star once,
        then those whose flux still moves and their overlapping neighbours."""
        todo = usable.copy()
        for _ in range(opt.flux_passes - 1):
            flux_moved[:] = 0.0
            for group in groups:
                step_colour([(idx, True, None) for idx in _chunks(group[todo[group]], opt.chunk)])
            moved = usable & (flux_moved >= opt.relative_tolerance)
            if not np.any(moved):
                break
            todo = moved.copy()
            if len(pairs):
                todo[pairs[moved[pairs[:, 1]], 0]] = True
                todo[pairs[moved[pairs[:, 0]], 1]] = True

    # initial fluxes: linear fit at fixed positions (positions frozen)
    sweeps = ([True] if flux0 is None else []) + [False] * int(opt.iterations)
    steps = np.zeros(n)
    thresh = np.full(n, opt.tolerance)
    cut = np.zeros(n, bool)  # the star's last position step was cut to max_step
    last_step = np.zeros((n, 2))  # each star's last position step (bisect_reversals)
    trust = np.full(n, float(opt.max_step))  # its trust radius [pixel]
    bracketed = np.zeros(n, bool)  # its last step was held by a reversal or the trust
    fitted = np.zeros(n, bool)  # the star took at least one position step (not held)
    done = 0
    bar = tqdm(sweeps, desc="fit sweeps", disable=not opt.progress, leave=False)
    for fixed in bar:
        if not fixed:
            held = None  # the positions move from here on
        steps[:] = 0.0
        for group in groups:
            group = group[active[group]]
            alone = gsize[label[group]] == 1
            step_colour(
                [(idx, fixed, None) for idx in _chunks(group[alone], opt.chunk)]
                + [(idx, fixed, label[idx]) for idx in _group_chunks(group[~alone], label, opt.chunk)]
            )  # fmt: skip
        if halo_pending:
            add_halo()
            halo_pending = False
        if window_pending:
            narrow_windows()
            window_pending = False
        if fixed:
            more_flux_passes()
        done += 0 if fixed else 1
        # converged stars rest until they or an overlapping neighbour move again
        moved = usable & (steps >= thresh)
        active = moved.copy()
        if len(pairs):
            # NB a fancy-indexed |= writes a repeated index once (its last pair wins), so a
            # star wakes by at most two of its pairs, chosen by the pairs' order. Waking it
            # by every moved neighbour (np.logical_or.at) was measured on the 1e5-star
            # frame: 47 % more star steps, +26 % fit CPU, V 24-25 scatter 130 -> 141 mpix,
            # not converged 1.34 -> 1.75 % (docs/measure-scale.md); not adopted
            active[pairs[:, 0]] |= moved[pairs[:, 1]]
            active[pairs[:, 1]] |= moved[pairs[:, 0]]
        # a group steps together: all its stars or none
        active = (np.bincount(label, active, minlength=len(gsize)) > 0)[label] & usable
        if fixed:
            active = usable.copy()
        else:
            # a star whose position was held (min_snr) has not converged: it is stepped
            # again every sweep (its flux recovers as its neighbours' models improve)
            active |= usable & ~fitted
        if not fixed and not np.any(moved):
            break
    bar.close()
    if opt.flux_refresh and done:
        moving = steps.copy()  # the last sweep's steps decide convergence, not this pass
        for group in groups:
            step_colour([(idx, True, None) for idx in _chunks(group, opt.chunk)])
        steps[:] = moving

    # final uncertainties from the (undamped) Fisher matrix at the solution
    x_err = np.full(n, np.nan)
    y_err = np.full(n, np.nan)
    f_err = np.full(n, np.nan)
    s_err = np.full(n, np.nan)
    chi2 = np.full(n, np.nan)
    chi2_odd = np.full(n, np.nan)
    crowding = np.full(n, np.nan)
    all_idx = order  # the usable stars in bands of rows (cache reuse; see the colours)
    if uncertainties or return_model or return_light:  # exact models at the solution
        work = list(_chunks(all_idx, opt.chunk))
        batch = 4 * pool.threads  # chunks evaluated at once (not all N stamps held)
        for lo in range(0, len(work), batch):
            part = work[lo : lo + batch]
            exact = pool.map(lambda i: evaluate(i, derivatives=False).reshape(len(i), -1), part)
            for idx, v in zip(part, exact):
                deposit(idx, flux[idx, None] * v)
    fisher = np.zeros((n, 4, 4))
    weight = np.zeros((n, s * s))
    next_step = np.zeros(n)  # the position step each star would take at the solution
    across = np.zeros(n)  # its part across the star's last step (bisect_reversals)
    # the position variance [px^2] per unit excess reduced chi^2 of a PSF-correlated
    # residual field on the stamp (:func:`_correlated_gain`), where a halo is
    gain = np.full((n, 2), np.nan)
    # the bright stars' halo light over all the model light on the stamp (a bright
    # star's own misfit, centro-symmetric, is not the halo's)
    halo_share = np.zeros(n)
    corr = residual_correlation(psf, nx, ny, r) if uncertainties and len(all_idx) else None

    def at_solution(idx):
        """The Fisher matrices, weights, chi^2, crowding (and halo gain and next step)
        of the stars ``idx`` at the solution: rows of their own, no sums across chunks."""
        v, dvx, dvy, a, b, w, resid = normal_equations(idx)
        fisher[idx], weight[idx] = _marginalise_slopes(a), w
        if len(halo_light):
            ok_pix = valid[idx]
            others = others_on(flat[idx], own[idx])
            light = np.sum((np.maximum(others, 0.0) + np.abs(own[idx])) * ok_pix, axis=1)
            halo_share[idx] = np.sum(
                np.maximum(halo_light[flat[idx]], 0.0) * ok_pix, axis=1
            ) / np.maximum(light, 1e-300)
            # the gain matters where a halo is (the error model scales it by the share)
            lit = np.flatnonzero(halo_share[idx] > 0)
        if len(halo_light) and len(lit):
            jac = jacobian(
                flux[idx[lit]],
                *(q.reshape(len(idx), s, s)[lit] for q in (v, dvx, dvy)),
                opt.sky_gradient,
            )
            jw = jac * (w[lit] * valid[idx[lit]])[:, None, :]
            gain[idx[lit]] = _correlated_gain(jw, a[lit], corr, npar)
        if opt.check_cut_steps:
            step = _solve(_damped(a, opt.damping), b)
            next_step[idx] = np.hypot(step[:, 0], step[:, 1])
            if opt.bisect_reversals:
                # the part across the last step: a bracketed star has its minimum along it
                unit = last_step[idx] / np.maximum(np.hypot(*last_step[idx].T), 1e-300)[:, None]
                across[idx] = np.abs(step[:, 0] * unit[:, 1] - step[:, 1] * unit[:, 0])
        dof = np.maximum(valid[idx].sum(axis=1) - npar, 1)
        chi2[idx] = np.sum(w * resid**2, axis=1) / dof
        # odd parameters: the position (and the sky slopes); flux and sky are even
        chi2_odd[idx] = odd_chi2(
            (np.sqrt(w) * resid).reshape(len(idx), s, s),
            valid[idx].reshape(len(idx), s, s),
            x[idx] - geom.cx[idx],
            y[idx] - geom.cy[idx],
            npar - 2,
        )
        crowding[idx] = _neighbour_misfit(
            w * resid**2, others_on(flat[idx], own[idx]), own[idx], valid[idx], npar
        )

    pool.map(at_solution, list(_chunks(all_idx if uncertainties else all_idx[:0], opt.chunk)))
    if uncertainties:
        separation = np.hypot(x[pairs[:, 0]] - x[pairs[:, 1]], y[pairs[:, 0]] - y[pairs[:, 1]])
        close = pairs[(separation < opt.blend_radius) & usable[pairs].all(axis=1)]
        fisher_eff = marginalise_neighbours(
            psf, fisher, weight, x, y, flux, geom, mix, close, opt.chunk, pool
        )
        cov, ok = safe_inverse(fisher_eff[all_idx])
        plain, ok_plain = safe_inverse(fisher[all_idx])
        # marginalising can only add variance; a degenerate joint fit (two stars at one
        # position) or a breakdown of the independent-neighbour sum keeps the star's own
        var, var_plain = np.einsum("nkk->nk", cov), np.einsum("nkk->nk", plain)
        keep = ~ok | ~np.all(np.isfinite(var) & (var >= var_plain * (1 - 1e-9)), axis=1)
        cov[keep] = plain[keep]
        err = np.sqrt(np.abs(np.einsum("nkk->nk", cov)))
        x_err[all_idx], y_err[all_idx], f_err[all_idx], s_err[all_idx] = err.T
        flag[all_idx[~ok_plain]] |= FLAG_FAILED
        if opt.check_cut_steps:
            # the tolerance at the solution, as step_stars takes it (own Fisher block,
            # times the neighbours' misfit)
            misfit = np.nan_to_num(crowding[all_idx], nan=1.0) if opt.chi2_tolerance else None
            final = _position_tolerance(plain, misfit, opt)
            flag[all_idx[cut[all_idx] & (next_step[all_idx] >= final)]] |= FLAG_NOT_CONVERGED
            if opt.bisect_reversals:
                off_line = bracketed[all_idx] & (across[all_idx] >= final)
                flag[all_idx[off_line]] |= FLAG_NOT_CONVERGED
    flag[usable & (steps >= thresh)] |= FLAG_NOT_CONVERGED
    failed = ~usable | ~(flux > 0)
    if done:  # positions never fitted (held by min_snr in every position step)
        failed |= ~fitted
    if uncertainties:
        failed |= ~np.isfinite(x_err) | ~(flux / f_err > opt.min_snr)
    flag[failed] |= FLAG_FAILED
    x_out = np.where(usable, x, x0)
    y_out = np.where(usable, y, y0)
    for arr in (x_err, y_err, f_err, s_err):
        arr[failed] = np.nan
    x_err[hold] = y_err[hold] = np.nan  # held, not measured
    return FitResult(
        x=x_out,
        y=y_out,
        flux=np.where(usable, flux, np.nan),
        sky=np.where(usable, sky, np.nan),
        x_err=x_err,
        y_err=y_err,
        flux_err=f_err,
        sky_err=s_err,
        chi2=chi2,
        flag=flag,
        iterations=done,
        chi2_odd=chi2_odd,
        model_image=_frame_image(_less(model, halo_light, tail_light), pixels, (ny, nx))
        if return_model
        else None,
        sky_slope=np.where(usable[:, None], slope, 0.0),
        halo_profile=measured if models_halo else None,
        crowding=crowding,
        correlated_gain=gain,
        halo_share=np.minimum(halo_share, 1.0),
        light_image=_frame_image(model, pixels, (ny, nx), np.float64, np.nan)
        if return_light
        else None,
    )


def _bisected_limit(step, last, trust, opt):
    """Each star's largest position step [pixel] with ``bisect_reversals``, and whether
    its step reverses its last one.

    A Gauss-Newton step that turns back on the star's last position step (cosine below
    :data:`REVERSAL_COSINE`) says the minimum along that line lies between the last two
    positions: the step is held to half the last step's length (bisection), and the
    star's trust radius keeps that limit until a step that keeps its direction regrows
    it. Without this a star whose chi^2 is far from quadratic over ``max_step`` (a faint
    star, or its neighbour's misfit) steps back and forth between two positions for
    ever (docs/measure-scale.md, twenty-ninth pass).

    Parameters
    ----------
    step : ndarray, shape (N, P)
        The Gauss-Newton steps, position first [pixel].
    last : ndarray, shape (N, 2)
        The stars' last position steps [pixel].
    trust : ndarray, shape (N,)
        Their trust radii [pixel].
    opt : FitOptions

    Returns
    -------
    limit : ndarray, shape (N,)
    reverse : ndarray of bool, shape (N,)
    """
    length = np.hypot(step[:, 0], step[:, 1])
    last_length = np.hypot(last[:, 0], last[:, 1])
    dot = step[:, 0] * last[:, 0] + step[:, 1] * last[:, 1]
    reverse = dot < REVERSAL_COSINE * length * last_length
    limit = np.where(reverse, np.minimum(trust, 0.5 * last_length), trust)
    return np.minimum(limit, opt.max_step), reverse


def _step_over_error(a_d: np.ndarray, step: np.ndarray, k: int) -> np.ndarray:
    """``|step_k| / sqrt((a_d^-1)_kk)``: each star's step of parameter ``k`` in units of
    its error (``a_d``: the damped normal matrices, shape (N, P, P); ``step``: (N, P))."""
    unit = np.zeros_like(step)
    unit[:, k] = 1.0
    variance = _solve(a_d, unit)[:, k]  # the diagonal element k of a_d^-1
    return np.abs(step[:, k]) / np.sqrt(np.maximum(variance, 1e-300))


def _correlated_gain(jw: np.ndarray, a: np.ndarray, corr: np.ndarray, npar: int) -> np.ndarray:
    """Position variance [pixel^2] per unit excess reduced chi^2 of a correlated field.

    A residual field on the stamp with covariance ``s^2 R`` (``R``:
    :func:`residual_correlation`) moves the fit by ``A^-1 J W r``, of covariance
    ``s^2 A^-1 B A^-1`` with ``B = J W R W J^T``. After the fit the part of the field
    that the star's parameters (position, flux, sky plane) absorb is gone from the
    residual, so it adds ``s^2 (sum W - tr(A^-1 B)) / dof`` to the reduced chi^2, not
    ``s^2 mean(W)``: a field at the PSF's scale is partly absorbed. The ratio of the two,
    per axis, is returned; times the star's excess chi^2 it is the field's position
    variance, for a field of any amplitude.

    Parameters
    ----------
    jw : ndarray, shape (N, P, M)
        Jacobian times the pixel weights (zero on unused pixels).
    a : ndarray, shape (N, P, P)
        Fisher matrices ``J W J^T`` (all parameters).
    corr : ndarray, shape (M, M)
    npar : int
        Fitted parameters per star.

    Returns
    -------
    ndarray, shape (N, 2)
        NaN where ``a`` is singular.
    """
    inv, ok = safe_inverse(a)
    b = np.matmul(np.matmul(jw, corr), jw.transpose(0, 2, 1))
    cov = np.matmul(np.matmul(inv, b), inv)
    # sum W: the weights are in jw's sky row (d m / d sky = 1)
    sum_w = jw[:, 3, :].sum(axis=1)
    npix = np.count_nonzero(jw[:, 3, :], axis=1)
    absorbed = np.einsum("nij,nji->n", inv, b)
    seen = np.maximum(sum_w - absorbed, 0.1 * sum_w)
    dof = np.maximum(npix - npar, 1)
    out = np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1) * (dof / np.maximum(seen, 1e-300))[:, None]
    out[~ok] = np.nan
    return out


def _neighbour_misfit(
    chi2_pixels: np.ndarray, others: np.ndarray, own: np.ndarray, valid: np.ndarray, npar: int
) -> np.ndarray:
    """The stamp's reduced chi^2 excess that its neighbours' light explains, plus one.

    ``1 + (chi2 - 1) q`` (at least 1), with ``chi2`` the stamp's reduced chi^2 and ``q``
    the neighbours' share of the model light on the stamp's valid pixels. A star's own
    model misfit is nearly centro-symmetric and barely moves it (a bright star's chi^2
    reaches 100-1000 on the MAVIS frames); its neighbours' mis-modelled light pulls it.
    With the whole chi^2 the bright stars stopped while still settling (V 15-17 on the
    1e5-star frame: robust scatter 1.1 -> 1.5 mpix; docs/measure-scale.md).

    Parameters
    ----------
    chi2_pixels : ndarray, shape (N, M)
        ``w r^2`` per stamp pixel (weight times residual squared).
    others, own : ndarray, shape (N, M)
        The neighbours' model (stars and halos) and the star's own on its stamp [electron].
    valid : ndarray of bool, shape (N, M)
        Pixels used.
    npar : int
        Fitted parameters per star.

    Returns
    -------
    ndarray, shape (N,)
    """
    dof = np.maximum(valid.sum(axis=1) - npar, 1)
    chi2 = np.sum(chi2_pixels, axis=1) / dof
    light_others = np.sum(np.maximum(others, 0.0) * valid, axis=1)
    light_own = np.sum(np.abs(own) * valid, axis=1)
    q = light_others / np.maximum(light_others + light_own, 1e-300)
    return np.maximum(1.0 + (chi2 - 1.0) * q, 1.0)


def _marginalise_slopes(a: np.ndarray) -> np.ndarray:
    """The (x, y, flux, sky) block of Fisher matrices with sky slopes (parameters
    4, 5) marginalised (Schur complement); 4 x 4 matrices are returned as they are."""
    if a.shape[1] == 4:
        return a
    inv, ok = safe_inverse(a[:, 4:, 4:])
    cross = a[:, :4, 4:]
    out = a[:, :4, :4] - np.einsum("nkl,nlm,npm->nkp", cross, np.nan_to_num(inv), cross)
    out[~ok] = a[~ok, :4, :4]
    return out


def _frame_image(
    values: np.ndarray,
    pixels: np.ndarray,
    shape: tuple[int, int],
    dtype=np.float32,
    fill: float = 0.0,
) -> np.ndarray:
    """Frame-shaped image (float32 by default) with ``values`` at the flat ``pixels``,
    ``fill`` elsewhere."""
    out = np.full(shape[0] * shape[1], fill, dtype=dtype)
    out[pixels] = values
    return out.reshape(shape)


def marginalise_neighbours(
    psf: VariableEPSF,
    fisher: np.ndarray,
    weight: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    geom: StampGeometry,
    mix: tuple[np.ndarray, np.ndarray],
    pairs: np.ndarray,
    chunk: int = 512,
    pool: ChunkPool | None = None,
) -> np.ndarray:
    """Fisher matrices of stars with their close neighbours' parameters marginalised.

    A star fitted with its neighbours subtracted has the per-star Fisher matrix
    ``A_ii``; but a close neighbour's position and flux are not known exactly,
    and their errors covary with the star's (a faint star 2 px from a bright one
    moves it). The joint-fit information of star i is the Schur complement
    ``A_ii - sum_j A_ij A_jj^-1 A_ji`` with ``A_ij = J_i W_i J_j^T`` on star i's
    stamp (``J_j`` the neighbour's model derivatives there, no sky term: each star
    has its own local sky) and ``A_jj`` the neighbour's own Fisher matrix. Summing
    over neighbours treats them as independent (adequate for pairs and sparse
    groups).

    Parameters
    ----------
    psf : VariableEPSF
    fisher : ndarray, shape (N, 4, 4)
        Per-star Fisher matrices.
    weight : ndarray, shape (N, S*S)
        Pixel weights of each star's stamp [1/electron^2].
    x, y, flux : ndarray, shape (N,)
        Fitted positions [pixel] and fluxes [electron].
    geom : StampGeometry
        The stars' stamps.
    mix : tuple
        ``psf.mixing(x, y)`` at the stamps' stars.
    pairs : ndarray of int, shape (P, 2)
        Close pairs (each once).
    chunk : int
    pool : ChunkPool, optional
        Runs the chunks' terms (subtracted afterwards in chunk order: the same on any
        thread count); None: one thread.

    Returns
    -------
    ndarray, shape (N, 4, 4)
    """
    out = fisher.copy()
    if len(pairs) == 0:
        return out
    both = np.concatenate([pairs, pairs[:, ::-1]])
    inv_other, ok_other = safe_inverse(fisher[both[:, 1]])

    def terms(start):
        i, j = both[start : start + chunk, 0], both[start : start + chunk, 1]
        stamps = StampGeometry(geom.cx[i], geom.cy[i], geom.radius)
        own = psf.evaluate(x[i], y[i], stamps, mix=(mix[0][i], mix[1][i]))
        other = psf.evaluate(x[j], y[j], stamps, mix=(mix[0][j], mix[1][j]))
        jac_i = jacobian(flux[i], *own)
        jac_j = jacobian(flux[j], *other)
        jac_j[:, 3] = 0.0
        cross = np.einsum("nkm,nlm,nm->nkl", jac_i, jac_j, weight[i])
        inv = np.nan_to_num(inv_other[start : start + chunk])
        term = np.einsum("nkl,nlm,npm->nkp", cross, inv, cross)
        term[~ok_other[start : start + chunk]] = 0.0
        return i, term

    starts = range(0, len(both), chunk)
    for i, term in (pool or ChunkPool(1)).map(terms, starts):
        np.add.at(out, i, -term)
    return out


def _coloured_groups(x, y, usable, pairs, opt):
    """Group label (:func:`~mavispm.measure.stars.joint_step.coupled_groups`) and colour
    (groups that share a pair differ) of each star. A function of its own so that its
    pair-sized temporaries are freed before the sweeps."""
    n = len(x)
    if opt.joint_radius <= 0:
        return np.arange(n), colour_graph(n, pairs)
    both = usable[pairs].all(axis=1)
    sep = np.hypot(x[pairs[:, 0]] - x[pairs[:, 1]], y[pairs[:, 0]] - y[pairs[:, 1]])
    label = coupled_groups(
        n, pairs[both], sep[both], opt.joint_radius, opt.joint_max, UNRESOLVED_SEPARATION
    )
    del both, sep
    links = label[pairs]
    links = np.unique(np.sort(links[links[:, 0] != links[:, 1]], axis=1), axis=0)
    return label, colour_graph(int(label.max()) + 1, links)[label]


def _group_chunks(index: np.ndarray, label: np.ndarray, size: int):
    """Chunks of about ``size`` of ``index`` (grouped by ``label``) never splitting a group."""
    if len(index) == 0:
        return
    starts = np.r_[0, np.flatnonzero(np.diff(label[index])) + 1, len(index)]
    lo = 0
    while lo < len(index):
        hi = starts[min(np.searchsorted(starts, lo + size), len(starts) - 1)]
        yield index[lo:hi]
        lo = hi


def _limit_group_steps(step, single, a, label, limit):
    """Scale each group's joint step so that its length in the stars' own metrics
    (``sum_i d_i^T A_ii d_i``) is at most ``limit`` times that of the single-star
    steps: a nearly degenerate group (two stars sharing one blob of light) would
    otherwise take a huge flux-trading step."""

    def length(d):
        return np.bincount(label - label.min(), np.abs(np.einsum("nk,nkl,nl->n", d, a, d)))

    ratio = np.sqrt(length(step) / np.maximum(length(single), 1e-300))
    factor = np.minimum(1.0, limit / np.maximum(ratio, 1e-300))
    return step * factor[label - label.min()][:, None]


def _less(model: np.ndarray, *parts: np.ndarray) -> np.ndarray:
    """``model`` less each of ``parts`` that is kept (not empty), in order: the stars' light
    without the light kept apart (the halos, the halo's smooth tail)."""
    for part in parts:
        if len(part):
            model = model - part
    return model


def _group_pairs(label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ordered pairs (i, j), i != j, of positions in ``label`` sharing a label."""
    same = label[:, None] == label[None, :]
    np.fill_diagonal(same, False)
    return np.nonzero(same)


def _damped(a: np.ndarray, damping: float) -> np.ndarray:
    """Levenberg-Marquardt normal matrices: ``a`` with ``damping`` times its diagonal added.

    Parameters
    ----------
    a : ndarray, shape (n, p, p)
    damping : float

    Returns
    -------
    ndarray, shape (n, p, p)
    """
    diag = np.einsum("nkk->nk", a)
    return a + damping * diag[:, :, None] * np.eye(a.shape[-1])


def _position_tolerance(cov: np.ndarray, misfit, opt: FitOptions) -> np.ndarray:
    """Convergence threshold [pixel] of each star's position step.

    ``max(tolerance, relative_tolerance * sigma)``, with ``sigma`` the position error
    of the covariance ``cov`` (x and y in quadrature), times ``sqrt(misfit)`` (the
    neighbours' misfit) when ``opt.chi2_tolerance``.

    Parameters
    ----------
    cov : ndarray, shape (n, p, p)
        Covariances, position first [pixel^2].
    misfit : ndarray (n,) or None
        The neighbours' misfit ratio (used with ``chi2_tolerance``).
    opt : FitOptions

    Returns
    -------
    ndarray (n,)
    """
    sigma_pos = np.sqrt(np.abs(cov[:, 0, 0]) + np.abs(cov[:, 1, 1]))
    if opt.chi2_tolerance:
        sigma_pos = sigma_pos * np.sqrt(misfit)
    return np.maximum(opt.tolerance, opt.relative_tolerance * np.nan_to_num(sigma_pos))


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve N small systems; zero step where singular or non-finite."""
    out = np.zeros_like(b)
    ok = np.all(np.isfinite(a), axis=(1, 2)) & np.all(np.isfinite(b), axis=1)
    if np.any(ok):
        try:
            out[ok] = np.linalg.solve(a[ok], b[ok][:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            inv, good = safe_inverse(a[ok])
            sol = np.einsum("nkl,nl->nk", np.nan_to_num(inv), b[ok])
            sol[~good] = 0.0
            out[ok] = sol
    out[~np.isfinite(out)] = 0.0
    return out
