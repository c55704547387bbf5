"""Whole frames: flux, halo, distortion truth, edges, determinism, bad input, CLI."""

from contextlib import contextmanager

import astropy.units as u
import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from hypothesis import given, settings
from hypothesis import strategies as st
from render_helpers import PolynomialDistortion, RingHalo, epoch_table, make_optics

from mavispm.core.catalogue import write_catalogue
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.products import read_product
from mavispm.simulate.render import cli as render_cli
from mavispm.simulate.render.frame import make_renderer, render_frame
from mavispm.simulate.render.scene import scene_from_mapping
from mavispm.simulate.render.zero_point import star_electrons

NOISELESS = {"noise": False, "nexp": 2, "detector": {"nx": 64, "ny": 64}}


@contextmanager
def float64_frames():
    """Frames accumulated in float64, for identities tested far below float32 round-off
    (``test_float32_frame_round_off_is_far_below_the_photon_noise`` bounds that)."""
    from mavispm.simulate.render import frame as frame_module

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(frame_module, "FRAME_DTYPE", np.float64)
        yield


@pytest.fixture(scope="module")
def optics():
    return make_optics("airy", stretch=0.03)


def _stars_only(frame, scene):
    sky = frame.attrs["sky"].value
    return frame.noiseless - sky


def test_isolated_star_flux_and_truth(optics):
    scene = scene_from_mapping(NOISELESS)
    frame = render_frame(epoch_table([0.0123], [-0.031], [18.0]), 0 * u.yr, scene, optics, None)
    flux = star_electrons([18.0], scene.photometry, 60 * u.s).value[0]
    assert frame.truth["flux"].to_value(u.electron)[0] == pytest.approx(flux)
    assert _stars_only(frame, scene).sum() == pytest.approx(flux, rel=1e-4)
    assert frame.truth["x_pix"][0] == pytest.approx(0.0123 / 0.0075 + 31.5)
    assert frame.adu.dtype == np.float32


def test_halo_conserves_flux_when_inside_the_frame():
    optics = make_optics("airy", halo=RingHalo(fraction=0.25, r_c=60.0, extent=400.0))
    for down in (1, 4):
        scene = scene_from_mapping(
            {**NOISELESS, "detector": {"nx": 160, "ny": 160}, "render": {"halo_downsample": down}}
        )
        frame = render_frame(epoch_table([0.01], [0.02], [17.0]), 0 * u.yr, scene, optics, None)
        flux = frame.truth["flux"].to_value(u.electron)[0]
        tol = 1e-4 if down == 1 else 2e-3
        assert _stars_only(frame, scene).sum() == pytest.approx(flux, rel=tol)
        assert frame.attrs["halo_fraction"] == pytest.approx(0.25)
    # switching the halo off keeps all flux in the core
    off = scene_from_mapping({**NOISELESS, "render": {"halo": False}})
    frame = render_frame(epoch_table([0.0], [0.0], [17.0]), 0 * u.yr, off, optics, None)
    assert frame.attrs["halo_fraction"] == 0.0


def test_distortion_moves_rendered_positions(optics):
    dist = make_optics("airy", distortion=PolynomialDistortion(a=0.01, b=0.005, c=0.002))
    scene = scene_from_mapping({**NOISELESS, "detector": {"nx": 96, "ny": 96}})
    t = epoch_table([0.1], [0.05], [16.0])
    frame = render_frame(t, 2.0 * u.yr, scene, dist, None)
    row = frame.truth[0]
    dx = 0.01 * 0.1 * 0.05
    dy = 0.005 * (0.1**2 - 0.05**2) + 0.002 * 2.0
    assert row["x"].value == pytest.approx(0.1 + dx)
    assert row["y"].value == pytest.approx(0.05 + dy)
    assert row["x_cat"].value == pytest.approx(0.1)
    img = _stars_only(frame, scene)
    yy, xx = np.mgrid[0:96, 0:96]
    assert (img * xx).sum() / img.sum() == pytest.approx(row["x_pix"], abs=2e-3)
    assert (img * yy).sum() / img.sum() == pytest.approx(row["y_pix"], abs=2e-3)


@pytest.fixture(scope="module")
def shared_renderer(optics):
    return make_renderer(optics, scene_from_mapping(NOISELESS))


@settings(max_examples=20, deadline=None)
@given(
    pos=st.lists(
        st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(10.0, 30.0)),
        min_size=0,
        max_size=5,
    )
)
def test_small_frame_is_crop_of_large_frame(optics, shared_renderer, pos):
    """Stars on edges, corners and outside: a small frame is exactly a crop of a big one."""
    x, y, mag = (np.array(v, dtype=float) for v in zip(*pos)) if pos else ([], [], [])
    t = epoch_table(x, y, mag)
    small = scene_from_mapping(NOISELESS)
    big = scene_from_mapping({**NOISELESS, "detector": {"nx": 160, "ny": 160}})
    with float64_frames():
        fs = render_frame(t, 0 * u.yr, small, optics, None, renderer=shared_renderer)
        fb = render_frame(t, 0 * u.yr, big, optics, None, renderer=shared_renderer)
    crop = fb.noiseless[48:112, 48:112]
    assert np.all(np.isfinite(fs.noiseless))
    # A position on a half-pixel boundary gets the same stamp in both frames although
    # x_pix differs by the round-off of the frame-centre offset (render.stamp_centre);
    # without that, stars such as (0, -5e-17, 15 mag) differed by up to 6e-7 of the peak.
    atol = max(1e-6, 1e-9 * float(np.max(fb.noiseless, initial=0.0)))
    np.testing.assert_allclose(fs.noiseless, crop, rtol=1e-9, atol=atol)
    assert set(fs.truth["id"]) <= set(fb.truth["id"])


def test_extreme_fluxes_coincident_stars_and_empty(optics):
    scene = scene_from_mapping({**NOISELESS, "noise": True})
    # a 1e10-photon star: saturated core, finite everywhere
    mag_1e10 = 18.0 - 2.5 * np.log10(
        1e10 / star_electrons([18.0], scene.photometry, 30 * u.s).value[0]
    )
    frame = render_frame(epoch_table([0.0], [0.0], [mag_1e10]), 0 * u.yr, scene, optics, rng())
    assert frame.saturated[31:33, 31:33].all()
    assert np.isfinite(frame.adu).all()
    assert frame.adu.max() == pytest.approx(2 * 65535.0)
    # a star too faint to matter and an empty catalogue give sky-only frames
    for t in (epoch_table([0.0], [0.0], [60.0]), epoch_table([], [], [])):
        f = render_frame(t, 0 * u.yr, scene, optics, rng())
        assert f.image.mean() == pytest.approx(f.attrs["sky"].value, rel=0.05)
    # coincident stars add
    with float64_frames():
        one = render_frame(epoch_table([0.0], [0.0], [19.0]), 0 * u.yr, scene_nl(), optics, None)
        two = render_frame(
            epoch_table([0, 0], [0, 0], [19, 19]), 0 * u.yr, scene_nl(), optics, None
        )
    sky = one.attrs["sky"].value
    np.testing.assert_allclose(two.noiseless - sky, 2 * (one.noiseless - sky), rtol=1e-9, atol=1e-6)


def test_float32_frame_round_off_is_far_below_the_photon_noise(monkeypatch):
    """The frame accumulates sky, halo and stars in float32 (``frame.FRAME_DTYPE``): its
    noise-free stack differs from the same frame accumulated in float64 (brute-force
    reference: every add in float64) by a few float32 spacings of the pixel values, below
    1e-3 of each unsaturated pixel's photon noise sqrt(stack electrons); the mask and truth
    are equal."""
    from mavispm.simulate.render import frame as frame_module

    optics = make_optics("airy", halo=RingHalo(fraction=0.25, r_c=60.0, extent=400.0))
    r = np.random.default_rng(11)
    n = 80
    x, y = r.uniform(-0.2, 0.2, n), r.uniform(-0.2, 0.2, n)
    mag = r.uniform(12.0, 24.0, n)
    x[:4], y[:4], mag[:4] = 0.01, -0.02, [13.0, 13.5, 14.0, 15.0]  # bright, coincident
    t = epoch_table(x, y, mag)
    scene = scene_from_mapping({"noise": False, "nexp": 120, "detector": {"nx": 96, "ny": 96}})
    renderer = make_renderer(optics, scene)
    f32 = render_frame(t, 0 * u.yr, scene, optics, None, renderer=renderer)
    monkeypatch.setattr(frame_module, "FRAME_DTYPE", np.float64)
    f64 = render_frame(t, 0 * u.yr, scene, optics, None, renderer=renderer)
    assert f32.noiseless.dtype == np.float32 and f64.noiseless.dtype == np.float64
    err = np.abs(f32.noiseless.astype(float) - f64.noiseless)
    assert err.max() > 0  # really float32
    # float32 spacing of the per-sub-exposure values the frame holds, in stack electrons
    ulp = 120 * np.spacing((f64.noiseless / 120).astype(np.float32)).astype(float)
    assert np.all(err <= 4 * ulp)
    # below saturation (the sub-exposure's full well), 4 spacings are < 1e-3 of the noise
    ok = ~f64.saturated
    assert f64.saturated.any() and ok.sum() > 0.5 * ok.size  # saturated cores
    assert np.max(err[ok] / np.sqrt(f64.noiseless[ok])) <= 1e-3
    np.testing.assert_array_equal(f32.saturated, f64.saturated)
    np.testing.assert_array_equal(np.asarray(f32.truth["x_pix"]), np.asarray(f64.truth["x_pix"]))


def test_singular_tiptilt_covariance(optics):
    from render_helpers import ConstantTipTilt

    sharp = make_optics("airy", tiptilt=ConstantTipTilt(0.0, 0.0, 0.0), blur_sigma=0.0)
    frame = render_frame(epoch_table([0.003], [0.0], [18.0]), 0 * u.yr, scene_nl(), sharp, None)
    img = frame.noiseless - frame.attrs["sky"].value
    assert np.isfinite(img).all()
    assert img.sum() == pytest.approx(frame.truth["flux"].value[0], rel=1e-4)


def scene_nl():
    return scene_from_mapping(NOISELESS)


def rng():
    return np.random.default_rng(0)


# ----------------------------------------------------------------- stage / CLI


@pytest.fixture
def catalogue(tmp_path):
    r = np.random.default_rng(3)
    t = epoch_table(r.uniform(-0.3, 0.3, 20), r.uniform(-0.3, 0.3, 20), r.uniform(15, 24, 20))
    t2 = t.copy()
    t2.meta["epoch"] = 10.0 * u.yr
    path = tmp_path / "cat.h5"
    write_catalogue(path, {"e0": t, "e1": t2}, attrs={"ra_center": 154.4 * u.deg})
    return path


@pytest.fixture
def fake_optics_module(monkeypatch, optics):
    class Module:
        @staticmethod
        def validate_settings(mapping, source=None):
            if mapping.get("bad"):
                raise ConfigError("unknown key", key="optics.bad", source=source)
            return dict(mapping)

        @staticmethod
        def build_optics(settings, cache_dir=None, progress=False):
            return optics

    monkeypatch.setattr(render_cli, "_optics_module", lambda: Module)
    return Module


SCENE = {"nexp": 3, "detector": {"nx": 64, "ny": 64}}


def test_run_stage_writes_frames_product_and_fits(tmp_path, catalogue, fake_optics_module):
    out = render_cli.run_stage(catalogue, "e1", SCENE, tmp_path / "f.h5", 7, tmp_path / "f.fits")
    prod = read_product(out, "frames")
    assert prod.arrays["image"].unit == u.adu
    assert prod.arrays["image"].shape == (64, 64)
    assert prod.attrs["epoch"] == 10 * u.yr and prod.attrs["nexp"] == 3
    assert prod.attrs["saturation"] == 65535 * u.adu
    truth = prod.tables["truth"]
    for col in ("id", "x_pix", "y_pix", "x", "y", "x_cat", "y_cat", "flux", "mag"):
        assert col in truth.colnames
    with fits.open(tmp_path / "f.fits") as hdul:
        hdr = hdul[0].header
        assert hdr["NCOMBINE"] == 3 and hdr["PIXSCALE"] == pytest.approx(0.0075)
        assert "EPOCH" not in hdr and hdr["EQUINOX"] == 2000.0 and hdr["RADESYS"] == "ICRS"
        assert hdr["MVEPOCH"] == 10.0 and hdr["EXPTIME"] == pytest.approx(3 * 30.0)
        assert hdr["TELESCOP"] == "ESO-VLT-U4" and hdr["INSTRUME"] == "MAVIS"
        for key in ("FILTER", "OBJECT", "DATE", "ORIGIN"):
            assert hdr[key]
        # DATE-OBS and MJD-OBS: 10 Julian years after epoch zero
        assert hdr["MJD-OBS"] == pytest.approx(62502.0 + 3652.5)  # MJD 62502 = 2030-01-01
        assert hdr["DATE-OBS"] == "2040-01-01T12:00:00"
        # the saturation mask carries the same WCS
        mask_wcs = WCS(hdul["SATURATED"].header)
        np.testing.assert_allclose(
            mask_wcs.wcs_pix2world([[3.0, 7.0]], 0), WCS(hdr).wcs_pix2world([[3.0, 7.0]], 0)
        )
        np.testing.assert_array_equal(hdul[0].data, prod.arrays["image"].value)
        wcs = WCS(hdr)
        ra, dec = wcs.wcs_pix2world([[31.5, 31.5]], 0)[0]
        assert ra == pytest.approx(154.4) and dec == pytest.approx(0.0)
    again = render_cli.run_stage(catalogue, "e1", SCENE, tmp_path / "g.h5", 7)
    np.testing.assert_array_equal(read_product(again).arrays["image"], prod.arrays["image"])
    other = render_cli.run_stage(catalogue, "e0", SCENE, tmp_path / "h.h5", 7)
    assert not np.array_equal(read_product(other).arrays["image"], prod.arrays["image"])


def test_bad_inputs_give_clear_errors_and_no_file(tmp_path, catalogue, fake_optics_module):
    with pytest.raises(ConfigError, match="pixel_scal"):
        render_cli.validate_settings({"detector": {"pixel_scal": 7.5}})
    with pytest.raises(ConfigError, match="detector.pixel_scale"):
        render_cli.validate_settings({"detector": {"pixel_scale": "7.5 s"}})
    with pytest.raises(ConfigError, match="optics.bad"):
        render_cli.validate_settings({"optics": {"bad": 1}})
    with pytest.raises(InputError, match="e7"):
        render_cli.run_stage(catalogue, "e7", SCENE, tmp_path / "x.h5", 1)
    nomag = tmp_path / "nomag.h5"
    from mavispm.core.products import read_product, write_product

    prod = read_product(catalogue, "catalogue")
    tables = dict(prod.tables)
    tables["epochs/e0"] = tables["epochs/e0"][
        [c for c in tables["epochs/e0"].colnames if c != "mag"]
    ]
    write_product(nomag, "catalogue", tables=tables, attrs=prod.attrs)
    with pytest.raises(InputError, match="mag"):
        render_cli.run_stage(nomag, "e0", SCENE, tmp_path / "y.h5", 1)
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "y.h5").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_cli_renders_one_and_all_epochs(tmp_path, catalogue, fake_optics_module, capsys):
    from mavispm.workflows.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text('nexp = 2\n[detector]\nnx = 48\nny = 48\npixel_scale = "7.36 mas"\n')
    rc = main(
        ["simulate", "frames", str(catalogue), "--scene", str(scene), "--epoch", "e0",
         "-o", str(tmp_path / "one.h5"), "--fits", str(tmp_path / "one.fits")]
    )  # fmt: skip
    assert rc == 0 and (tmp_path / "one.fits").exists()
    assert read_product(tmp_path / "one.h5").attrs["pixel_scale"] == 7.36 * u.mas
    rc = main(
        ["simulate", "frames", str(catalogue), "--scene", str(scene), "--epoch", "all",
         "-o", str(tmp_path / "all"), "--fits-dir", str(tmp_path / "fits")]
    )  # fmt: skip
    assert rc == 0
    assert sorted(p.name for p in (tmp_path / "all").iterdir()) == ["frames_e0.h5", "frames_e1.h5"]
    assert len(list((tmp_path / "fits").iterdir())) == 2
    scene.write_text("nexpp = 2\n")
    rc = main(["simulate", "frames", str(catalogue), "--scene", str(scene), "-o", "z.h5"])
    assert rc == 2
    assert "nexp" in capsys.readouterr().err


def test_result_does_not_depend_on_thread_count(optics):
    t = epoch_table([0.0, 0.1, -0.2], [0.05, -0.1, 0.2], [16.0, 18.0, 20.0])
    images = []
    for threads in (1, 2):
        scene = scene_from_mapping(
            {"nexp": 3, "detector": {"nx": 600, "ny": 600}, "render": {"threads": threads}}
        )
        frame = render_frame(t, 0 * u.yr, scene, optics, np.random.default_rng(9))
        images.append(frame.image)
    np.testing.assert_array_equal(images[0], images[1])


def test_sky_only_frame_variance_is_mean_plus_read_noise(optics):
    for gain, nexp in ((1.0, 1), (2.0, 5)):
        scene = scene_from_mapping(
            {"nexp": nexp, "detector": {"nx": 300, "ny": 300, "gain": gain, "read_noise": 3.0}}
        )
        frame = render_frame(epoch_table([], [], []), 0 * u.yr, scene, optics, rng())
        e = frame.adu.astype(float) * gain
        sky = frame.attrs["sky"].to_value(u.electron)
        var = sky + nexp * 9.0
        assert e.mean() == pytest.approx(sky, abs=5 * np.sqrt(var / e.size))
        assert e.var() == pytest.approx(var, rel=0.02)
