"""Reader for MAVISIM-format PSF databases (FITS).

Layout: a primary HDU, then one image HDU per PSF with header keywords
``XPOS`` and ``YPOS`` (field position, arcsec) and ``LAMBDA`` (wavelength; m,
um or nm are recognised by magnitude). The optical axis of each stamp is taken
at pixel ``(N//2, N//2)`` (FFT convention). PSFs are resampled (cubic spline)
to the grid pixel scale and stamp size and normalised to unit sum.

Pixel scale and its unit. The scale is read from ``PIXSCALE`` or ``PIXSIZE`` in
the image or primary header, or from the setting ``psf.file_pixel_scale`` (mas).
A header value's unit is taken, in this order, from ``PIXUNIT`` or ``CUNIT1``
("mas" / "arcsec" / "deg"), from the card comment (a word "mas",
"milliarcsec", "arcsec" or "deg"), else from the setting ``psf.file_pixel_unit``
(default "mas"); the unit used is part of every error message. The scale is
then checked against the optics: a PSF whose FWHM comes out narrower than
``0.85 lambda / D`` (the diffraction limit of the obstructed VLT pupil is
~``1.0 lambda / D``) or wider than its own field is refused with the reason
(the classic failure is a scale in arcsec read as mas, which would turn the
PSFs into delta functions). After resampling, each stamp's FWHM must match the
source's within 10% (or one target pixel) and the flux inside the stamp must
match the source flux over the same square within 2% (both of the stamp sum).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.utils.exceptions import AstropyUserWarning
from scipy.ndimage import map_coordinates

from mavispm.core.errors import InputError
from mavispm.simulate.optics.atmosphere import MAS_PER_RAD
from mavispm.simulate.optics.psf_metrics import fwhm

__all__ = [
    "MIN_FWHM_LAMBDA_OVER_D",
    "read_mavisim_psfs",
]

_SCALE_KEYS = ("PIXSCALE", "PIXSIZE")
_UNIT_KEYS = ("PIXUNIT", "CUNIT1")
#: mas per unit, by the names accepted in headers and settings
_UNITS = {"mas": 1.0, "milliarcsec": 1.0, "arcsec": 1000.0, "deg": 3.6e6}
#: narrowest accepted FWHM in lambda / D
MIN_FWHM_LAMBDA_OVER_D = 0.85


def _unit_from_text(text: str) -> str | None:
    """The first unit name found in a header comment or value (None if none)."""
    import re

    for word in re.findall(r"[a-z]+", str(text).lower()):
        if word in ("mas", "milliarcsec", "milliarcsecond", "milliarcseconds"):
            return "mas"
        if word in ("arcsec", "arcsecond", "arcseconds", "asec"):
            return "arcsec"
        if word in ("deg", "degree", "degrees"):
            return "deg"
    return None


def _header_scale(header) -> tuple[float, str, str] | None:
    """(value, unit or '', keyword) of the pixel scale in one header, or None."""
    for key in _SCALE_KEYS:
        if key in header:
            unit = next(
                (_unit_from_text(header[k]) for k in _UNIT_KEYS if k in header), None
            ) or _unit_from_text(header.comments[key])
            return float(header[key]), unit or "", key
    return None


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


def _check_width(data, scale_mas, lam_nm, diameter, where, path) -> float:
    """FWHM (mas) of a source PSF; refuses impossible pixel scales with the reason."""
    width = fwhm(data, scale_mas)
    limit = MIN_FWHM_LAMBDA_OVER_D * lam_nm * 1e-9 / diameter * MAS_PER_RAD
    field = data.shape[0] * scale_mas
    if width < limit:
        raise InputError(
            f"{where}: FWHM {width:.3g} mas is narrower than {MIN_FWHM_LAMBDA_OVER_D} lambda/D "
            f"= {limit:.3g} mas at {lam_nm:g} nm for D = {diameter:g} m; the pixel scale "
            f"({scale_mas:.6g} mas) is too small: is it in arcsec? State the unit "
            "(PIXUNIT, the card comment, or psf.file_pixel_unit)",
            path=path,
        )
    if width > field:
        raise InputError(
            f"{where}: FWHM {width:.4g} mas is wider than the PSF field "
            f"{data.shape[0]} px x {scale_mas:.6g} mas = {field:.4g} mas; the pixel scale is "
            "too large or the image is not a PSF",
            path=path,
        )
    return width


def _check_resampled(data, scale, stamp, pixel_scale, width, where, path) -> None:
    """Flux and width of a resampled stamp (point samples of the source, unnormalised)
    against its source (normalised to unit sum)."""
    new_width = fwhm(stamp, pixel_scale)
    if abs(new_width - width) > max(0.10 * width, pixel_scale):
        raise InputError(
            f"{where}: resampling to {pixel_scale:g} mas pixels changed the FWHM from "
            f"{width:.3g} to {new_width:.3g} mas (target pixel too coarse for this PSF?)",
            path=path,
        )
    # source flux over the square the stamp covers (source pixels fully inside, plus
    # fractional edge pixels)
    n = stamp.shape[0]
    half = n * pixel_scale / 2 / scale  # half width in source pixels
    c = data.shape[0] // 2
    idx = np.arange(data.shape[0]) - c
    w1 = np.clip(half + 0.5 - np.abs(idx), 0.0, 1.0)
    expected = float(w1 @ data @ w1)
    got = float(stamp.sum()) * (pixel_scale / scale) ** 2  # point samples -> flux
    if abs(got - expected) > 0.02 * max(expected, 1e-12):
        raise InputError(
            f"{where}: resampling does not conserve flux ({got:.4f} of the PSF in the "
            f"stamp against {expected:.4f} in the same square of the source)",
            path=path,
        )


def read_mavisim_psfs(
    path: str | Path,
    pixel_scale: float,
    stamp_size_mas: float,
    file_pixel_scale: float | None = None,
    file_pixel_unit: str = "mas",
    diameter: float = 8.0,
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
    file_pixel_unit : {"mas", "arcsec", "deg"}
        Unit of a header pixel scale whose header states none.
    diameter : float
        Telescope diameter (m), for the diffraction-limit check.

    Returns
    -------
    cube : ndarray, shape (ny, nx, n, n)
    nodes_x, nodes_y : ndarray (arcsec)
    wavelength : float (nm)

    Raises
    ------
    InputError
        Unreadable file, missing headers, NaN pixels, mixed wavelengths, an
        incomplete grid, an impossible pixel scale (PSF narrower than lambda / D or
        wider than its field) or a resampling that loses flux or width, naming the
        file and the HDU.
    """
    if file_pixel_unit not in _UNITS:
        raise ValueError(
            f"file_pixel_unit must be one of {sorted(_UNITS)}, got {file_pixel_unit!r}"
        )
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
        primary_scale = _header_scale(hdul[0].header)
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
            found = _header_scale(h) or primary_scale
            if found is not None:
                value, unit, key = found
                unit = unit or file_pixel_unit
                scale = value * _UNITS[unit]
                source = f"{key} = {value:g} {unit}"
            else:
                scale, source = file_pixel_scale, f"psf.file_pixel_scale = {file_pixel_scale} mas"
            if scale is None or not scale > 0:
                raise InputError(
                    f"HDU {i}: no positive pixel scale ({source if found else 'none'}; "
                    "header PIXSCALE/PIXSIZE with its unit, or setting psf.file_pixel_scale)",
                    path=path,
                )
            entries.append(
                (
                    float(h["XPOS"]),
                    float(h["YPOS"]),
                    _wavelength_nm(float(h["LAMBDA"])),
                    scale,
                    data,
                    f"HDU {i} ({source})",
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
    for x, y, lam, scale, data, where in entries:
        iy, ix = np.searchsorted(ys, y), np.searchsorted(xs, x)
        data = data / data.sum()
        width = _check_width(data, scale, lam, diameter, where, path)
        stamp = _resample(data, scale, pixel_scale, n)
        if not stamp.sum() > 0:
            raise InputError(f"PSF at ({x}, {y}) has no flux inside the stamp", path=path)
        _check_resampled(data, scale, stamp, pixel_scale, width, where, path)
        cube[iy, ix] = stamp / stamp.sum()
    if np.isnan(cube).any():
        raise InputError("inconsistent grid: duplicated (XPOS, YPOS) positions", path=path)
    return cube, xs, ys, float(lams[0])
