"""Frames rendered with the real optics model (mavispm.simulate.optics.model), small and fast."""

import astropy.units as u
import numpy as np
import pytest
from optics_helpers import small_table
from render_helpers import epoch_table

from mavispm.core.catalogue import write_catalogue
from mavispm.core.errors import ConfigError
from mavispm.core.products import read_product
from mavispm.simulate.render import cli as render_cli
from mavispm.simulate.render.frame import render_frame


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("psfcache")


def _scene(**extra):
    optics = small_table()
    optics["halo"] = {"size": "0.9 arcsec"}
    return {
        "noise": False,
        "nexp": 2,
        "detector": {"nx": 160, "ny": 160},
        "optics": optics,
        **extra,
    }


def test_real_optics_frame_conserves_flux_with_halo(cache):
    scene = render_cli.validate_settings(_scene())
    optics = render_cli.build_scene_optics(scene, cache)
    assert optics.halo is not None and 0 < optics.halo.fraction < 1
    t = epoch_table([0.004], [-0.006], [18.0])
    frame = render_frame(t, 0 * u.yr, scene, optics, None)
    stars = frame.noiseless - frame.attrs["sky"].value
    assert stars.sum() == pytest.approx(frame.truth["flux"].value[0], rel=3e-3)
    assert frame.attrs["halo_fraction"] == pytest.approx(optics.halo.fraction)
    # the brightest pixel is the star's pixel
    iy, ix = np.unravel_index(np.argmax(stars), stars.shape)
    assert (ix, iy) == (round(frame.truth["x_pix"][0]), round(frame.truth["y_pix"][0]))


def test_real_optics_run_stage_and_bad_optics_key(tmp_path, cache):
    with pytest.raises(ConfigError, match="scene.optics.psf.n_nodez"):
        render_cli.validate_settings({"optics": {"psf": {"n_nodez": 3}}})
    cat = tmp_path / "cat.h5"
    write_catalogue(cat, {"e0": epoch_table([0.0, 0.3], [0.1, -0.2], [19.0, 21.0])})
    scene = _scene(noise=True)
    out = render_cli.run_stage(cat, "e0", scene, tmp_path / "f.h5", 4, cache_dir=cache)
    prod = read_product(out, "frames")
    assert prod.arrays["image"].shape == (160, 160)
    assert len(prod.tables["truth"]) == 2


def test_real_dynamic_distortion_sets_truth_positions(cache):
    optics_table = _scene()["optics"]
    optics_table["distortion"] = {"dynamic": True, "dynamic_amplitude": "2 mas"}
    scene = render_cli.validate_settings({**_scene(), "optics": optics_table})
    optics = render_cli.build_scene_optics(scene, cache)
    t = epoch_table([0.2, -0.3], [0.1, 0.25], [20.0, 20.0])
    frame = render_frame(t, 10.0 * u.yr, scene, optics, None)
    dx, dy = optics.distortion.displacement([0.2, -0.3], [0.1, 0.25], 10.0)
    assert np.any(np.abs(dx) > 0)
    np.testing.assert_allclose(frame.truth["x"].value - frame.truth["x_cat"].value, dx)
    np.testing.assert_allclose(frame.truth["y"].value - frame.truth["y_cat"].value, dy)


def test_documented_scene_example_is_valid():
    """The TOML example in docs/render.md parses and validates (defaults documented)."""
    import re
    import tomllib
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "render.md").read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    scene = render_cli.validate_settings(tomllib.loads(block))
    default = render_cli.validate_settings({})
    assert scene == default


def test_run_stage_caches_stamp_plans_and_halo_next_to_the_psf_grid(tmp_path, cache):
    """A second epoch (as from another process) loads the plans and halo, same frame."""
    from mavispm.simulate.render.frame import make_renderer

    cat = tmp_path / "cat.h5"
    write_catalogue(cat, {"e0": epoch_table([0.0, 0.3], [0.1, -0.2], [19.0, 21.0])})
    scene = _scene(noise=True)
    first = render_cli.run_stage(cat, "e0", scene, tmp_path / "a.h5", 4, cache_dir=cache)
    plans = sorted(cache.glob("stampplan-*.npz"))
    halos = sorted(cache.glob("halo-*.npz"))
    assert plans and len(halos) == 1
    again = render_cli.run_stage(cat, "e0", scene, tmp_path / "b.h5", 4, cache_dir=cache)
    image_a = read_product(first, "frames").arrays["image"]
    image_b = read_product(again, "frames").arrays["image"]
    assert np.array_equal(image_a, image_b)
    # the stored plans equal freshly computed ones; a corrupt file is recomputed
    settings = render_cli.validate_settings(scene)
    optics = render_cli.build_scene_optics(settings, cache)
    fresh = make_renderer(optics, settings)
    m = int(plans[0].stem.rsplit("-m", 1)[1])
    plans[0].write_bytes(b"not a zip file")
    cached = make_renderer(optics, settings, cache)
    for size in {m, *(int(p.stem.rsplit("-m", 1)[1]) for p in plans)}:
        a, b = fresh.plan(size), cached.plan(size)
        assert np.array_equal(a.target, b.target)
        assert np.allclose(a.transforms, b.transforms, rtol=0, atol=1e-12)
    assert render_cli.plan_cache_dir(optics) == cache
