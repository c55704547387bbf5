"""The Optics facade, its settings and the ``simulate optics`` CLI stage."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from optics_helpers import small_settings, small_table

from mavispm.core.errors import ConfigError
from mavispm.core.products import open_product
from mavispm.simulate.optics import cli as optics_cli
from mavispm.simulate.optics.model import build_optics, validate_settings
from mavispm.workflows.cli import main


@pytest.fixture(scope="module")
def optics(tmp_path_factory):
    return build_optics(
        small_settings(), cache_dir=tmp_path_factory.mktemp("cache"), progress=False
    )


def test_unknown_and_bad_keys_named():
    with pytest.raises(ConfigError, match="scene.optics.psf.pixl_scale"):
        validate_settings({"psf": {"pixl_scale": 2.0}})
    with pytest.raises(ConfigError, match="scene.optics.tiptilt.asterism"):
        validate_settings({"tiptilt": {"asterism": "great"}})
    with pytest.raises(ConfigError, match="Nyquist"):
        build_optics(validate_settings({"psf": {"pixel_scale": "10 mas"}}))
    s = validate_settings({"psf": {"wavelength": "0.7 um"}, "blur": {"vibration": False}})
    assert s.psf.wavelength == pytest.approx(700.0)


def test_settings_round_trip():
    from mavispm.core.config import to_mapping
    from mavispm.simulate.optics.model import OpticsSettings

    table = {
        "tiptilt": {"asterism": "custom", "ngs": [[10, 0, 15], [20, 90, 17]]},
        "distortion": {"static": "polynomial", "coefficients_x": [[1, 0, 0.1]]},
    }
    s = validate_settings(table)
    assert s.tiptilt.ngs == ((10.0, 0.0, 15.0), (20.0, 90.0, 17.0))
    assert validate_settings(to_mapping(s)) == s
    assert validate_settings(to_mapping(OpticsSettings())) == OpticsSettings()


def test_contract(optics):
    g = optics.psf_grid
    assert g.cube.ndim == 4 and g.cube.shape[:2] == (3, 3) and g.n % 2 == 1
    np.testing.assert_allclose(g.cube.sum(axis=(-2, -1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(g.nodes_x, [-15, 0, 15])
    assert g.pixel_scale == pytest.approx(3.75)
    assert not g.is_static
    assert g.psf_at(3.3, -7.1).sum() == pytest.approx(1.0)
    iy, ix, w = g.bilinear_weights(np.array([0.0, 7.5]), np.array([0.0, 0.0]))
    assert iy.shape == ix.shape == w.shape == (2, 4)
    # halo
    assert 0 < optics.halo.fraction < 1
    k = optics.halo.kernel(7.5)
    assert k.shape[0] % 2 == 1 and k.shape[0] == k.shape[1]
    assert k.sum() == pytest.approx(optics.halo.fraction, rel=1e-9)
    c = (k.shape[0] - 1) // 2
    assert k[c, c] == 0.0  # nothing inside the control radius
    # kernels
    x, y = np.array([0.0, 10.0]), np.array([0.0, -5.0])
    kc = optics.kernel_covariance(x, y)
    np.testing.assert_allclose(
        kc, optics.tiptilt.covariance(x, y) + optics.blur_sigma**2 * np.eye(2)
    )
    assert optics.blur_sigma == pytest.approx(np.hypot(3.0, 3.5))
    dx, dy = optics.distortion.displacement(x, y, 0.0)
    assert dx.shape == (2,) and optics.distortion.enabled


def test_halo_off_gives_none_and_untapered(tmp_path):
    table = small_table()
    table["halo"] = {"enabled": False}
    o = build_optics(validate_settings(table), cache_dir=tmp_path, progress=False)
    assert o.halo is None
    assert o.psf_grid.cube[1, 1].max() > 0


def test_run_stage_and_cli(tmp_path):
    out = optics_cli.run_stage(
        small_table(n_nodes=2), tmp_path / "grid.h5", cache_dir=tmp_path / "c", progress=False
    )
    with open_product(out, "psfgrid") as f:
        assert f["cube"].shape[:2] == (2, 2)
        assert float(f.attrs["pixel_scale"]) == pytest.approx(3.75)
    scene = tmp_path / "scene.toml"
    scene.write_text(
        "[scene.optics.psf]\nn_nodes = 2\npupil_sampling = 32\npsd_padding = 2.5\n"
        'stamp_size = "0.3 arcsec"\npixel_scale = "3.75 mas"\n'
        '[scene.optics.halo]\nsize = "4 arcsec"\n'
    )
    rc = main(
        [
            "simulate",
            "optics",
            "--scene",
            str(scene),
            "-o",
            str(tmp_path / "g2.h5"),
            "--plots",
            str(tmp_path / "plots"),
            "--cache-dir",
            str(tmp_path / "c"),
            "--quiet",
        ]
    )
    assert rc == 0
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert pngs == [
        "distortion_map.png",
        "psf_grid.png",
        "psf_profile.png",
        "tiptilt_kernel_map.png",
        "tiptilt_map.png",
    ]
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene.optics.psf]\nwavelenght = 500\n")
    assert main(["simulate", "optics", "--scene", str(bad), "-o", str(tmp_path / "x.h5")]) == 2


def test_product_holds_tt_kernel_map(tmp_path):
    table = small_table(n_nodes=3)
    table["tiptilt"] = {"asterism": "bad", "scale_factor": 3.0}
    table["atmosphere"] = {"seeing": "0.7 arcsec", "zenith_angle": "20 deg"}
    out = optics_cli.run_stage(table, tmp_path / "g.h5", cache_dir=tmp_path / "c", progress=False)
    optics = build_optics(validate_settings(table), cache_dir=tmp_path / "c", progress=False)
    with open_product(out, "psfgrid") as f:
        major = np.asarray(f["tt_sigma_major"])
        minor = np.asarray(f["tt_sigma_minor"])
        angle = np.asarray(f["tt_angle"])
        assert f["tt_sigma_major"].attrs["unit"] == "mas"
        assert f["tt_angle"].attrs["unit"] == "deg"
        nx, ny = np.asarray(f["nodes_x"]), np.asarray(f["nodes_y"])
        assert float(f.attrs["seeing"]) == pytest.approx(0.7)
        assert float(f.attrs["zenith_angle"]) == pytest.approx(20.0)
        assert f.attrs["asterism"] == "bad"
        assert float(f.attrs["tt_scale_factor"]) == pytest.approx(3.0)
    assert major.shape == minor.shape == angle.shape == (3, 3)
    assert np.all(major >= minor) and np.all(minor > 0)
    assert np.all((angle >= 0) & (angle < 180))
    # the three numbers rebuild the covariance of the TT field at every node
    gx, gy = np.meshgrid(nx, ny)
    cov = optics.tiptilt.covariance(gx.ravel(), gy.ravel())
    t = np.radians(angle.ravel())
    u1 = np.stack([np.cos(t), np.sin(t)], -1)
    u2 = np.stack([-np.sin(t), np.cos(t)], -1)
    rebuilt = (major.ravel() ** 2)[:, None, None] * np.einsum("ni,nj->nij", u1, u1) + (
        minor.ravel() ** 2
    )[:, None, None] * np.einsum("ni,nj->nij", u2, u2)
    np.testing.assert_allclose(rebuilt, cov, rtol=1e-6, atol=1e-9)


def test_file_mode_through_facade(tmp_path):
    hdus = [fits.PrimaryHDU()]
    hdus[0].header["PIXSCALE"] = (2.0, "[mas]")
    for y in (-10.0, 10.0):
        for x in (-10.0, 10.0):
            yy, xx = np.indices((65, 65)) - 32
            h = fits.ImageHDU(np.exp(-0.5 * (xx**2 + yy**2) / 16.0))
            h.header.update({"XPOS": x, "YPOS": y, "LAMBDA": 550e-9})
            hdus.append(h)
    path = tmp_path / "db.fits"
    fits.HDUList(hdus).writeto(path)
    table = small_table(mode="file", file=str(path))
    o = build_optics(validate_settings(table), cache_dir=tmp_path, progress=False)
    assert o.psf_grid.cube.shape[:2] == (2, 2)
    np.testing.assert_allclose(o.psf_grid.nodes_x, [-10, 10])
