"""Per-exposure image motion and dynamic distortion of stacks."""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from render_helpers import epoch_table, make_optics
from scipy import integrate

from mavispm.core.errors import ConfigError
from mavispm.simulate.optics.atmosphere import AtmosphereSettings, layers
from mavispm.simulate.optics.image_motion import (
    ImageMotion,
    ImageMotionSettings,
    build_image_motion,
    exposure_average_factor,
    noise_free_covariance,
)
from mavispm.simulate.optics.model import validate_settings
from mavispm.simulate.optics.pupil import PupilSettings
from mavispm.simulate.optics.tiptilt import TipTiltField, TipTiltSettings
from mavispm.simulate.render.frame import render_frame
from mavispm.simulate.render.scene import scene_from_mapping


def _motion(**kw) -> ImageMotion:
    s = ImageMotionSettings(enabled=True, **kw)
    return ImageMotion(s, np.zeros((6, 6)), tau=1.0)


def _moments(img):
    y, x = np.indices(img.shape)
    f = img.sum()
    cx, cy = (img * x).sum() / f, (img * y).sum() / f
    cxx = (img * (x - cx) ** 2).sum() / f
    cyy = (img * (y - cy) ** 2).sum() / f
    cxy = (img * (x - cx) * (y - cy)).sum() / f
    return np.array([cx, cy]), np.array([cxx, cyy, cxy])


def test_uniform_tilt_is_a_pure_shift_of_the_stack():
    """Common tilt only: every star moves by the same mean shift and the stacked image has
    the centroid and second moments of the sum of the N individually shifted exposures."""
    nexp, exptime = 4, 30.0
    motion = _motion(tilt=3.0, plate_scale=0.0, distortion_rms=0.0)
    drawn = motion.draw(nexp, exptime, epoch=0.0)
    xs, ys = np.array([-10.0, 0.0, 12.0]), np.array([5.0, 0.0, -7.0])
    mean, cov = drawn.stack_moments(xs, ys)
    np.testing.assert_allclose(mean, np.tile(drawn.modes[:, :2].mean(0), (3, 1)), atol=1e-12)
    np.testing.assert_allclose(cov, np.tile(cov[0], (3, 1, 1)), atol=1e-12)
    per_exp = drawn.displacements(xs, ys)
    np.testing.assert_allclose(per_exp, np.repeat(per_exp[:, :1], 3, axis=1), atol=1e-12)

    # render: stacked model against the brute-force sum of the shifted sub-exposures
    scene = scene_from_mapping(
        {"noise": False, "nexp": nexp, "exptime": "30 s", "detector": {"nx": 64, "ny": 64}}
    )
    one = scene_from_mapping(
        {"noise": False, "nexp": 1, "exptime": "30 s", "detector": {"nx": 64, "ny": 64}}
    )
    optics = make_optics("airy")
    x0, y0 = 0.0123, -0.0071  # arcsec
    optics.image_motion = motion
    stacked = render_frame(epoch_table([x0], [y0], [17.0]), 0 * u.yr, scene, optics, None)
    optics.image_motion = None
    brute = 0.0
    for d in drawn.modes[:, :2]:
        t = epoch_table([x0 + d[0] / 1000], [y0 + d[1] / 1000], [17.0])
        brute = brute + render_frame(t, 0 * u.yr, one, optics, None).noiseless
    sky_stack = stacked.attrs["sky"].value
    img_s = stacked.noiseless - sky_stack
    img_b = brute - sky_stack
    c_s, m_s = _moments(img_s)
    c_b, m_b = _moments(img_b)
    np.testing.assert_allclose(c_s, c_b, atol=2e-4)  # pixels (7.5 mas): 1.5 uas
    np.testing.assert_allclose(m_s, m_b, rtol=0.01, atol=0.01)
    assert stacked.truth["dx_motion"].to_value(u.mas)[0] == pytest.approx(mean[0, 0])
    # truth keeps the true position: the motion is an astrometric error
    assert stacked.truth["x"].to_value(u.arcsec)[0] == pytest.approx(x0)


def _ar1_mean_variance(sigma2: float, n: int, rho: float) -> float:
    """Variance of the mean of n stationary AR(1) samples (written out independently)."""
    s = sum((1 - k / n) * rho**k for k in range(1, n))
    return sigma2 / n * (1 + 2 * s)


@pytest.mark.parametrize("correlation_time", [0.0, 60.0])
def test_stacked_centroid_jitter_against_drawn_variance_over_n(correlation_time):
    sigma, n, exptime = 1.5, 10, 30.0
    motion = _motion(
        tilt=sigma, plate_scale=0.0, distortion_rms=0.0, correlation_time=correlation_time
    )
    means = np.array(
        [motion.stack([3.0], [-4.0], n, exptime, epoch=e)[0][0] for e in np.arange(1500) * 0.01]
    )
    rho = np.exp(-exptime / correlation_time) if correlation_time else 0.0
    expect = _ar1_mean_variance(sigma**2, n, rho)
    # 1500 stacks: the variance estimate scatters by sqrt(2 / 1500) = 3.7%
    assert np.var(means[:, 0]) == pytest.approx(expect, rel=0.12)
    assert np.var(means[:, 1]) == pytest.approx(expect, rel=0.12)
    if correlation_time:
        assert expect > 1.5 * sigma**2 / n  # correlated draws average down more slowly


def test_plate_scale_mode_gives_differential_motion():
    motion = _motion(tilt=0.0, plate_scale=1.0, distortion_rms=0.0)
    drawn = motion.draw(20, 30.0)
    d = drawn.displacements([15.0, -15.0, 0.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(d[:, 0], -d[:, 1], atol=1e-12)  # odd in position
    np.testing.assert_allclose(d[:, 2], 0.0, atol=1e-12)  # no motion at the centre


def test_exposure_average_factor_against_quadrature():
    for tau, t in ((1.0, 30.0), (5.0, 3.0), (0.2, 0.1)):
        # (1/T^2) int_0^T int_0^T exp(-|a-b|/tau) = (2/T^2) int_0^T (T - s) exp(-s/tau) ds
        val, _ = integrate.quad(lambda s, tau=tau, t=t: (t - s) * np.exp(-s / tau), 0, t)
        assert exposure_average_factor(tau, t) == pytest.approx(2 * val / t**2, rel=1e-8)


def test_budget_from_the_tt_field():
    atm, pupil = AtmosphereSettings(), PupilSettings()
    # a very bright asterism: the noise-free residual equals the kernel covariance
    bright = TipTiltSettings(asterism="custom", ngs=((10.0, 0.0, 0.0), (10.0, 120.0, 0.0)))
    field = TipTiltField(bright, atm, pupil)
    xy = np.array([[0.0, 0.0], [8.0, -6.0]])
    nf = noise_free_covariance(field, xy)
    np.testing.assert_allclose(nf[1, 1], field.covariance([8.0], [-6.0])[0], rtol=1e-3)
    good = TipTiltField(TipTiltSettings(asterism="good"), atm, pupil)
    m = build_image_motion(ImageMotionSettings(enabled=True), good, layers(atm), 8.0)
    c = m.exposure_covariance(30.0)
    assert np.all(np.linalg.eigvalsh(c) >= -1e-12)
    assert 0.02 < np.sqrt(c[0, 0]) < 1.0  # mas per 30 s exposure
    assert m.tau == pytest.approx(8.0 / 8.97, rel=0.05)  # D / v_eff of the MAVIS.ini winds


def test_settings_validated():
    with pytest.raises(ConfigError, match="image_motion"):
        validate_settings({"image_motion": {"tilt": "-1 mas"}})
    s = validate_settings({"image_motion": {"enabled": True, "correlation_time": "2 min"}})
    assert s.image_motion.correlation_time == pytest.approx(120.0)


def test_single_exposure_and_disabled_edges():
    m = _motion(tilt=2.0, plate_scale=1.0)
    drawn = m.draw(1, 30.0)
    mean, cov = drawn.stack_moments([5.0], [5.0])
    np.testing.assert_allclose(cov, 0.0, atol=1e-12)  # one exposure: a pure shift
    np.testing.assert_allclose(mean[0], drawn.displacements([5.0], [5.0])[0, 0], atol=1e-12)
    off = build_image_motion(
        ImageMotionSettings(),
        TipTiltField(TipTiltSettings(), AtmosphereSettings(), PupilSettings()),
        layers(AtmosphereSettings()),
        8.0,
    )
    assert not off.enabled
    np.testing.assert_allclose(off.budget_covariance, 0.0)
