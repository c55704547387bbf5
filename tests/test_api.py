"""The in-memory Python API (``import mavispm``) and the one Frame type."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import astropy.units as u
import numpy as np
import pytest
from astropy.coordinates import SkyCoord
from optics_helpers import small_table
from render_helpers import epoch_table

import mavispm
from mavispm.core.catalogue import read_catalogue, write_catalogue
from mavispm.core.errors import InputError
from mavispm.core.frame import Frame
from mavispm.core.products import read_product
from mavispm.measure.stars import cli as stars_cli
from mavispm.measure.stars.measure_frame import read_frame
from mavispm.simulate.render import cli as render_cli

ROOT = Path(__file__).resolve().parents[1]


def test_import_mavispm_is_lazy():
    """``import mavispm`` loads no stage (nor astropy.table); first use loads it."""
    code = (
        "import sys, mavispm; print([m for m in ('mavispm.api', 'astropy.table', "
        "'numpy', 'mavispm.measure.stars.cli') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert mavispm.measure_stars.__module__ == "mavispm.measure.stars.cli"
    assert "fit_dynamics" in dir(mavispm)
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        mavispm.nonexistent  # noqa: B018


@pytest.fixture(scope="module")
def scene_and_catalogue(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api")
    rng = np.random.default_rng(4)
    g = (np.arange(6) - 2.5) * 0.2
    xx, yy = np.meshgrid(g, g)
    x = xx.ravel() + rng.uniform(-0.02, 0.02, xx.size)
    y = yy.ravel() + rng.uniform(-0.02, 0.02, xx.size)
    mag = rng.uniform(17.0, 21.0, xx.size)
    path = tmp / "cat.h5"
    write_catalogue(path, {"e0": epoch_table(x, y, mag)}, attrs={"distance": 4.6 * u.kpc})
    scene = {"nexp": 4, "detector": {"nx": 180, "ny": 180}, "optics": small_table()}
    return tmp, scene, path


def test_render_and_measure_in_memory_equal_the_products(scene_and_catalogue):
    """Rendering and measuring in memory give the numbers the command-line products hold;
    the measured positions agree with the rendered truth within their errors."""
    tmp, scene, cat_path = scene_and_catalogue
    cache = tmp / "cache"
    optics = render_cli.build_scene_optics(render_cli.scene_from_mapping(scene), cache)
    cat = read_catalogue(cat_path)
    frame = mavispm.render_epoch(cat, "e0", scene, optics, seed=3)
    assert isinstance(frame, Frame)
    frames_path = render_cli.run_stage(cat_path, "e0", scene, tmp / "f.h5", 3, optics=optics)
    on_disk = read_frame(frames_path)
    np.testing.assert_array_equal(frame.adu, on_disk.adu)
    np.testing.assert_array_equal(frame.image, on_disk.image)
    assert frame.attrs["distance"] == on_disk.attrs["distance"]

    # the NDData view round-trips to the same frame (photutils-style input)
    back = Frame.from_nddata(frame.to_nddata(), truth=frame.truth)
    np.testing.assert_array_equal(back.image, frame.image)
    np.testing.assert_array_equal(back.bad, frame.bad)
    assert back.sky == frame.sky and back.read_noise_var == frame.read_noise_var

    settings = {"psf_variation": "constant", "psf_stars_per_node": 20, "epsf_size": 21}
    stars, psf = mavispm.measure_stars(frame, settings, seed=0)
    out = stars_cli.run_stage(frames_path, settings, tmp / "m.h5", seed=0)
    product = read_product(out, "measured")
    for col in ("x", "y", "x_err", "flux", "flag"):
        np.testing.assert_array_equal(
            np.asarray(stars[col]), np.asarray(product.tables["stars"][col])
        )
    assert stars.meta["epoch"] == 0 * u.yr and stars["x"].unit == u.arcsec

    good = np.asarray(stars["flag"]) == 0
    assert good.sum() >= 30
    # measured magnitudes follow the input ones, fainter by the light outside the ePSF
    # footprint (the seeing halo): -2.5 log10 of the fitted / true flux fraction
    offset = -2.5 * np.log10(stars.meta["epsf_flux_fraction"])
    bright = good & (stars["mag"] < 19 * u.mag)
    dmag = (stars["mag_fit"] - stars["mag"]).to_value(u.mag)[bright]
    assert abs(np.median(dmag) - offset) < 0.02 and np.std(dmag) < 0.05
    dx = ((stars["x"] - stars["x_true"]) / stars["x_err"]).decompose().value[good]
    dy = ((stars["y"] - stars["y_true"]) / stars["y_err"]).decompose().value[good]
    # normalised residuals: unbiased and of about unit width (the errors describe the scatter)
    assert abs(np.median(dx)) < 1.0 and abs(np.median(dy)) < 1.0
    assert 0.4 < np.std(np.r_[dx, dy]) < 2.5


def test_frame_nddata_and_wcs_against_spherical_geometry():
    """The frame's WCS puts the field centre at (ra_center, dec_center) and one pixel
    east of it (x decreasing) one pixel scale away on the sky."""
    attrs = {
        "gain": 2.0 * u.electron / u.adu,
        "read_noise": 3.0 * u.electron,
        "sky": 40.0 * u.electron,
        "saturation": 6e4 * u.adu,
        "pixel_scale": 7.5 * u.mas,
        "epoch": 10.0 * u.yr,
        "nexp": 4,
        "ra_center": 154.4 * u.deg,
        "dec_center": -46.41 * u.deg,
    }
    image = np.arange(11 * 9, dtype=np.float32).reshape(11, 9)
    frame = Frame.from_attrs(image, None, attrs)
    nd = frame.to_nddata()
    assert nd.unit == u.adu
    np.testing.assert_array_equal(nd.data, image)
    centre = nd.wcs.pixel_to_world((9 - 1) / 2, (11 - 1) / 2)
    assert centre.separation(SkyCoord(154.4 * u.deg, -46.41 * u.deg)).to_value(u.uarcsec) < 1
    west = nd.wcs.pixel_to_world((9 - 1) / 2 + 1, (11 - 1) / 2)
    assert centre.separation(west).to_value(u.mas) == pytest.approx(7.5, rel=1e-6)
    assert west.ra < centre.ra  # x (columns) grows towards the west
    north = nd.wcs.pixel_to_world((9 - 1) / 2, (11 - 1) / 2 + 1)
    assert north.dec > centre.dec
    with pytest.raises(InputError, match="pixel_scale"):
        Frame.from_attrs(image, None, {k: v for k, v in attrs.items() if k != "pixel_scale"})


def _readme_block() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Python API", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1
    return blocks[0]


def test_readme_python_api_runs_as_written(tmp_path, monkeypatch):
    """The README's Python API block chains the whole pipeline in memory in under a minute
    (4-14 s: not slow, so that the block cannot break unseen; it did once, when the
    default velocity law came to need the nested evidences the block had switched off)."""
    monkeypatch.setenv("MAVISPM_CACHE", str(tmp_path / "cache"))
    namespace: dict = {}
    t0 = time.perf_counter()
    exec(compile(_readme_block(), "README.md", "exec"), namespace)
    wall = time.perf_counter() - t0
    assert wall < 60, f"README chain took {wall:.1f} s"
    pm, fit = namespace["pm"], namespace["fit"]
    assert pm["pm_x"].unit == u.mas / u.yr and len(pm) > 50
    # the measured motions follow the catalogue's (scored against the truth columns)
    assert pm.meta["pm_rms_true"] < 0.2 * u.mas / u.yr
    assert np.isfinite(fit.attrs["bh_mass_median"].value)


@pytest.mark.parametrize(
    "module",
    [
        "mavispm.core.frame",
        "mavispm.api",
        "mavispm.measure.stars.settings",
        "mavispm.measure.propermotions.cli",
    ],
)
def test_docstring_examples(module):
    """The doctest'd examples of the API modules run as written."""
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0
