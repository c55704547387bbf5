"""The rescue pass (:mod:`mavispm.measure.stars.rescue`; docs/measure-scale.md,
twenty-eighth pass): stars the batched fit leaves unconverged or failed in blended pairs
are refitted with their neighbours, against the rendered truth; the stars it does not
rescue keep every value bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from measure_helpers import Detector, SynthPSF, grid_positions, noisy_frame, render_image, true_epsf

from mavispm.measure.stars.batched_fit import FitOptions, fit_stars
from mavispm.measure.stars.crlb import BLEND_PARAMETERS, blend_crlb
from mavispm.measure.stars.measure_frame import with_rescued
from mavispm.measure.stars.rescue import RescueOptions, rescue_stars

SHAPE = (200, 200)
FLUX = 8000.0  # electron: a blend Cramer-Rao flux SNR of ~14 at 1.5 px


@pytest.fixture(scope="module")
def scene():
    """Isolated stars and equal pairs 1.5 px apart (0.53 FWHM) on a 20-px grid, every
    start 0.5 px off the truth in a random direction: single-star Gauss-Seidel steps
    crawl along such a pair and leave most of its stars unconverged after 40 sweeps."""
    rng = np.random.default_rng(1)
    psf, det = SynthPSF(1.2), Detector()
    cx, cy = grid_positions(SHAPE, 20, 12, rng)
    pair = np.arange(len(cx)) % 2 == 0
    angle = rng.uniform(0, np.pi, len(cx))
    half = 0.75
    xa = np.where(pair, cx + half * np.cos(angle), cx)
    ya = np.where(pair, cy + half * np.sin(angle), cy)
    xb, yb = (cx - half * np.cos(angle))[pair], (cy - half * np.sin(angle))[pair]
    x, y = np.concatenate([xa, xb]), np.concatenate([ya, yb])
    flux = np.full(len(x), FLUX)
    in_pair = np.concatenate([pair, np.ones(len(xb), bool)])
    image, sat = noisy_frame(render_image(SHAPE, x, y, flux, psf), det, rng)
    image = image * det.gain
    turn = rng.uniform(0, 2 * np.pi, len(x))
    x0, y0 = x + 0.5 * np.cos(turn), y + 0.5 * np.sin(turn)
    epsf = true_epsf(psf, SHAPE)
    rn = det.read_noise**2 * det.nexp
    fit = fit_stars(
        image, epsf, x0, y0, read_noise_var=rn, sky0=det.sky, saturated=sat,
        options=FitOptions(wing_threshold=0.0), return_light=True,
    )  # fmt: skip
    rescued = rescue_stars(
        image, fit.light_image, epsf, fit, x0, y0, rn, det.sky, None, sat,
        RescueOptions(radius=6.0, stamp_radius=5),
    )  # fmt: skip
    # the Cramer-Rao bound of the pairs' first stars with the partner free (what any
    # fitter of the pair can reach)
    n_pair = len(xb)
    bound = blend_crlb(epsf, xa[pair], ya[pair], flux[:n_pair], xb, yb, flux[:n_pair], det.sky, rn)
    return dict(x=x, y=y, flux=flux, in_pair=in_pair, fit=fit, rescued=rescued, bound=bound)


def test_the_fit_alone_leaves_the_pairs_flagged(scene):
    """The premise (the old code's result): most pair stars end flagged 1 or 32 although
    their Cramer-Rao flux SNR is far above ``min_snr``; no isolated star does."""
    fit, in_pair = scene["fit"], scene["in_pair"]
    flagged = (fit.flag & (1 | 32)) != 0
    assert flagged[in_pair].mean() > 0.5
    assert not flagged[~in_pair].any()
    snr = FLUX / scene["bound"][:, BLEND_PARAMETERS.index("flux1")]
    assert np.all(snr > 10), snr.min()


def test_rescued_pair_stars_are_measured_within_their_errors(scene):
    """Against the truth: after the rescue >= 90 % of the pair stars are unflagged, every
    rescued star lies within 5 of its reported sigma of the truth, and the normalised
    residuals have a robust std within 0.7-1.4 (the old code: the pairs stay flagged)."""
    fit, res, in_pair = scene["fit"], scene["rescued"], scene["in_pair"]
    out = with_rescued(fit, res)
    flagged = (out.flag & (1 | 32)) != 0
    # measured: unflagged and within 5 reported sigma of the rendered truth
    near = (np.abs(out.x - scene["x"]) < 5 * out.x_err) & (
        np.abs(out.y - scene["y"]) < 5 * out.y_err
    )
    measured = ~flagged & near
    assert measured[in_pair].mean() >= 0.9, (~measured[in_pair]).sum()
    i = res.index
    assert np.all(in_pair[i])
    nx_ = (res.x - scene["x"][i]) / res.x_err
    ny_ = (res.y - scene["y"][i]) / res.y_err
    assert np.all(np.abs(nx_) < 5) and np.all(np.abs(ny_) < 5)
    for n in (nx_, ny_):
        spread = 1.4826 * np.median(np.abs(n - np.median(n)))
        assert 0.7 < spread < 1.4, spread
    np.testing.assert_allclose(res.flux, scene["flux"][i], rtol=0.2)


def test_stars_not_rescued_are_bit_identical(scene):
    """Every star outside the rescued set, the isolated ones and the pairs' neighbours
    alike, keeps each fitted value bit for bit."""
    fit, res = scene["fit"], scene["rescued"]
    out = with_rescued(fit, res)
    other = np.ones(len(fit.x), bool)
    other[res.index] = False
    for name in ("x", "y", "flux", "sky", "x_err", "y_err", "flux_err", "chi2", "flag",
                 "chi2_odd", "crowding"):  # fmt: skip
        a, b = getattr(fit, name)[other], getattr(out, name)[other]
        assert np.array_equal(a, b, equal_nan=True), name
