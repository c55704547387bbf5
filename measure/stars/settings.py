"""Settings of the ``stars`` stage (ePSF building and PSF fitting).

:class:`MeasureSettings` holds the method (engine, ePSF variation model, error
model, forced or blind positions, flags); its ``knobs`` (:class:`MeasureKnobs`,
GalSim's GSParams pattern, TOML table ``[measure.knobs]``) hold every accuracy
and speed knob, each with a default that reaches the Cramer-Rao bound on the
shipped scenes (docs/measure.md). Build them from a TOML table with
:func:`mavispm.measure.stars.cli.validate_settings`, which also takes the knobs
as top-level keys of the table (the older flat form).

Example
-------
>>> from mavispm.measure.stars.cli import validate_settings
>>> s = validate_settings({"psf_variation": "constant", "knobs": {"epsf_iterations": 4}})
>>> s.knobs.epsf_iterations, s.epsf_iterations, s.knobs.stamp_radius
(4, 4, 5)
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field, fields
from typing import Literal

from mavispm.core.config import unit_field
from mavispm.core.errors import ConfigError

__all__ = [
    "KNOB_NAMES",
    "MeasureKnobs",
    "MeasureSettings",
    "nest_knobs",
]

#: Names of the accuracy/speed knobs (fields of :class:`MeasureKnobs`).
KNOB_NAMES: tuple[str, ...] = ()


@dataclass(frozen=True)
class MeasureKnobs:
    """Accuracy and speed knobs of the ``stars`` stage (``[measure.knobs]``).

    None of them changes what is measured, only how well and how fast; the
    defaults are the documented accuracy/speed trade-off (docs/measure.md).

    Parameters
    ----------
    oversampling : int or "auto"
        ePSF oversampling factor; "auto" (default): 4 with at least 600
        PSF stars used per ePSF node (after the ``psf_stars_per_node`` cap), else 2
        (:func:`mavispm.measure.stars.epsf.resolve_oversampling`).
    epsf_size : int
        ePSF footprint [pixel] (odd).
    epsf_iterations : int
        ePSF builder iterations.
    epsf_builder : {"fast", "photutils"}
        Our vectorised residual-stacking builder or photutils' EPSFBuilder
        (about 100x slower; cross-check).
    psf_stars_per_node : int
        Cap on the PSF stars per ePSF grid node (the brightest of its cell).
    psf_star_isolation : float [pix]
        Isolation radius of PSF stars.
    psf_star_sky_mesh : float [pix]
        In the isolation test a neighbour is rated by its 5 x 5 box flux over the larger
        of two backgrounds: its own local one (the ring 6-8 px around it) and the frame's
        background from a mesh of this block size
        (:func:`~mavispm.measure.stars.sky_mesh.mesh_sky`): the ring alone can be
        raised by the bright candidate next to it. 0: the frame's global sky instead of
        the mesh (before 2026-12-03: on the 1e5-star frame the unresolved crowd's light
        made a V 24-26 neighbour read ~7.5 x its flux and the 12-px isolation left 1,132
        PSF stars; docs/measure-scale.md, twentieth pass).
    psfr_star_isolation : float [pix]
        Isolation radius of the PSF-R model's PSF stars (``psf_star_isolation`` stays the
        frame-built ePSF's, whose cut-outs are ``epsf_size`` wide): the kernel and position
        fits of the PSF-R build see only the stars' fit stamps (``stamp_radius``). 8 px (12
        before 2026-12-03): on the 1e5-star frame 5,752 PSF stars instead of 1,964, enough
        for the 5 x 5 correction grid (docs/measure-scale.md, twentieth pass).
    psf_star_min_snr : float
        Minimum flux SNR of PSF stars.
    psf_star_max_gradient : float
        Largest background gradient across a PSF star's cut-out (centre to edge,
        relative to its flux; :func:`mavispm.measure.stars.epsf.background_gradient`):
        stars in the wings of much brighter stars are not PSF stars. 0: no test.
    neighbour_passes : int
        Times the ePSF is rebuilt after subtracting fitted neighbours (0 = none).
    psf_star_neighbour_ratio : float
        In those rebuilds, PSF stars may have neighbours within ``psf_star_isolation``
        up to this fraction of their flux (the first build: 0.01). With 1.0 (before
        2026-12-02) a neighbour as bright as the star, subtracted with the first ePSF,
        left its residual in a few PSF stars of a node and moved that node's ePSF by
        up to 0.024 px: the bright stars of the peer benchmark's frame were at 3.6 x
        CRLB (V 16-18), with 0.1 at 1.8 x; the NGC 3201 frame without prior at 6.1 /
        3.9 x (V 17-20). Where the stars it allows cannot fill ``min(psf_stars_per_node,
        50)`` per node, neighbours up to as bright as the star are allowed
        (:data:`mavispm.measure.stars.epsf.MIN_CLEAN_PER_NODE`; docs/measure.md, "Error
        model of the frame-built ePSF").
    psfr_grid : int or "auto"
        Nodes per axis of the PSF-R model's correction kernels (``psf_grid`` stays the
        frame-built ePSF's grid and the error model's cells). Each node's kernel is fitted
        to its ``psf_stars_per_node x (3 / psfr_grid)^2`` nearest PSF stars (the 3 x 3
        grid's total). "auto" (default): 5 when every node's stars lie within half a
        node spacing of it, else 3 (:func:`~mavispm.measure.stars.measure_frame.psfr_grid_for`;
        docs/measure-scale.md, twentieth pass).
    stamp_radius : int
        Fit stamp half-width [pixel].
    iterations : int
        Maximum fitter sweeps (converged stars rest: more sweeps cost only the stars
        still moving; 10 left 12.7 % of the V < 25 stars of the 1e5-star frame
        unconverged, 40 leave 3.8 %; docs/measure-scale.md).
    tolerance : float [pix]
        Convergence threshold on position steps.
    relative_tolerance : float
        ... or this fraction of the star's position error (0.2: on the 3e4 / 1e5-star
        NGC 3201 frames the unconverged stars fall from 6.5 / 22.5 % with 0.05 to
        4.3 / 14.4 %, the scatter unchanged; docs/measure-scale.md).
    chi2_tolerance : bool
        That position error is inflated by the stamp's misfit that the neighbours' light
        explains (:class:`~mavispm.measure.stars.batched_fit.FitOptions`): on the
        1e5-star frame the V < 25 stars unconverged fall from 3.7 % to 1.3 % and those
        ending > 1 px from the truth while called converged from 4.7 % to 1.9 %
        (docs/measure-scale.md).
    flux_refresh : bool
        After the last sweep, one pass at fixed positions refits every star's flux and
        sky against its neighbours' final models.
    flux_passes : int
        The fast engine's passes at fixed positions before the first position step, at
        most (after the first, every star again, then only those whose flux still moves
        by ``relative_tolerance`` of its error, and their neighbours): the first pass
        sees neither the halos nor the fluxes of the neighbours fitted after the star
        (:class:`~mavispm.measure.stars.batched_fit.FitOptions`). On the 1e5-star frame
        failed / not converged at V < 25 go from 1.71 / 3.85 % (one pass) to 1.70 / 1.80
        %, the scatter 3-8 % lower at V 20-26 (docs/measure-scale.md, twelfth pass).
    crowded_window : int
        Half-width of the fitting window of a crowded star (0: the whole stamp): one
        whose own light on its stamp outside it is below ``crowded_ratio`` times its
        neighbours' there (:class:`~mavispm.measure.stars.batched_fit.FitOptions`). On
        the 1e5-star frame failed / not converged at V < 25 2.02 / 4.55 -> 1.78 / 4.24 %,
        the V 22-26 scatter 6-9 % lower; 1e4 and 3e4 as good or better (3: 1.66 / 4.00
        %, 10-17 %, but 12 % more scatter on the misfit crowd of
        ``tests/test_measure_crowded_convergence.py``; docs/measure-scale.md).
    crowded_ratio : float
        That light ratio.
    check_cut_steps : bool
        A star whose last position step was cut by the trust region (0.5 px) is flagged
        not converged (1) when the step it would take at the solution exceeds its
        tolerance there (:class:`~mavispm.measure.stars.batched_fit.FitOptions`): on the
        1e5-star frame 2.9 % of the V < 25 stars were called converged after one cut
        step, 6.7 x their error from the truth (docs/measure-scale.md). A last step
        held back by ``max_shift`` counts as cut (since 2026-12-03: 1.05 % of the V < 25
        stars rested at the clamp called converged; docs/measure-scale.md, thirteenth pass).
    bisect_reversals : bool
        A star whose position step turns back on its last one takes at most half that
        step (its trust radius shrinks; bisection), and such a bracketed step counts as
        converged when below its tolerance
        (:class:`~mavispm.measure.stars.batched_fit.FitOptions`): on the 1e5-star frame
        152 of the V < 25 stars flagged 1 stepped back and forth between two positions
        in every sweep; with it not converged 1.74 -> 1.50 % (docs/measure-scale.md,
        twenty-ninth pass). False: the fitter before 2026-12-04.
    max_shift : float [pix]
        Largest allowed move from the forced position.
    wing_threshold : float
        The fast engine puts the light of stars outside their fit stamps (a radial
        profile measured on the frame around its brightest stars, out to
        ``halo_radius``) into the model their neighbours see, for stars where
        it peaks above this many times the sky's pixel noise; 0: off
        (:mod:`mavispm.measure.stars.halo`; docs/measure-scale.md).
    halo_radius : float [pix]
        Outer radius of that light.
    halo_rings : float
        Stars whose halo at 20 px exceeds this many times the sky's pixel noise (1000:
        V < 15 on the MAVIS frames) get
        their own radial correction, the residual's medians in 1-px annuli out to 30
        px after the first pass (docs/measure-scale.md, eleventh pass); 0: off.
    halo_field_radial : bool
        PSF-R model: the halo's maps also carry the prior's radial variation over the
        field (each star's own profile, not only its shape;
        :func:`~mavispm.measure.stars.halo_shape.prior_halo_shape`; docs/measure-scale.md,
        thirteenth pass).
    halo_stack : float [pix]
        With ``halo_rings``: half-width of a 2-D map of the ring stars' common non-round
        misfit (the median over them of the residual per unit flux by pixel offset, their
        ring medians taken out), measured with the rings and added around the stars of
        ``halo_stack_stars``; 0: off. 45 px: on the 1e5-star MAVIS frame two random
        halves of the V < 15 stars give maps that correlate 0.85-0.97 out to 45 px and
        0.42 beyond; maps of 20 / 45 / 60 px onto the V < 15 stars gave 4.18 / 4.09 /
        4.11 % failed or not converged at V < 25 (4.22 % without; docs/measure-scale.md,
        sixteenth pass).
    halo_stack_stars : float
        The stars whose halo at 20 px exceeds this many times the sky's pixel noise get
        that map (0: every star with a halo). 20 (5,028 stars at 1e5, V < ~18.5): the
        failures of every star with a halo (4.06 against 4.08 %) and their V 22-25
        scatter within 0.4 %, without the ~6-8 s of CPU of a deposit around ~32,000 stars.
    halo_tail : float [pix]
        The halo past ``halo_radius`` continued as a seeing halo, ``A r^(-11/3)`` (the
        Kolmogorov slope past the AO control radius, which the light at 60-100 px of the
        1e5-star MAVIS frame follows), its amplitude fitted to the profile's last 12 px,
        out to this radius, added at once by FFT; 0: off. 150 px: there a V 12 star's tail
        curves by about the sky's pixel noise across a stamp; at 1e5 failed or not
        converged at V < 25 3.66 % against 4.06 % without (fit alone), 150 and 250 px the
        same within 0.01 point (docs/measure-scale.md, seventeenth pass).
    halo_background : float [pix]
        The frame's halo profile is measured out to this radius, against the median of
        the annulus ``[halo_background, halo_background + 10)`` (its zero point), and kept
        out to ``halo_radius`` for each star's own deposit, the rest for the tail's fit;
        at most ``halo_radius`` (0, the default): the background annulus just past
        ``halo_radius``. On the 1e5-star MAVIS frame a V < 15 star's light at 60-70 px is
        still ~80 % of that at 59 px, and the default profile (with its tail) is 76-89 % of
        the rendered light at 15-40 px and 34-46 % at 50-60 px; with 120 px and
        ``halo_saturated`` it is 95-100 % at 8-70 px, but the failed / not-converged
        fractions move by < 0.1 point (docs/measure-scale.md, twenty-sixth pass: not
        the default). Must lie inside ``halo_tail``.
    halo_saturated : bool
        The halo profile is also measured around saturated stars (their pixels left
        out; their fitted fluxes scale it), the stars whose halo it models; False (the
        default): the unsaturated ones only (on the 1e5-star MAVIS frame V 15-16.7, too
        faint to show their halo beyond ~40 px above the crowd).
    halo_map : float [pix]
        With ``halo_rings``: each ring star's own 2-D misfit out to this radius (block
        medians of its residual after the first pass, interpolated) added to its halo;
        0 (the default): none (docs/measure-scale.md, twenty-seventh pass).
    halo_map_block : int [pix]
        Side of those median blocks (odd); with ``halo_map_arc`` the polar bins' radial
        length.
    halo_map_arc : float [pix]
        If > 0: polar bins this wide in azimuth instead of square blocks.
    halo_map_core : int [pix]
        If > 0: the ``(2 halo_map_core + 1)^2`` px around every star are left out of the
        residual the maps are measured on.
    min_snr : float
        Stars below this flux SNR have positions held fixed and are flagged 32.
    rescue_radius : float [pix]
        If > 0: after the fit, each star flagged 1 or 32 with a neighbour within this
        distance is refitted with those neighbours (positions, fluxes, a sky plane)
        from several starts, and keeps the result only when it converges, reaches
        ``min_snr`` and lowers the stamp's chi^2 by at least 9 against the group
        without it (:mod:`~mavispm.measure.stars.rescue`); 0 (default): off.
    chunk : int
        Stars evaluated at once by the fast engine (memory knob).
    threads : int
        Threads of the fast engine's chunks (each colour's, the uncertainties', the
        neighbour marginalisation's) and of the ePSF error model's; 0 (default): every
        core this process may use. The results are the same bit for bit on any number
        (:mod:`mavispm.measure.stars.chunk_pool`).
    photutils_fitter : {"levmar", "default"}
        Fitter of the photutils engine.
    group_separation : float [pix]
        Grouping distance of the photutils engine.
    """

    oversampling: int | Literal["auto"] = "auto"
    epsf_size: int = 25
    epsf_iterations: int = 10
    epsf_builder: Literal["fast", "photutils"] = "fast"
    psf_stars_per_node: int = 150
    psf_star_isolation: float = unit_field(12.0, "pix")
    psf_star_sky_mesh: float = unit_field(32.0, "pix")
    psfr_star_isolation: float = unit_field(8.0, "pix")
    psf_star_min_snr: float = 100.0
    psf_star_max_gradient: float = 0.01
    neighbour_passes: int = 1
    psf_star_neighbour_ratio: float = 0.1
    psfr_grid: int | Literal["auto"] = "auto"
    stamp_radius: int = 5
    iterations: int = 40
    tolerance: float = unit_field(1e-4, "pix")
    relative_tolerance: float = 0.2
    chi2_tolerance: bool = True
    flux_refresh: bool = True
    flux_passes: int = 5
    check_cut_steps: bool = True
    bisect_reversals: bool = True
    crowded_window: int = 4
    crowded_ratio: float = 0.05
    max_shift: float = unit_field(2.0, "pix")
    wing_threshold: float = 3.0
    halo_radius: float = unit_field(60.0, "pix")
    halo_rings: float = 1000.0
    halo_field_radial: bool = True
    halo_stack: float = unit_field(45.0, "pix")
    halo_stack_stars: float = 20.0
    halo_tail: float = unit_field(150.0, "pix")
    halo_background: float = unit_field(0.0, "pix")
    halo_saturated: bool = False
    halo_map: float = unit_field(0.0, "pix")
    halo_map_block: int = 5
    halo_map_arc: float = unit_field(0.0, "pix")
    halo_map_core: int = 0
    min_snr: float = 3.0
    rescue_radius: float = unit_field(0.0, "pix")
    chunk: int = 512
    threads: int = 0
    photutils_fitter: Literal["levmar", "default"] = "levmar"
    group_separation: float = unit_field(8.0, "pix")

    def __post_init__(self):
        positive_ints = {
            "oversampling": 1 if self.oversampling == "auto" else self.oversampling,
            "psfr_grid": 1 if self.psfr_grid == "auto" else self.psfr_grid,
            "epsf_iterations": self.epsf_iterations,
            "psf_stars_per_node": self.psf_stars_per_node,
            "stamp_radius": self.stamp_radius,
            "iterations": self.iterations,
            "flux_passes": self.flux_passes,
            "chunk": self.chunk,
        }
        for key, value in positive_ints.items():
            if value < 1:
                raise ConfigError(f"must be a positive integer, got {value}", key=f"knobs.{key}")
        if self.epsf_size < 5 or self.epsf_size % 2 == 0:
            raise ConfigError(
                f"must be an odd integer >= 5, got {self.epsf_size}", key="knobs.epsf_size"
            )
        if self.threads < 0:
            raise ConfigError(
                f"must be >= 0 (0: every core), got {self.threads}", key="knobs.threads"
            )
        if self.halo_map_block < 1 or self.halo_map_block % 2 == 0:
            raise ConfigError(
                f"must be an odd integer >= 1, got {self.halo_map_block}",
                key="knobs.halo_map_block",
            )
        if self.halo_map_core < 0:
            raise ConfigError("must be >= 0", key="knobs.halo_map_core")
        if self.neighbour_passes < 0:
            raise ConfigError("must be >= 0", key="knobs.neighbour_passes")
        for key in (
            "max_shift",
            "tolerance",
            "relative_tolerance",
            "group_separation",
            "psf_star_neighbour_ratio",
        ):
            if not getattr(self, key) > 0:
                raise ConfigError(f"must be > 0, got {getattr(self, key)}", key=f"knobs.{key}")
        for key in (
            "min_snr",
            "rescue_radius",
            "psf_star_max_gradient",
            "psf_star_sky_mesh",
            "wing_threshold",
            "halo_radius",
            "halo_rings",
            "halo_stack",
            "halo_stack_stars",
            "halo_tail",
            "halo_background",
            "halo_map",
            "halo_map_arc",
            "crowded_window",
            "crowded_ratio",
        ):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"must be >= 0, got {getattr(self, key)}", key=f"knobs.{key}")


KNOB_NAMES = tuple(f.name for f in fields(MeasureKnobs))


@dataclass(frozen=True)
class MeasureSettings:
    """Settings of ``mavispm measure stars``: the method, and its knobs.

    Parameters
    ----------
    engine : {"fast", "photutils"}
        "fast": the batched Gauss-Newton fitter; "photutils": PSFPhotometry.
    psf_variation : {"constant", "grid", "polynomial"}
        ePSF field variation model.
    psf_grid : int
        ePSF grid nodes per axis (also the sampling of a polynomial ePSF).
    psf_poly_order : int
        Order of the polynomial ePSF (3: DAOPhot's cubically variable PSF).
    error_model : {"epsf", "fisher"}
        Reported errors: "epsf" (default) adds the ePSF model error measured
        from two half-set ePSFs and inflates by the fit chi^2
        (:mod:`mavispm.measure.stars.error_model`); "fisher": the Fisher (Cramér-Rao)
        errors alone. The Fisher errors are always in ``x_err_fisher`` etc.
    sky_gradient : bool
        Fast engine: fit each star's local sky as a plane instead of a constant
        (the wings of a much brighter star tilt the background of its stamp).
    perturbation : float [pix]
        Gaussian perturbation (sigma per axis) of the forced starting positions.
    forced_positions : {"rendered", "catalogue"}
        Start from the truth's rendered ``x_pix, y_pix`` or from its catalogue
        ``x_cat, y_cat`` (before distortion). Used by a first epoch, and by every
        epoch when ``later_epochs = "truth"``.
    later_epochs : {"measured", "truth"}
        How an epoch after the first starts when the stage is given the earlier
        epochs' measured products. "measured" (default, observer mode): from the
        earlier epochs' measured positions moved into this frame by a transform
        fitted on bright stars (:mod:`mavispm.measure.stars.start_list`); no truth
        enters. "truth": from the true positions at this epoch (the paper's
        truth-forced mode; the proper motion is already in the starting point).
    refine_start : bool
        Observer mode: refine the carried start list by one quick measurement
        before the ePSF is built (:func:`mavispm.measure.stars.measure_frame.refined_start`).
    epsf_anchor : {"earlier", "start"}
        Observer mode: what fixes a later epoch's ePSF. "earlier" (default): the
        earlier epoch's ePSF (read from its product) refines the carried start
        list, and every node ePSF is shifted onto it at the same place on the sky
        (:mod:`mavispm.measure.stars.epsf_anchor`): the carried positions, off by
        the stars' own motions, no longer enter the measured positions. "start"
        (the method before): a quick ePSF built on the carried positions refines
        them and each node ePSF is centred on its PSF stars' mean start (as at
        the first epoch, where the start is the input list). An earlier product
        without an ePSF falls back to "start".
    epsf_centring : {"all", "psf_stars"}
        What centres each node of a frame-built ePSF. "all" (default): after the
        fit, every well-measured star near the node, weighted by the node's
        interpolation weight and its Fisher and start-position errors
        (:mod:`mavispm.measure.stars.node_centring`), against the start list of a
        first epoch (blind or forced) or, at a later epoch in observer mode, the start
        refined on the frame with the earlier epoch's ePSF (``refine_start`` with
        ``epsf_anchor = "earlier"``; a carried start not refined so holds the
        motions and is not used). "psf_stars" (the method before): the mean start
        position of the node's PSF stars only.
    match_radius : float [pix]
        Truth cross-match distance cut.
    crowding_radius : float [pix]
        A neighbour closer than this ...
    crowding_ratio : float
        ... and at least this fraction as bright flags a star as crowded (8).
    blind : bool
        Detect sources instead of using the truth list (forced positions).
    detection_threshold : float
        Detection threshold [background sigma] in blind mode.
    detection_fwhm : float [pix]
        Finder FWHM (blind mode); 0 uses 2.5 pixels.
    detection_method : {"psf", "daofind"}
        Blind mode: "psf" (default) finds, fits and subtracts stars and detects
        again on the residuals, rejecting PSF structure around bright stars
        (:mod:`mavispm.measure.stars.psf_detection`); "daofind": one
        ``DAOStarFinder`` pass (many false detections in PSF wings).
    detection_passes : int
        Fit-subtract-detect passes of the "psf" detector.
    detection_model_error : float
        Fractional ePSF model error of the "psf" detector: a candidate must be
        significant against this fraction of its neighbours' model light too.
    detection_wing_radius : float [pix]
        Outer radius of the structured PSF wing (speckles, the AO control-radius
        ring) beyond the ePSF footprint that the "psf" detector measures on the
        bright stars' residuals and counts as their neighbours' model error; 0: off.
    psf_model : {"auto", "epsf", "psfr"}
        "epsf": the empirical ePSF built from the frame's PSF stars (``epsf_builder``);
        "psfr": the AO PSF-reconstruction prior ``psf_prior`` (a ``psfgrid`` product,
        width degraded by ``psfr_width_error``) convolved with a Gaussian kernel fitted
        per ePSF node to the frame's PSF stars
        (:mod:`mavispm.measure.stars.psf_reconstruction`); "auto" (default): "psfr"
        when a prior is given (a workflow gives its scene's optics product), else "epsf".
    psf_prior : str
        The ``psfgrid`` product of the PSF-R prior (needed with ``psf_model = "psfr"``;
        a workflow passes its scene's optics product).
    psfr_width_error : float
        Fractional width error given to the PSF-R prior (its PSFs are stretched by
        ``1 + psfr_width_error``): an observer's reconstruction is not the true PSF.
    psfr_strehl_error : float
        Strehl error given to the PSF-R prior: this fraction of each PSF's light is
        moved into a copy blurred by 15 mas (a misfit no stretch and Gaussian kernel
        undo exactly).
    psfr_model_error : float
        PSF-R model: the fraction ``beta`` of the typical excess chi^2 at a star's flux
        that enters its position error as a model-error floor,
        ``beta sigma_F^2 max(chi2_typ(F) - 1, 0)``
        (:func:`mavispm.measure.stars.error_model.estimate_error_model`). Default 0:
        with the prior's stretch fitted, the five full NGC 3201 frames of
        docs/measure.md need no floor (0.01 made the tip-tilt scene's V 17-20 errors
        20 % too large).
    correlated_misfit : bool
        The position errors also hold the bright stars' mis-modelled light on the stamp as
        a residual field at the PSF's scale (``gain max(chi2 - chi2_typ(F) - s(F), 0) h``, ``h``
        the halo's share of the model light on the stamp; fast engine only;
        :func:`mavispm.measure.stars.error_model.estimate_error_model`). False: the chi^2
        ratio alone (before 2026-12-03: the stars within 60 px of a V < 15 star on the
        1e5-star frame had errors ~7x too small; docs/measure-scale.md, fourteenth pass).
    progress : bool
        Show progress bars.
    knobs : MeasureKnobs
        Accuracy and speed knobs; also readable as attributes of the settings
        (``settings.stamp_radius`` is ``settings.knobs.stamp_radius``).
    """

    engine: Literal["fast", "photutils"] = "fast"
    psf_variation: Literal["constant", "grid", "polynomial"] = "grid"
    psf_grid: int = 3
    psf_poly_order: int = 2
    error_model: Literal["epsf", "fisher"] = "epsf"
    sky_gradient: bool = True
    perturbation: float = unit_field(0.0, "pix")
    forced_positions: Literal["rendered", "catalogue"] = "rendered"
    later_epochs: Literal["measured", "truth"] = "measured"
    refine_start: bool = True
    epsf_anchor: Literal["earlier", "start"] = "earlier"
    epsf_centring: Literal["all", "psf_stars"] = "all"
    match_radius: float = unit_field(2.0, "pix")
    crowding_radius: float = unit_field(10.0, "pix")
    crowding_ratio: float = 0.1
    blind: bool = False
    detection_threshold: float = 5.0
    detection_fwhm: float = unit_field(0.0, "pix")
    detection_method: Literal["psf", "daofind"] = "psf"
    detection_passes: int = 3
    detection_model_error: float = 0.03
    detection_wing_radius: float = unit_field(48.0, "pix")
    psf_model: Literal["auto", "epsf", "psfr"] = "auto"
    psf_prior: str = ""
    psfr_width_error: float = 0.03
    psfr_model_error: float = 0.0
    correlated_misfit: bool = True
    psfr_strehl_error: float = 0.0
    progress: bool = field(default=False)
    knobs: MeasureKnobs = field(default_factory=MeasureKnobs)

    def replace(self, **changes) -> MeasureSettings:
        """A copy with ``changes`` applied; knob names go into :attr:`knobs`.

        Parameters
        ----------
        **changes
            Method settings and knobs by name (``neighbour_passes=0, progress=False``).

        Returns
        -------
        MeasureSettings
        """
        knobs = {k: changes.pop(k) for k in list(changes) if k in KNOB_NAMES}
        if knobs:
            changes["knobs"] = dataclasses.replace(self.knobs, **knobs)
        return dataclasses.replace(self, **changes)

    @property
    def uses_psfr(self) -> bool:
        """Whether the PSF-R model is used (``psf_model``, resolving "auto")."""
        return self.psf_model == "psfr" or (self.psf_model == "auto" and bool(self.psf_prior))

    def __getattr__(self, name):
        # only called when normal lookup fails: the knobs read as settings attributes
        if name in KNOB_NAMES:
            return getattr(self.knobs, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __post_init__(self):
        for key in ("psf_grid", "detection_passes"):
            if getattr(self, key) < 1:
                raise ConfigError(f"must be a positive integer, got {getattr(self, key)}", key=key)
        if not 0 <= self.psf_poly_order <= 5:
            raise ConfigError(f"must be 0..5, got {self.psf_poly_order}", key="psf_poly_order")
        nterms = (self.psf_poly_order + 1) * (self.psf_poly_order + 2) // 2
        if self.psf_variation == "polynomial" and self.psf_grid**2 < nterms:
            raise ConfigError(
                f"a polynomial ePSF of order {self.psf_poly_order} needs psf_grid**2 >= {nterms}",
                key="psf_grid",
            )
        if not self.psfr_model_error >= 0:
            raise ConfigError(f"must be >= 0, got {self.psfr_model_error}", key="psfr_model_error")
        if not 0 <= self.psfr_strehl_error < 1:
            raise ConfigError(
                f"must be in [0, 1), got {self.psfr_strehl_error}", key="psfr_strehl_error"
            )
        if not -0.5 < self.psfr_width_error < 0.5:
            raise ConfigError(
                f"must be in (-0.5, 0.5), got {self.psfr_width_error}", key="psfr_width_error"
            )
        for key in ("match_radius", "crowding_radius"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"must be > 0, got {getattr(self, key)}", key=key)
        for key in (
            "perturbation",
            "detection_fwhm",
            "crowding_ratio",
            "detection_model_error",
            "detection_wing_radius",
        ):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"must be >= 0, got {getattr(self, key)}", key=key)


def nest_knobs(mapping, source=None) -> dict:
    """A ``[measure]`` table with its top-level knob keys moved into ``knobs``.

    Parameters
    ----------
    mapping : mapping or None
        The TOML table; knobs may be given flat (``epsf_iterations = 4``) or in
        ``knobs`` (``[measure.knobs]``), not both for the same key.
    source : str, optional
        File name for messages.

    Returns
    -------
    dict

    Raises
    ------
    ConfigError
        A knob given both ways.
    """
    out = dict(mapping or {})
    knobs = dict(out.get("knobs") or {})
    for name in KNOB_NAMES:
        if name in out:
            if name in knobs:
                raise ConfigError(
                    "given both flat and in [knobs]; keep one", key=name, source=source
                )
            knobs[name] = out.pop(name)
    known = {f.name for f in fields(MeasureSettings)}
    for key in out:
        close = difflib.get_close_matches(key, KNOB_NAMES, n=1, cutoff=0.8)
        if key not in known and close:
            raise ConfigError(f"unknown key; did you mean '{close[0]}'?", key=key, source=source)
    if knobs or "knobs" in out:
        out["knobs"] = knobs
    return out
