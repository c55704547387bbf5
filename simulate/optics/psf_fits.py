"""Reader for MAVISIM-format PSF databases (FITS).

Layout: a primary HDU, then one image HDU per PSF with header keywords
``XPOS`` and ``YPOS`` (field position, arcsec) and ``LAMBDA`` (wavelength; m,
um or nm are recognised by magnitude). The pixel scale is read from
``PIXSCALE`` or ``PIXSIZE`` (mas) in the image or primary header, or given in
the settings. The optical axis of each stamp is taken at pixel ``(N//2, N//2)``
(FFT convention). PSFs are resampled (cubic spline) to the grid pixel scale
and stamp size and normalised to unit sum.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.utils.exceptions import AstropyUserWarning
from scipy.ndimage import map_coordinates

from mavispm.core.errors import InputError

_SCALE_KEYS = ("PIXSCALE", "PIXSIZE")


def _wavelength_nm(value: float) -> float:
    if value < 1e-3:
        return value * 1e9
    if value < 10:
        return value * 1e3
    return value


def _resample(psf: np.ndarray, src_scale: float, dst_scale: float, n: int) -> np.ndarray:
    c_src = psf.shape[0] // 2
    c_dst = (n - 1) / 2
    offs = (np.arange(n) - c_dst) * dst_scale / src_scale
    yy, xx = np.meshgrid(offs + c_src, offs + c_src, indexing="ij")
    out = map_coordinates(psf, [yy, xx], order=3, mode="constant", cval=0.0)
    out = np.clip(out, 0.0, None)
    return out


def read_mavisim_psfs(
    path: str | Path,
    pixel_scale: float,
    stamp_size_mas: float,
    file_pixel_scale: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Read a MAVISIM PSF database onto a regular grid.

    Parameters
    ----------
    path : str or Path
        The FITS file.
    pixel_scale : float
        Target PSF pixel (mas).
    stamp_size_mas : float
        Target stamp width (mas); rounded to an odd number of pixels.
    file_pixel_scale : float, optional
        Pixel scale of the file (mas) if its headers do not give it.

    Returns
    -------
    cube : ndarray, shape (ny, nx, n, n)
    nodes_x, nodes_y : ndarray (arcsec)
    wavelength : float (nm)

    Raises
    ------
    InputError
        Unreadable file, missing headers, NaN pixels, mixed wavelengths or an
        incomplete grid, naming the file and the HDU.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("PSF database does not exist", path=path)
    size = path.stat().st_size
    if size % 2880:  # FITS files are whole 2880-byte blocks: a cut one is not
        raise InputError(
            f"truncated or damaged FITS file ({size} bytes, not a multiple of 2880)", path=path
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", AstropyUserWarning)  # "may have been truncated"
            hdul = fits.open(path, memmap=False)
            hdul.readall()
    except (OSError, ValueError, TypeError, AstropyUserWarning) as exc:
        raise InputError(f"not a readable FITS file ({exc})", path=path) from None
    with hdul:
        if len(hdul) < 2:
            raise InputError("no PSF image HDUs after the primary HDU", path=path)
        primary_scale = next((hdul[0].header[k] for k in _SCALE_KEYS if k in hdul[0].header), None)
        entries = []
        for i, hdu in enumerate(hdul[1:], 1):
            h = hdu.header
            for key in ("XPOS", "YPOS", "LAMBDA"):
                if key not in h:
                    raise InputError(f"HDU {i} lacks header keyword {key}", path=path)
            data = hdu.data
            if data is None or np.ndim(data) != 2 or data.shape[0] != data.shape[1]:
                raise InputError(f"HDU {i} is not a square 2-D image", path=path)
            data = np.asarray(data, float)
            if not np.all(np.isfinite(data)):
                raise InputError(f"HDU {i} has NaN or infinite pixels", path=path)
            if not data.sum() > 0:
                raise InputError(f"HDU {i} has no positive flux", path=path)
            scale = next((h[k] for k in _SCALE_KEYS if k in h), primary_scale)
            scale = file_pixel_scale if scale is None else float(scale)
            if scale is None or not scale > 0:
                raise InputError(
                    f"HDU {i}: no pixel scale (header PIXSCALE/PIXSIZE in mas, or "
                    "setting psf.file_pixel_scale)",
                    path=path,
                )
            entries.append(
                (
                    float(h["XPOS"]),
                    float(h["YPOS"]),
                    _wavelength_nm(float(h["LAMBDA"])),
                    scale,
                    data,
                )
            )
    lams = np.array([e[2] for e in entries])
    if np.ptp(lams) > 1e-6 * lams.max():
        raise InputError(f"PSFs have different LAMBDA values {sorted(set(lams))}", path=path)
    xs = np.unique([e[0] for e in entries])
    ys = np.unique([e[1] for e in entries])
    if xs.size * ys.size != len(entries):
        raise InputError(
            f"inconsistent grid: {len(entries)} PSFs but {xs.size} XPOS x {ys.size} YPOS values",
            path=path,
        )
    n = int(round(stamp_size_mas / pixel_scale)) // 2 * 2 + 1
    cube = np.full((ys.size, xs.size, n, n), np.nan)
    for x, y, _lam, scale, data in entries:
        iy, ix = np.searchsorted(ys, y), np.searchsorted(xs, x)
        stamp = _resample(data / data.sum(), scale, pixel_scale, n)
        if not stamp.sum() > 0:
            raise InputError(f"PSF at ({x}, {y}) has no flux inside the stamp", path=path)
        cube[iy, ix] = stamp / stamp.sum()
    if np.isnan(cube).any():
        raise InputError("inconsistent grid: duplicated (XPOS, YPOS) positions", path=path)
    return cube, xs, ys, float(lams[0])
