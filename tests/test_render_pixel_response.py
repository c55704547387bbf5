"""Detector pixel response: intra-pixel sensitivity and the flat-field residual."""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from render_helpers import brute_force_stamp, epoch_table, make_optics
from scipy.integrate import quad

from mavispm.core.config import from_mapping
from mavispm.core.errors import ConfigError
from mavispm.simulate.render.detector import DetectorSettings
from mavispm.simulate.render.frame import render_frame
from mavispm.simulate.render.pixel_response import flat_field_residual, pixel_transfer
from mavispm.simulate.render.scene import scene_from_mapping
from mavispm.simulate.render.stamps import RenderParams, StarRenderer

SCALE = 7.5


def test_uniform_pixel_is_the_sinc_bit_for_bit():
    f = np.linspace(-0.3, 0.3, 101)
    assert np.array_equal(pixel_transfer(f, SCALE, 0.0), np.sinc(f * SCALE))


@pytest.mark.parametrize("a", [0.1, 0.5, 0.9])
def test_transfer_matches_quadrature(a):
    """The transform of the normalised parabolic profile, by adaptive quadrature."""

    def profile(xi):
        return (1 - a * (2 * xi / SCALE) ** 2) / (1 - a / 3)

    for f in (0.0, 0.01, 0.05, 0.13, 0.4):
        ref = quad(lambda xi, f=f: profile(xi) * np.cos(2 * np.pi * f * xi), -SCALE / 2, SCALE / 2)[
            0
        ]
        assert pixel_transfer(np.array([f]), SCALE, a)[0] == pytest.approx(ref / SCALE, abs=1e-12)


def test_rendered_star_matches_sub_pixel_brute_force():
    """A star on pixels that are 40% less sensitive at their edges, against direct
    sub-pixel integration of PSF x kernel x response."""
    a = 0.4
    optics = make_optics("airy", stretch=0.06)
    r = StarRenderer(optics.psf_grid, SCALE, RenderParams(oversampling=2), intrapixel_amplitude=a)
    cov = np.array([[29.2, 1.5], [1.5, 27.2]])
    xp, yp = 20.37, 19.81
    stamps, _, _ = r.render_stamps(32, [xp], [yp], [0.7], [-1.3], cov[None], [1.0])
    ref = brute_force_stamp(
        optics.psf_grid, 0.7, -1.3, cov, xp, yp, SCALE, 32, sub=15,
        sensitivity=lambda t: 1 - a * (2 * t) ** 2,
    )  # fmt: skip
    assert np.abs(stamps[0] - ref).max() <= 1e-3 * ref.max()
    uniform = brute_force_stamp(optics.psf_grid, 0.7, -1.3, cov, xp, yp, SCALE, 32)
    # the response matters (0.8% of the peak for this 2-pixel FWHM star), 3x the tolerance
    assert np.abs(stamps[0] - uniform).max() > 3e-3 * ref.max()
    assert stamps[0].sum() == pytest.approx(1.0, abs=1e-4)  # mean response 1


def _scene(**detector):
    return scene_from_mapping(
        {
            "noise": False,
            "nexp": 1,
            "detector": {"nx": 64, "ny": 48, **detector},
            "render": {"halo": False},
        }
    )


def test_flat_residual_pattern_fixed_and_of_the_stated_rms():
    t = epoch_table([0.0], [0.0], [30.0])  # a star too faint to matter: the sky shows the flat
    optics = make_optics("gaussian")
    base = render_frame(t, 0 * u.yr, _scene(), optics, None)
    off = render_frame(t, 0 * u.yr, _scene(flat_residual=0.0), optics, None)
    assert np.array_equal(base.image, off.image)  # 0: today's frame bit for bit
    f0 = render_frame(t, 0 * u.yr, _scene(flat_residual=0.02, flat_seed=3), optics, None)
    f1 = render_frame(t, 10 * u.yr, _scene(flat_residual=0.02, flat_seed=3), optics, None)
    ratio = f0.noiseless / base.noiseless
    assert np.std(ratio) == pytest.approx(0.02, rel=0.1)
    assert np.array_equal(f0.noiseless, f1.noiseless)  # one detector, every epoch
    assert flat_field_residual((4, 4), 0.0, 1) is None


def test_bad_detector_settings_name_the_key():
    with pytest.raises(ConfigError, match="detector.*intrapixel_amplitude"):
        from_mapping(DetectorSettings, {"intrapixel_amplitude": 1.5}, prefix="scene.detector")
    with pytest.raises(ConfigError, match="flat_residual"):
        from_mapping(DetectorSettings, {"flat_residual": -0.1}, prefix="scene.detector")
