"""Convergence of the batched fitter on a small crowded frame, scored against the truth.

An independent synthetic frame (``measure_helpers``: exact pixel-integrated Gaussian
PSF, Poisson and read noise) with the density of the 1e5-star MAVIS frame (6.25e-3
stars per pixel^2, 2.4 neighbours within a stamp width). Given enough sweeps the
fitter converges for nearly all stars brighter than m = 23 and the converged stars
are measured honestly (positions at the Cramér-Rao bound, fluxes within their
errors). With 10 sweeps and a tolerance of 5 % of the position error about 9 % of
them are still moving (block Gauss-Seidel converges slowly in tight groups;
docs/measure-scale.md); 60 sweeps converge them, and so do 15 with the stage's
default tolerance of 20 % (``relative_tolerance``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from measure_helpers import (
    Detector,
    SynthPSF,
    mag_to_flux,
    noisy_frame,
    render_image,
    robust_sigma,
    true_epsf,
)

from mavispm.measure.stars.batched_fit import FLAG_FAILED, FLAG_NOT_CONVERGED, FitOptions, fit_stars
from mavispm.measure.stars.cli import validate_settings
from mavispm.measure.stars.crlb import crlb
from mavispm.measure.stars.measure_frame import fit_options

SHAPE = (160, 160)
PSF = SynthPSF(1.0)
DET = Detector(saturation=1e9)
RN2 = DET.read_noise**2 * DET.nexp


def _frame(seed, n=160):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(6, SHAPE[1] - 7, n), rng.uniform(6, SHAPE[0] - 7, n)
    mag = rng.uniform(17, 25, n)
    image, sat = noisy_frame(render_image(SHAPE, x, y, mag_to_flux(mag), PSF), DET, rng)
    return image * DET.gain, sat, x, y, mag


@pytest.mark.parametrize("iterations, tolerance", [(60, 0.05), (15, 0.2)])
def test_crowded_frame_converges_and_converged_stars_are_honest(iterations, tolerance):
    psf = true_epsf(PSF, SHAPE)
    bad, failed, pos, flux_res = 0, 0, [], []
    total = 0
    for seed in range(3):
        image, sat, x, y, mag = _frame(seed)
        fit = fit_stars(
            image,
            psf,
            x,
            y,
            read_noise_var=RN2,
            sky0=DET.sky,
            saturated=sat,
            options=FitOptions(iterations=iterations, relative_tolerance=tolerance),
        )
        bright = mag < 23
        total += bright.sum()
        bad += np.sum((fit.flag[bright] & (FLAG_FAILED | FLAG_NOT_CONVERGED)) > 0)
        failed += np.sum((fit.flag[bright] & FLAG_FAILED) > 0)
        good = bright & (fit.flag & (FLAG_FAILED | FLAG_NOT_CONVERGED) == 0)
        bound = crlb(psf, x[good], y[good], mag_to_flux(mag[good]), DET.sky, RN2)
        pos.append(
            np.r_[(fit.x[good] - x[good]) / bound[:, 0], (fit.y[good] - y[good]) / bound[:, 1]]
        )
        flux_res.append((fit.flux[good] - mag_to_flux(mag[good])) / fit.flux_err[good])
    assert failed / total <= 0.01
    assert bad / total <= 0.02
    # crowding costs some accuracy, never a factor (isolated stars: 1.0)
    assert robust_sigma(np.concatenate(pos)) <= 1.25
    assert 0.8 <= robust_sigma(np.concatenate(flux_res)) <= 1.25


# --- started off the truth: a fit that stops early must fail --------------------------

START_OFFSET = 0.3  # [pixel]: about ten years of a 2 mas/yr motion at 7.4 mas/px


@pytest.fixture(scope="module")
def started_off_frames():
    """:func:`started_off`, once per module."""
    return started_off()


def started_off():
    """The crowded frames above with every star started 0.3 px off its true position,
    in a random direction (a later epoch starts from the earlier epoch's positions)."""
    out = []
    for seed in range(3):
        image, sat, x, y, mag = _frame(seed)
        angle = np.random.default_rng(100 + seed).uniform(0, 2 * np.pi, len(x))
        out.append(
            (
                image,
                sat,
                x,
                y,
                mag,
                x + START_OFFSET * np.cos(angle),
                y + START_OFFSET * np.sin(angle),
            )
        )
    return out


def _started_off_score(frames, options):
    """Robust std of (fit - truth) / CRLB over the stars with m < 23 that claim to have
    converged (flags 1 and 32 clear), and the fraction of those stars flagged 1."""
    psf = true_epsf(PSF, SHAPE)
    pos, unconverged, total = [], 0, 0
    for image, sat, x, y, mag, x0, y0 in frames:
        fit = fit_stars(
            image, psf, x0, y0, read_noise_var=RN2, sky0=DET.sky, saturated=sat,
            options=options, return_model=False,
        )  # fmt: skip
        bright = mag < 23
        total += bright.sum()
        unconverged += np.sum((fit.flag[bright] & FLAG_NOT_CONVERGED) > 0)
        good = bright & (fit.flag & (FLAG_FAILED | FLAG_NOT_CONVERGED) == 0)
        bound = crlb(psf, x[good], y[good], mag_to_flux(mag[good]), DET.sky, RN2)
        pos.append(
            np.r_[(fit.x[good] - x[good]) / bound[:, 0], (fit.y[good] - y[good]) / bound[:, 1]]
        )
    return robust_sigma(np.concatenate(pos)), unconverged / total


def _reaches_truth(score):
    """Converged stars at the Cramér-Rao bound (1.0 for isolated stars; the stage's sky
    plane and crowding cost ~8 % here) and few stars still moving."""
    spread, unconverged = score
    return spread <= 1.12 and unconverged <= 0.05


def test_started_off_crowded_frame_reaches_the_truth(started_off_frames):
    """The stage's fitter, started 0.3 px (~6-15 CRLB) off the truth on the crowded
    frame, ends at the Cramér-Rao bound (measured 2026-12-02: 1.09 robust, 3 %
    flagged 1 with 10 sweeps; 1.25 with 2 sweeps)."""
    options = fit_options(validate_settings({}))
    score = _started_off_score(started_off_frames, options)
    assert _reaches_truth(score), score


@pytest.mark.parametrize("change", [{"iterations": 3}, {"relative_tolerance": 2.0}])
def test_started_off_check_fails_a_fit_that_stops_early(started_off_frames, change):
    """The check above fails for a fit capped at 3 sweeps and for one that calls a star
    converged while its step is still 2 sigma (measured: 1.18 and 1.16)."""
    options = dataclasses.replace(fit_options(validate_settings({})), **change)
    score = _started_off_score(started_off_frames, options)
    assert not _reaches_truth(score), score


#: An ePSF 8 % narrower than the stars: every star's model misfits (a bright star's
#: chi^2 reaches ~100, like the frame-built models of the MAVIS frames), and each faint
#: star's stamp holds its neighbours' mis-modelled light.
NARROW = SynthPSF(0.92)


def _misfit_score(options, seeds=range(8)):
    """On the crowded frames fitted with :data:`NARROW` (started at the truth): the
    fractions of the stars with m < 24 flagged 1 (still moving) and 32 (failed), the
    robust std of (fit - truth) / CRLB of the others at m 22-24 (the bound of the true
    PSF), and the fraction of the m < 24 stars called converged while resting at
    ``max_shift`` from their start (the truth)."""
    psf, exact = true_epsf(NARROW, SHAPE), true_epsf(PSF, SHAPE)
    unconverged = failed = total = clamped = 0
    pos = []
    for seed in seeds:
        image, sat, x, y, mag = _frame(seed + 10, n=250)
        fit = fit_stars(
            image, psf, x, y, read_noise_var=RN2, sky0=DET.sky, saturated=sat,
            options=options, return_model=False,
        )  # fmt: skip
        scored = mag < 24
        total += scored.sum()
        bad = (fit.flag & FLAG_FAILED) > 0
        still = ((fit.flag & FLAG_NOT_CONVERGED) > 0) & ~bad
        unconverged += np.sum(still[scored])
        failed += np.sum(bad[scored])
        moved = np.hypot(fit.x - x, fit.y - y)
        clamped += np.sum(scored & ~bad & ~still & (moved > options.max_shift - 1e-9))
        good = (mag >= 22) & (mag < 24) & ~bad & ~still
        bound = crlb(exact, x[good], y[good], mag_to_flux(mag[good]), DET.sky, RN2)
        pos.append(
            np.r_[(fit.x[good] - x[good]) / bound[:, 0], (fit.y[good] - y[good]) / bound[:, 1]]
        )
    return unconverged / total, failed / total, robust_sigma(np.concatenate(pos)), clamped / total


def test_misfit_crowd_converges_without_stopping_early():
    """In a crowd 1.6 x as dense as the 1e5-star frame (250 stars on 160 x 160 px) fitted with
    a misfitting ePSF, the stage's fitter converges for >= 99 % of the stars with m < 24,
    fails for <= 1 %, and the converged stars at m 22-24 stay within 1.7 x the CRLB
    (measured 2026-12-02: 0.29 % unconverged, 0.69 % failed, 1.58; with
    ``check_cut_steps`` 1.15 %, 0.69 %, 1.54: the 15 stars it flags were stopped by one
    cut step a median 25 x CRLB from the truth, against 2.1 for those still called
    converged; with ``crowded_window`` 0.80 %, 0.40 %, 1.52; 2026-12-03, held positions
    retried and a never-fitted one failed: 0.80 %, 0.29 %, 1.59, while counting the
    never-fitted ones without the retry gave 1.72 % failed: they had sat at their start,
    the truth, as converged; docs/measure-scale.md, tenth pass). The convergence test
    counts a step against the position error that the neighbours' share of the stamp's
    misfit implies (``chi2_tolerance``): against the Fisher error alone 4.4 % were still
    moving after 40 sweeps (0.52 % failed, 1.66;
    ``test_misfit_crowd_check_fails_the_fisher_criterion``). Since 2026-12-03
    (thirteenth pass) a star resting at ``max_shift`` with a free step above its
    tolerance is not converged either: 18 of the 1,743 stars (1.03 %) sat at the 2-px
    clamp, 2 px (a median 35 of their own errors) from the truth, called converged
    (0.86 % unconverged then); now none is, and 1.89 % are flagged (the bound <= 2.5 %
    counts them honestly)."""
    unconverged, failed, spread, clamped = _misfit_score(fit_options(validate_settings({})))
    assert unconverged <= 0.025 and failed <= 0.01 and spread <= 1.7, (unconverged, failed, spread)
    assert clamped == 0, clamped


def test_misfit_crowd_fits_crowded_stars_on_their_central_window():
    """On the same frames, the crowded stars' smaller fitting window (``crowded_window``:
    their outer stamp holds mostly their neighbours' mis-modelled light) leaves fewer stars
    with m < 24 unconverged or failed than the whole stamp, at no more scatter about the
    truth (measured: 1.20 % against 1.84 %, 1.52 against 1.54 x CRLB; with held
    positions retried, 2026-12-03: 1.09 % against 1.72 %, 1.59 against 1.64). Measured
    with one flux pass before the first position step (``flux_passes = 1``, the
    stage before 2026-12-03): with the stage's five the window gains less on these
    frames (1.26 % against 1.38 %, 1.57 against 1.59: most of its gain here came from
    the wrong first steps that the later flux passes remove); on the 1e5-star MAVIS
    frame it still gains (with two passes failed + not converged at V < 25 4.09 -> 3.86
    %; docs/measure-scale.md, twelfth pass)."""
    options = dataclasses.replace(fit_options(validate_settings({})), flux_passes=1)
    assert options.crowded_window == 4
    unconverged, failed, spread, _ = _misfit_score(options)
    whole = _misfit_score(dataclasses.replace(options, crowded_window=0))
    assert unconverged + failed <= 0.75 * (whole[0] + whole[1]), (unconverged, failed, whole)
    assert spread <= whole[2] * 1.02, (spread, whole)


def test_misfit_crowd_check_fails_the_fisher_criterion():
    """The check above fails for the Fisher-error convergence test (the stage before
    2026-12-02)."""
    options = dataclasses.replace(
        fit_options(validate_settings({})), chi2_tolerance=False, flux_refresh=False
    )
    unconverged, *_ = _misfit_score(options)
    assert unconverged > 0.01, unconverged


def test_neighbour_misfit_counts_the_neighbours_share_of_the_chi2():
    """``1 + (chi2 - 1) q``: a star alone on its stamp keeps its Fisher error whatever
    its misfit; a stamp lit only by neighbours counts the whole chi^2; equal light half
    the excess; masked pixels count in neither the chi^2 nor the light."""
    from mavispm.measure.stars.batched_fit import _neighbour_misfit

    m, npar = 25, 4
    chi2_pixels = np.full((4, m), 9.0)  # reduced chi^2 9 * m / (m - npar)
    valid = np.ones((4, m), bool)
    own = np.array([np.full(m, 100.0), np.zeros(m), np.full(m, 50.0), np.full(m, 50.0)])
    others = np.array([np.zeros(m), np.full(m, 100.0), np.full(m, 50.0), np.full(m, 50.0)])
    valid[3, :5] = False
    others[3, :5] = 1e6  # masked: not counted
    chi2 = 9.0 * m / (m - npar)
    got = _neighbour_misfit(chi2_pixels * valid, others, own, valid, npar)
    chi2_masked = 9.0 * (m - 5) / (m - 5 - npar)
    assert np.allclose(got, [1.0, chi2, 1 + (chi2 - 1) / 2, 1 + (chi2_masked - 1) / 2])
    assert _neighbour_misfit(np.full((1, m), 0.1), others[1:2], own[1:2], valid[1:2], npar) == 1.0


def _crowd_normalised_std(n_stars, crowding_term):
    """Robust std of (fit - truth) / reported error, stars with m 20-24 not flagged 1 or 32,
    on eight crowded frames of ``n_stars`` fitted with :data:`NARROW`: the PSF-R error
    model's chi^2 terms (``relative_chi2``; no half-set ePSF term: the model error here
    is the misfit itself), with or without the crowding term."""
    from mavispm.measure.stars.error_model import estimate_error_model

    psf, options = true_epsf(NARROW, SHAPE), fit_options(validate_settings({}))
    out = []
    for seed in range(8):
        image, sat, x, y, mag = _frame(seed + 10, n=n_stars)
        fit = fit_stars(
            image, psf, x, y, read_noise_var=RN2, sky0=DET.sky, saturated=sat,
            options=options, return_model=False,
        )  # fmt: skip
        ok = (fit.flag & (FLAG_FAILED | FLAG_NOT_CONVERGED)) == 0
        model = estimate_error_model(
            fit.flux, fit.chi2, ok, None, relative_chi2=True,
            crowding=fit.crowding if crowding_term else None,
        )  # fmt: skip
        g = ok & (mag >= 20) & (mag < 24)
        x_err, y_err = (
            model.total(fit.x_err, model.position),
            model.total(fit.y_err, model.position),
        )
        out.append(np.r_[(fit.x[g] - x[g]) / x_err[g], (fit.y[g] - y[g]) / y_err[g]])
    return robust_sigma(np.concatenate(out))


@pytest.mark.parametrize("n_stars", [120, 180])
def test_crowding_term_makes_the_errors_honest_in_a_misfit_crowd(n_stars):
    """With a misfitting ePSF in a crowd every star's stamp holds its neighbours'
    mis-modelled light. The PSF-R error model's ``max(chi2 / chi2_typ(F), 1)`` divides
    out what all peers share, so its errors were too small (robust normalised std 1.20 /
    1.41 at 120 / 180 stars on 160 x 160 px, measured 2026-12-02); with the crowding term
    (the peers' typical neighbour misfit) they are within 1 +- 0.15 (1.02 / 0.97). At
    250 stars the term over-corrects (1.41 -> 0.76; docs/measure-scale.md). With
    today's fit (2026-12-04) 1.08 / 1.10 with the term and 1.15 / 1.31 without
    (``bisect_reversals`` on; off: 1.08 / 1.11 and 1.15 / 1.31): the control's 1.12."""
    assert abs(_crowd_normalised_std(n_stars, True) - 1) <= 0.15
    assert _crowd_normalised_std(n_stars, False) > 1.12
