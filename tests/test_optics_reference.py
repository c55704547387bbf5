"""Regression figures against published numbers (independent truth).

With the default settings (TIPTOP's MAVIS.ini: 0.8" seeing, 30 deg zenith, 10
layers, 8 LGS at 17.5" / 90 km, DMs at 0 / 6 / 13.5 km, 550 nm):

* TIPTOP 1.6.0 run on its shipped perfTest/MAVIS.ini (numbers quoted in
  issue 15): Strehl centre 0.249, field median 0.225, corner 0.04-0.05;
  FWHM centre 14.5, field median 15.4, corner 18.0 mas. Tolerance 10%.
* The MAVISIM paper: field-average sigma_TT of tab:ttjitter's asterisms 2.92 /
  6.45 / 9.23 mas (good / typical / bad), tolerance 10%; FWHM_ave of
  tab:simparams (the HO PSF's FWHM in quadrature with the TT kernel, 3 mas
  charge diffusion and 3.5 mas vibration, as the paper computes it:
  :func:`fwhm_ave_quadrature`), tolerance 5%.

Figures the model does not reach yet are ``xfail(strict=True)`` with the
measured value in the reason, so they flip to failures (and must be promoted)
the day the model reaches them. Full 11 x 11 grids are slow-marked.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mavispm.simulate.optics.ao_psd import AOSettings, noise_gain
from mavispm.simulate.optics.atmosphere import AtmosphereSettings
from mavispm.simulate.optics.psf_grid import (
    PSFSettings,
    compute_fourier_grid,
    compute_grid,
    residual_psd_model,
)
from mavispm.simulate.optics.psf_metrics import fwhm
from mavispm.simulate.optics.pupil import PupilSettings
from mavispm.simulate.optics.tiptilt import TipTiltField, TipTiltSettings, field_average_sigma

ATM, PUPIL, AO = AtmosphereSettings(), PupilSettings(), AOSettings()
#: accuracy knobs: pupil_sampling 64 is within 0.002 in Strehl of 128 (docs/optics.md)
PSF = PSFSettings(pupil_sampling=64, stamp_size=0.4)
TIPTOP = {"strehl": (0.249, 0.225, (0.04, 0.05)), "fwhm": (14.5, 15.4, 18.0)}
PAPER_TT = {"good": 2.92, "typical": 6.45, "bad": 9.23}
#: tab:simparams: (asterism or None, TT scale, static HO PSF) -> FWHM_ave (mas)
SIMPARAMS = {
    "I": (None, 1, True, 17.99),
    "Ia": (None, 1, False, 17.99),
    "Ib": ("typical", 1, True, 22.20),
    "II": ("good", 1, False, 18.96),
    "III": ("typical", 1, False, 22.20),
    "IV": ("bad", 1, False, 26.58),
    "IIIx3": ("typical", 3, False, 42.99),
    "IVx3": ("bad", 3, False, 61.42),
}
#: measured (idle-machine independent) values of the cases the model misses
MISSES = {"IV": 28.14, "IIIx3": 46.21, "IVx3": 67.04}
#: TIPTOP 1.6.0 (astro-tiptop, with astro-p3 1.6.4) run on its shipped perfTest/MAVIS.ini
#: (getHoErrorBreakDown; PSD sums per science direction), RMS wavefront error in nm:
#: fitting, aliasing, servo-lag alone (its SCAO integrator formula), spatio-temporal
#: (servo-lag + tomography, its tomographic model), LGS noise, MCAO cone ("reduced
#: sensing volume"). Its "sole tomographic error" 57.9 = sqrt(70.8^2 - 40.7^2) mixes the
#: two servo models and is not used.
TIPTOP_ON_AXIS = {"fitting": 67.55, "aliasing": 26.82, "servo": 40.70, "noise": 17.1}
#: (x, y) arcsec -> (servo + tomography, noise, cone) nm
TIPTOP_BUDGET = {
    (0.0, 0.0): (70.8, 17.1, 0.0),
    (15.0, 0.0): (66.1, 15.1, 25.4),
    (-15.0, 0.0): (72.3, 15.1, 25.3),
    (0.0, 15.0): (68.7, 15.1, 25.3),
    (0.0, -15.0): (69.6, 15.1, 25.3),
    (15.0, 15.0): (115.0, 16.9, 42.6),
    (-15.0, -15.0): (123.6, 16.9, 42.3),
    (15.0, -15.0): (116.7, 16.9, 42.5),
    (-15.0, 15.0): (122.1, 16.9, 42.4),
}
#: P3's conventions (see AOSettings.layer_stretch / servo_model)
P3_CONVENTIONS = {"layer_stretch": "all", "servo_model": "pure_delay"}


@pytest.fixture(scope="module")
def centre_and_corner():
    pos = np.array([[0.0, 0.0], [-15.0, -15.0]])
    psfs, strehl, _, _ = compute_fourier_grid(PSF, PUPIL, ATM, AO, pos, progress=False)
    return strehl, [fwhm(p, PSF.pixel_scale) for p in psfs]


@pytest.mark.xfail(strict=True, reason="centre Strehl 0.299 against TIPTOP 0.249 (+20%)")
def test_tiptop_strehl_centre(centre_and_corner):
    assert centre_and_corner[0][0] == pytest.approx(TIPTOP["strehl"][0], rel=0.10)


@pytest.mark.xfail(
    strict=True,
    reason="(-15,-15) Strehl 0.109 against 0.04-0.05 (TIPTOP's own HO-only corners 0.057 / "
    "0.074): the cone term is now the kriging error (33.9 nm, P3 42.6) and our corner "
    "servo-lag + tomography is 16-19% below P3's (its layer-stretch convention)",
)
def test_tiptop_strehl_corner(centre_and_corner):
    lo, hi = TIPTOP["strehl"][2]
    assert 0.9 * lo <= centre_and_corner[0][1] <= 1.1 * hi


def test_tiptop_fwhm_centre(centre_and_corner):
    assert centre_and_corner[1][0] == pytest.approx(TIPTOP["fwhm"][0], rel=0.10)


@pytest.mark.xfail(
    strict=True,
    reason="(-15,-15) FWHM 14.64 mas against 18.0 (-19%); TIPTOP's own HO-only corner "
    "FWHM is 15.17 (16.06 with its LO kernel); 16.45 passed only with the cone's tilt in the PSD",
)
def test_tiptop_fwhm_corner(centre_and_corner):
    assert centre_and_corner[1][1] == pytest.approx(TIPTOP["fwhm"][2], rel=0.10)


@pytest.mark.parametrize(
    "asterism",
    [
        "good",
        "typical",
        pytest.param(
            "bad", marks=pytest.mark.xfail(strict=True, reason="10.19 mas against 9.23 (+10.4%)")
        ),
    ],
)
def test_paper_sigma_tt(asterism):
    field = TipTiltField(TipTiltSettings(asterism=asterism), ATM, PUPIL)
    assert field_average_sigma(field) == pytest.approx(PAPER_TT[asterism], rel=0.10)


@pytest.fixture(scope="module")
def budgets():
    """Term budgets (nm) per direction: defaults, servo-lag alone, P3's conventions."""
    out = {}
    for name, ao in (
        ("all", AO),
        ("servo", dataclasses.replace(AO, tomography=False)),
        ("p3", dataclasses.replace(AO, **P3_CONVENTIONS)),
    ):
        model = residual_psd_model(PSF, PUPIL, ATM, ao)
        out[name] = {pos: model.budget(pos) for pos in TIPTOP_BUDGET}
    return out


def test_tiptop_budget_terms_that_agree(budgets):
    """Fitting, aliasing, servo-lag alone and the on-axis total against TIPTOP's breakdown."""
    ours, ref = budgets["all"][(0.0, 0.0)], TIPTOP_ON_AXIS
    assert ours["fitting"] == pytest.approx(ref["fitting"], rel=0.05)
    assert ours["aliasing"] == pytest.approx(ref["aliasing"], rel=0.15)
    servo = budgets["servo"][(0.0, 0.0)]["servo_tomography"]
    assert servo == pytest.approx(ref["servo"], rel=0.05)
    st, noise, _ = TIPTOP_BUDGET[(0.0, 0.0)]
    total = np.sqrt(ref["fitting"] ** 2 + ref["aliasing"] ** 2 + st**2 + noise**2)
    assert ours["total"] == pytest.approx(total, rel=0.10)


def test_tiptop_tomography_with_p3_conventions(budgets):
    """With P3's cone stretch of every layer and its pure-delay servo model, our MMSE
    tomography + DM projection gives TIPTOP's servo + tomography error in all 9 directions
    (field pattern included: the downwind side is the better one)."""
    for pos, (st, _, _) in TIPTOP_BUDGET.items():
        assert budgets["p3"][pos]["servo_tomography"] == pytest.approx(st, rel=0.05), pos


def test_tiptop_centre_strehl_with_p3_conventions():
    """End to end, PSD to PSF: with P3's stretch and pure-delay conventions the on-axis HO
    image Strehl is TIPTOP's (0.259, its HO-only PSF of MAVIS.ini)."""
    ao = dataclasses.replace(AO, **P3_CONVENTIONS)
    _, strehl, _, _ = compute_fourier_grid(PSF, PUPIL, ATM, ao, np.zeros((1, 2)), progress=False)
    assert strehl[0] == pytest.approx(0.259, rel=0.05)


def test_tiptop_noise_gap_is_its_noise_gain(budgets):
    """P3 propagates tomographic LGS noise with a fixed gain min(0.8, 0.4 + 0.1333 delay)^2
    (fourierModel.noisePSD); with it in place of our exact integrator gain the on-axis noise
    matches TIPTOP's 17.1 nm (the single-WFS variance is the same Thomas formula)."""
    p3_gain = min(0.8, 0.4 + 0.1333 * AO.loop_delay) ** 2
    ours = budgets["all"][(0.0, 0.0)]["noise"] * np.sqrt(p3_gain / noise_gain(AO))
    assert ours == pytest.approx(TIPTOP_BUDGET[(0.0, 0.0)][1], rel=0.10)


@pytest.mark.xfail(strict=True, reason="LGS noise 13.5 nm on axis against TIPTOP 17.1 (-21%)")
def test_tiptop_budget_noise(budgets):
    assert budgets["all"][(0.0, 0.0)]["noise"] == pytest.approx(17.1, rel=0.10)


@pytest.mark.xfail(
    strict=True,
    reason="cone 11.4 / 33.9 nm at (15,0) / (15,15) against P3's 25.4 / 42.6: the kriging "
    "error (tested against a brute force) is below P3's calibrated term at (15,0)",
)
def test_tiptop_budget_cone(budgets):
    for pos in ((15.0, 0.0), (15.0, 15.0)):
        ours = budgets["all"][pos]["cone"]
        assert ours == pytest.approx(TIPTOP_BUDGET[pos][2], rel=0.20)


@pytest.fixture(scope="module")
def full_grid():
    return compute_grid(PSF, PUPIL, ATM, AO, progress=False).grid


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="field median Strehl 0.277 against 0.225 (+23%)")
def test_tiptop_field_median_strehl(full_grid):
    assert np.median(full_grid.strehl) == pytest.approx(TIPTOP["strehl"][1], rel=0.10)


@pytest.mark.slow
def test_tiptop_field_median_fwhm(full_grid):
    g = full_grid
    f = [fwhm(p, g.pixel_scale) for p in g.cube.reshape(-1, g.n, g.n)]
    assert np.median(f) == pytest.approx(TIPTOP["fwhm"][1], rel=0.10)


def fwhm_ave_quadrature(fwhm_ho: float, tt_cov: np.ndarray, blur: float) -> float:
    """tab:simparams' FWHM_ave as the paper computes it [mas].

    The paper (sec. "Modeling the Imager") obtains the realistic FWHM by adding the HO
    PSF's FWHM in quadrature with the FWHM of the average TT residual and the charge
    diffusion; tab:simparams follows that law exactly (I = Ia and Ib = III although the
    HO PSF varies, and the TT term of the x3 rows is 3.00 times that of the x1 rows to
    rounding), which a FWHM measured on field-variable PSFs would not. The TT kernel is
    elliptical: its quadrature term is the per-axis variance tr(C) / 2 (second moments
    add exactly under convolution), averaged over the nodes.

    Parameters
    ----------
    fwhm_ho : float
        FWHM of the HO PSF [mas] (the centre node, or the mean over the nodes).
    tt_cov : ndarray, shape (N, 2, 2)
        TT residual covariances at the nodes [mas^2].
    blur : float
        Charge diffusion and vibration sigma in quadrature [mas].
    """
    tt_var = float(np.mean(np.trace(tt_cov, axis1=1, axis2=2))) / 2
    return float(np.sqrt(fwhm_ho**2 + 8 * np.log(2) * (blur**2 + tt_var)))


@pytest.mark.slow
@pytest.mark.parametrize(
    "sim",
    [
        pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=f"measured {MISSES[s]} mas"))
        if s in MISSES
        else s
        for s in SIMPARAMS
    ],
)
def test_paper_fwhm_ave(full_grid, sim):
    asterism, scale, static, paper = SIMPARAMS[sim]
    g = full_grid
    gx, gy = np.meshgrid(g.nodes_x, g.nodes_y)
    if asterism is None:
        cov = np.zeros((gx.size, 2, 2))
    else:
        tt = TipTiltField(TipTiltSettings(asterism=asterism, scale_factor=scale), ATM, PUPIL)
        cov = tt.covariance(gx.ravel(), gy.ravel())
    c = g.cube.shape[0] // 2  # the centre node (11 x 11 grid)
    nodes = [g.cube[c, c]] if static else list(g.cube.reshape(-1, g.n, g.n))
    fwhm_ho = float(np.mean([fwhm(p, g.pixel_scale) for p in nodes]))
    got = fwhm_ave_quadrature(fwhm_ho, cov, np.hypot(3.0, 3.5))
    assert got == pytest.approx(paper, rel=0.05)


def test_fwhm_ave_quadrature_is_the_second_moment_law():
    """For a Gaussian HO PSF and an elliptical TT kernel the quadrature figure is the FWHM of
    the Gaussian whose per-axis variance is half the trace of the second moments of the
    convolved image, measured by brute force on pixels (the law the paper's sum relies on)."""
    pixel, n = 0.5, 401
    yy, xx = (np.mgrid[:n, :n] - (n - 1) / 2) * pixel
    sigma_ho = 14.5 / (2 * np.sqrt(2 * np.log(2)))
    cov = np.array([[30.0, 12.0], [12.0, 18.0]])
    total = cov + (sigma_ho**2 + 3.0**2 + 3.5**2) * np.eye(2)
    ic = np.linalg.inv(total)
    img = np.exp(-0.5 * (ic[0, 0] * xx**2 + 2 * ic[0, 1] * xx * yy + ic[1, 1] * yy**2))
    img /= img.sum()
    half_trace = 0.5 * np.sum(img * (xx**2 + yy**2))
    want = 2 * np.sqrt(2 * np.log(2)) * np.sqrt(half_trace)
    got = fwhm_ave_quadrature(14.5, cov[None], np.hypot(3.0, 3.5))
    assert got == pytest.approx(want, rel=1e-3)
