"""MAVISIM-format PSF FITS databases."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.errors import InputError
from mavispm.simulate.optics.psf_fits import read_mavisim_psfs


def gaussian(n, sigma_pix, dx=0.0):
    c = n // 2
    y, x = np.indices((n, n))
    return np.exp(-0.5 * (((x - c - dx) / sigma_pix) ** 2 + ((y - c) / sigma_pix) ** 2))


def write_db(
    path,
    positions,
    n=64,
    scale_key=True,
    drop=None,
    nan=False,
    lam=5.5e-7,
    scale=2.0,
    comment=None,
    key="PIXSCALE",
    sigma0=4.0,
):
    hdus = [fits.PrimaryHDU()]
    if scale_key:
        hdus[0].header[key] = (scale, comment) if comment else scale
    for k, (x, y) in enumerate(positions):
        sigma = sigma0 + 0.1 * (abs(x) + abs(y))
        img = gaussian(n, sigma)
        if nan and k == 1:
            img[3, 3] = np.nan
        h = fits.ImageHDU(img)
        for key, val in (("XPOS", x), ("YPOS", y), ("LAMBDA", lam)):
            if key != drop:
                h.header[key] = val
        hdus.append(h)
    fits.HDUList(hdus).writeto(path)
    return path


GRID = [(x, y) for y in (-15.0, 15.0) for x in (-15.0, 0.0, 15.0)]


def test_reads_grid_and_resamples(tmp_path):
    path = write_db(tmp_path / "db.fits", GRID)
    cube, xs, ys, lam = read_mavisim_psfs(path, pixel_scale=2.0, stamp_size_mas=81.0)
    assert cube.shape == (2, 3, 41, 41)
    np.testing.assert_array_equal(xs, [-15.0, 0.0, 15.0])
    np.testing.assert_array_equal(ys, [-15.0, 15.0])
    assert lam == pytest.approx(550.0)
    np.testing.assert_allclose(cube.sum(axis=(-2, -1)), 1.0, atol=1e-12)
    # the Gaussian at (0, -15) had sigma 5.5 file pixels = 11 mas -> 5.5 new pixels
    psf = cube[0, 1]
    y, x = np.indices(psf.shape) - 20
    assert np.sqrt((psf * x**2).sum()) == pytest.approx(5.5, rel=0.02)
    assert (psf * x).sum() == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"drop": "XPOS"}, "lacks header keyword XPOS"),
        ({"drop": "LAMBDA"}, "lacks header keyword LAMBDA"),
        ({"nan": True}, "NaN"),
        ({"scale_key": False}, "no positive pixel scale"),
    ],
)
def test_bad_databases_named(tmp_path, kwargs, message):
    path = write_db(tmp_path / "bad.fits", GRID, **kwargs)
    with pytest.raises(InputError, match=message) as err:
        read_mavisim_psfs(path, 2.0, 41.0)
    assert "bad.fits" in str(err.value)


def test_inconsistent_grid(tmp_path):
    path = write_db(tmp_path / "holes.fits", GRID[:-1])
    with pytest.raises(InputError, match="inconsistent grid"):
        read_mavisim_psfs(path, 2.0, 41.0)


def test_not_fits(tmp_path):
    path = tmp_path / "junk.fits"
    path.write_text("not a fits file")
    with pytest.raises(InputError, match="junk.fits"):
        read_mavisim_psfs(path, 2.0, 41.0)


def test_pixel_scale_in_arcsec_is_refused_with_the_reason(tmp_path):
    """A MAVISIM-style PIXSIZE = 0.00375 (arcsec) read as mas would give delta functions."""
    path = write_db(tmp_path / "arcsec.fits", GRID, key="PIXSIZE", scale=0.00375)
    with pytest.raises(InputError, match="narrower than 0.85 lambda/D") as err:
        read_mavisim_psfs(path, 2.0, 41.0)
    msg = str(err.value)
    assert "PIXSIZE = 0.00375 mas" in msg and "arcsec" in msg and "arcsec.fits" in msg


@pytest.mark.parametrize(
    "kwargs",
    [
        {"comment": "[arcsec] pixel scale"},
        {"comment": "pixel size in arcseconds"},
    ],
)
def test_pixel_scale_unit_from_the_header(tmp_path, kwargs):
    path = write_db(tmp_path / "u.fits", GRID, key="PIXSIZE", scale=0.002, **kwargs)
    cube, *_ = read_mavisim_psfs(path, 2.0, 81.0)
    psf = cube[0, 1]
    y, x = np.indices(psf.shape) - 20
    assert np.sqrt((psf * x**2).sum()) == pytest.approx(5.5, rel=0.02)  # 0.002" = 2 mas


def test_pixel_scale_unit_keyword_and_setting(tmp_path):
    path = write_db(tmp_path / "k.fits", GRID, key="PIXSIZE", scale=0.002)
    cube, *_ = read_mavisim_psfs(path, 2.0, 41.0, file_pixel_unit="arcsec")
    assert np.isfinite(cube).all()
    with fits.open(path, mode="update") as hdul:
        hdul[0].header["PIXUNIT"] = "arcsec"
    cube2, *_ = read_mavisim_psfs(path, 2.0, 41.0)  # the keyword wins over the default
    np.testing.assert_allclose(cube, cube2)


def test_psf_wider_than_its_field_is_refused(tmp_path):
    path = write_db(tmp_path / "wide.fits", GRID, n=16, sigma0=40.0)
    with pytest.raises(InputError, match="wider than the PSF field"):
        read_mavisim_psfs(path, 2.0, 41.0)


def test_undersampling_resample_is_refused(tmp_path):
    """A 20 mas target pixel cannot sample a 14 mas FWHM PSF: width / flux are checked."""
    path = write_db(tmp_path / "coarse.fits", [(0.0, 0.0)], sigma0=3.0)
    with pytest.raises(InputError, match="resampling") as err:
        read_mavisim_psfs(path, 20.0, 101.0)
    assert "HDU 1" in str(err.value)


def test_resampled_flux_and_width_checked_pass_for_good_sampling(tmp_path):
    path = write_db(tmp_path / "fine.fits", GRID, scale=3.75)
    cube, *_ = read_mavisim_psfs(path, 1.875, 300.0)
    # sigma 4 source pixels x 3.75 mas = 15 mas = 8 target pixels at (-15,15)+...
    psf = cube[0, 1]
    c = (psf.shape[0] - 1) // 2
    y, x = np.indices(psf.shape) - c
    sigma_mas = (4.0 + 1.5) * 3.75
    assert np.sqrt((psf * x**2).sum()) * 1.875 == pytest.approx(sigma_mas, rel=0.02)


@settings(max_examples=15, deadline=None)
@given(log_scale=st.floats(-4.0, 2.5))
def test_hypothesis_any_pixel_scale_is_used_or_refused(tmp_path_factory, log_scale):
    """Every header pixel scale either gives PSFs of the source's width or a reasoned refusal."""
    scale = 10.0**log_scale
    path = write_db(tmp_path_factory.mktemp("h") / "db.fits", [(0.0, 0.0)], n=48, scale=scale)
    width = 2.3548 * 4.0 * scale  # source Gaussian sigma 4 px
    try:
        cube, *_ = read_mavisim_psfs(path, 2.0, 201.0)
    except InputError as exc:
        msg = str(exc)
        assert "narrower than" in msg or "wider than" in msg or "resampling" in msg
        assert width < 12.1 or width > 150.0
        return
    assert width >= 0.85 * 14.18 - 0.5
    from mavispm.simulate.optics.psf_metrics import fwhm

    assert fwhm(cube[0, 0], 2.0) == pytest.approx(width, rel=0.1, abs=2.0)
