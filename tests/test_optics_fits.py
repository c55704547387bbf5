"""MAVISIM-format PSF FITS databases."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

from mavispm.core.errors import InputError
from mavispm.simulate.optics.psf_fits import read_mavisim_psfs


def gaussian(n, sigma_pix, dx=0.0):
    c = n // 2
    y, x = np.indices((n, n))
    return np.exp(-0.5 * (((x - c - dx) / sigma_pix) ** 2 + ((y - c) / sigma_pix) ** 2))


def write_db(path, positions, n=64, scale_key=True, drop=None, nan=False, lam=5.5e-7):
    hdus = [fits.PrimaryHDU()]
    if scale_key:
        hdus[0].header["PIXSCALE"] = 1.0
    for k, (x, y) in enumerate(positions):
        sigma = 4.0 + 0.1 * (abs(x) + abs(y))
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
    cube, xs, ys, lam = read_mavisim_psfs(path, pixel_scale=2.0, stamp_size_mas=41.0)
    assert cube.shape == (2, 3, 21, 21)
    np.testing.assert_array_equal(xs, [-15.0, 0.0, 15.0])
    np.testing.assert_array_equal(ys, [-15.0, 15.0])
    assert lam == pytest.approx(550.0)
    np.testing.assert_allclose(cube.sum(axis=(-2, -1)), 1.0, atol=1e-12)
    # the Gaussian at (0, -15) had sigma 5.5 file pixels = 5.5 mas -> 2.75 new pixels
    psf = cube[0, 1]
    y, x = np.indices(psf.shape) - 10
    assert np.sqrt((psf * x**2).sum()) == pytest.approx(2.75, rel=0.03)
    assert (psf * x).sum() == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"drop": "XPOS"}, "lacks header keyword XPOS"),
        ({"drop": "LAMBDA"}, "lacks header keyword LAMBDA"),
        ({"nan": True}, "NaN"),
        ({"scale_key": False}, "no pixel scale"),
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
