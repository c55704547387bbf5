"""Telescope plate-scale variations and field distortion."""

from __future__ import annotations

from types import SimpleNamespace

import astropy.units as u
import numpy as np
import pytest
from render_helpers import epoch_table, make_optics

from mavispm.core.config import from_mapping
from mavispm.core.errors import ConfigError
from mavispm.simulate.optics.telescope import (
    TelescopeSettings,
    plate_scale_change,
    telescope_displacement,
)
from mavispm.simulate.render.frame import render_frame
from mavispm.simulate.render.scene import scene_from_mapping


def test_plate_scale_draws_have_the_stated_rms_and_repeat():
    s = TelescopeSettings(plate_scale_rms=20.0, seed=5)
    eps = np.array([plate_scale_change(s, t) for t in np.arange(2000) * 0.01])
    assert np.std(eps) == pytest.approx(20e-6, rel=0.08)
    assert abs(np.mean(eps)) < 4 * 20e-6 / np.sqrt(2000)
    assert plate_scale_change(s, 3.0) == plate_scale_change(s, 3.0)
    assert plate_scale_change(TelescopeSettings(), 3.0) == 0.0


def test_plate_scale_is_removed_by_a_linear_fit_and_field_distortion_is_static():
    s = TelescopeSettings(plate_scale_rms=50.0, field_distortion_corner=2.0, seed=1)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-15, 15, (2, 500))
    d0 = np.array(telescope_displacement(x, y, 0.0, s))
    d1 = np.array(telescope_displacement(x, y, 10.0, s))
    diff = d1 - d0  # the field distortion cancels between epochs: a pure scale is left
    eps = (diff[0] @ x + diff[1] @ y) / (x @ x + y @ y)
    assert np.allclose(diff, eps * np.array([x, y]), atol=1e-15)
    assert eps == pytest.approx(plate_scale_change(s, 10.0) - plate_scale_change(s, 0.0))
    corner = telescope_displacement(15.0, 15.0, 0.0, TelescopeSettings(field_distortion_corner=2.0))
    assert np.hypot(*corner) * 1000 == pytest.approx(2.0, rel=1e-12)


def test_frames_carry_the_telescope_terms():
    scene = scene_from_mapping(
        {"noise": False, "nexp": 1, "detector": {"nx": 400, "ny": 400}, "render": {"halo": False}}
    )
    t = epoch_table([1.2, -0.8], [0.5, -1.1], [18.0, 18.0])
    optics = make_optics("gaussian")
    tel = TelescopeSettings(plate_scale_rms=1000.0, field_distortion_corner=5.0, seed=2)
    optics.settings = SimpleNamespace(telescope=tel)
    frame = render_frame(t, 4 * u.yr, scene, optics, None)
    dx, dy = telescope_displacement([1.2, -0.8], [0.5, -1.1], 4.0, tel)
    assert np.allclose((frame.truth["x"] - frame.truth["x_cat"]).to_value(u.arcsec), dx)
    assert np.allclose((frame.truth["y"] - frame.truth["y_cat"]).to_value(u.arcsec), dy)


def test_bad_settings_name_the_key():
    with pytest.raises(ConfigError, match="telescope.*plate_scale_rms"):
        from_mapping(TelescopeSettings, {"plate_scale_rms": -1}, prefix="scene.optics.telescope")
