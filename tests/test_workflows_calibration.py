"""The workflow's calibration stage: a calibration-mask node feeding a scene's frames."""

from __future__ import annotations

import textwrap

import astropy.units as u
import numpy as np
import pytest

from mavispm.core.catalogue import read_catalogue
from mavispm.core.errors import ConfigError
from mavispm.core.products import read_product
from mavispm.simulate.optics.calibration_mask import read_recovered_distortion
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings
from mavispm.workflows.config import load_workflow
from mavispm.workflows.runner import run_workflow

TINY = """
[workflow]
name = "tiny_calibration"
seed = 3
executor = "serial"

[cluster]
preset = "ngc3201"
imbh_mass = 0
n_stars = 60
field_size = "1.2 arcsec"

[epochs]
times = [0]

[scene]
exptime = "30 s"
nexp = 2

[scene.detector]
nx = 200
ny = 200

[scene.render]
halo = false

[scene.optics.psf]
mode = "diffraction"
n_nodes = 1
stamp_size = "0.3 arcsec"
pixel_scale = "3.75 mas"
pupil_sampling = 32
psd_padding = 2.5

[scene.optics.halo]
enabled = false

[scene.optics.tiptilt]
enabled = false

[scene.optics.distortion]
enabled = true
static = "default"
corner_amplitude = "40 mas"

[outputs]
fits = false
plots = false
report = false

[scenes.raw]

[scenes.calibrated.calibration]
order = 5
centroid_noise = "0.02 mas"
"""


def _write(tmp_path, text, name="wf.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_calibrated_scene_renders_the_post_calibration_residual(tmp_path):
    wf = load_workflow(_write(tmp_path, TINY))
    result = run_workflow(wf, workdir=tmp_path / "work", progress=False)
    assert "calibration/calibrated" in result.ran
    assert not any(n.startswith("calibration/raw") for n in result.ran)
    calib = result.product("calibration/calibrated")
    attrs = read_product(calib, "calibration", load_arrays=False).attrs
    assert attrs["residual_rms"] < 0.05 * attrs["input_rms"]

    truth = {
        s: read_product(result.product(f"frames/{s}/e0"), "frames").tables["truth"]
        for s in ("raw", "calibrated")
    }
    cat = read_catalogue(result.product("cluster")).epochs["e0"]
    x_cat = truth["raw"]["x_cat"].to_value(u.arcsec)
    y_cat = truth["raw"]["y_cat"].to_value(u.arcsec)
    # the uncalibrated scene: the full static map (independently evaluated here)
    dist = Distortion(DistortionSettings(enabled=True, static="default", corner_amplitude=40.0))
    dx, dy = (1e3 * d for d in dist.displacement(x_cat, y_cat, 0.0))  # mas
    raw_dx = (truth["raw"]["x"].to_value(u.arcsec) - x_cat) * 1e3
    assert np.allclose(raw_dx, dx, atol=1e-9)
    # the calibrated scene: the map minus the recovered polynomial of the node's product
    rec = read_recovered_distortion(calib)
    cal = truth["calibrated"]
    assert np.array_equal(cal["id"], truth["raw"]["id"])
    rx, ry = rec.displacement_mas(x_cat, y_cat)
    cal_dx = (cal["x"].to_value(u.arcsec) - x_cat) * 1e3
    cal_dy = (cal["y"].to_value(u.arcsec) - y_cat) * 1e3
    assert np.allclose(cal_dx, dx - rx, atol=1e-9)
    assert np.allclose(cal_dy, dy - ry, atol=1e-9)
    assert len(cat) >= len(cal)

    again = run_workflow(wf, workdir=tmp_path / "work", progress=False)
    assert not again.ran  # everything cached, the calibration node included


@pytest.mark.parametrize(
    "extra, match",
    [
        ("[scenes.bad.calibration]\nn_holes = 1\n", "calibration.*n_holes"),
        ("[scenes.bad.calibration]\nholes = 15\n", "holes"),
        (
            "[scenes.bad.calibration]\n[scenes.bad.optics.distortion]\nenabled = false\n",
            "distortion.enabled is false",
        ),
        (
            '[scenes.bad.calibration]\n[scenes.bad.optics.distortion]\ncalibration = "c.h5"\n',
            "one of the two",
        ),
    ],
)
def test_bad_calibration_tables_are_refused_at_load(tmp_path, extra, match):
    with pytest.raises(ConfigError, match=match):
        load_workflow(_write(tmp_path, TINY + extra))


def test_rendered_mask_imaging_hands_the_scene_to_the_calibration_node(tmp_path):
    from mavispm.workflows.graph import expand

    text = TINY.replace("order = 5\n", 'order = 5\nimaging = "rendered"\n')
    nodes = expand(load_workflow(_write(tmp_path, text)))
    node = nodes["calibration/calibrated"]
    assert node.params["scene"]["detector"] == {"nx": 200, "ny": 200}
    assert "calibration" not in node.params["scene"]
    assert nodes["frames/calibrated/e0"].inputs["calibration"] == "calibration/calibrated"
    plain = expand(load_workflow(_write(tmp_path, TINY, "plain.toml")))
    assert "scene" not in plain["calibration/calibrated"].params  # analytic: distortion only
