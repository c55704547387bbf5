"""FITS copy of a frame: the image in adu with a standard header and a TAN WCS.

The header carries the FITS-standard and common observatory keywords
(``TELESCOP = 'ESO-VLT-U4'``, ``INSTRUME = 'MAVIS'``, ``FILTER = 'V'``,
``OBJECT``, ``DATE-OBS`` / ``MJD-OBS`` of the epoch, ``DATE`` of the file,
``ORIGIN``, ``RADESYS = 'ICRS'``, ``EQUINOX = 2000``), the exposure as
``EXPTIME`` (total integration of the stack [s]) with ``NCOMBINE``
sub-exposures of ``SUBEXPT`` [s] each, the detector (``PIXSCALE`` arcsec,
``GAIN``, ``RDNOISE`` and ``SATURATE`` per sub-exposure, ``SKYLEVEL``), the epoch
in years after the simulation's epoch zero (``MVEPOCH``; ``DATE-OBS`` puts epoch
zero at :data:`EPOCH_ZERO`), every scene parameter as a ``HIERARCH MAVISPM ...``
keyword, and a gnomonic (TAN) WCS centred on the cluster on every image HDU: the
field centre (x = y = 0) is at ``CRPIX = ((nx+1)/2, (ny+1)/2)`` (1-based), x grows
with the column towards the west (RA decreasing, ``CD1_1 < 0``), y grows with the
row towards the north. There is no ``EPOCH`` card (the deprecated FITS word for
the equinox).
"""

from __future__ import annotations

import datetime as _datetime
import json
import os
import warnings
from collections.abc import Mapping
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.io import fits
from astropy.io.fits.verify import VerifyWarning

from mavispm.core.atomic import atomic_path

__all__ = [
    "EPOCH_ZERO",
    "frame_header",
    "standard_cards",
    "write_frame_fits",
]


def _flatten(mapping: Mapping, prefix: str = ""):
    for key, value in mapping.items():
        name = f"{prefix} {key}".strip()
        if isinstance(value, Mapping):
            yield from _flatten(value, name)
        else:
            yield name, value


#: Calendar date of epoch 0 of a simulation (a simulated MAVIS-era date, UTC).
EPOCH_ZERO = "2030-01-01T00:00:00"
_MJD_ZERO = _datetime.datetime(1858, 11, 17)  # MJD 0


def _object_name(attrs: Mapping) -> str:
    config = attrs.get("config") if isinstance(attrs.get("config"), Mapping) else {}
    name = attrs.get("object") or config.get("preset") or "simulated cluster"
    return str(name).upper() if str(name).lower().startswith("ngc") else str(name)


def standard_cards(attrs: Mapping, shape: tuple[int, int]) -> fits.Header:
    """FITS-standard cards of a frame: observatory, date, exposure and the TAN WCS.

    Parameters
    ----------
    attrs : mapping
        Frame attributes: ``pixel_scale`` [mas], ``exptime`` [s] (one
        sub-exposure), ``nexp``, ``epoch`` [yr after epoch zero], optional
        ``ra_center``, ``dec_center`` [deg], ``object`` or ``config["preset"]``.
    shape : tuple of int
        Image shape (ny, nx).

    Returns
    -------
    astropy.io.fits.Header
        ``TELESCOP``, ``INSTRUME``, ``FILTER``, ``OBJECT``, ``DATE-OBS``,
        ``MJD-OBS``, ``DATE``, ``ORIGIN``, ``EXPTIME`` (total [s]), ``NCOMBINE``,
        ``SUBEXPT``, ``MVEPOCH``, ``PIXSCALE`` and the WCS (with ``RADESYS``,
        ``EQUINOX``).
    """
    from mavispm import __version__
    from mavispm.core.frame import frame_wcs

    sub = u.Quantity(attrs["exptime"], u.s).value
    nexp = int(attrs["nexp"])
    epoch = u.Quantity(attrs["epoch"], u.yr).value
    # epochs count Julian years (365.25 d); plain datetime avoids ERFA's leap-second
    # warnings for dates beyond its table
    zero = _datetime.datetime.fromisoformat(EPOCH_ZERO)
    obs = zero + _datetime.timedelta(days=epoch * 365.25)
    mjd = (zero - _MJD_ZERO).total_seconds() / 86400.0 + epoch * 365.25
    hdr = fits.Header()
    hdr["TELESCOP"] = ("ESO-VLT-U4", "VLT Unit Telescope 4 (Yepun)")
    hdr["INSTRUME"] = ("MAVIS", "MCAO Assisted Visible Imager and Spectrograph")
    hdr["FILTER"] = ("V", "Johnson V (Vega), the simulated band")
    hdr["OBJECT"] = (_object_name(attrs), "simulated field")
    hdr["DATE-OBS"] = (
        obs.isoformat(timespec="seconds"),
        "simulated: epoch 0 is " + EPOCH_ZERO[:10],
    )
    hdr["MJD-OBS"] = (mjd, "[d] MJD of DATE-OBS")
    hdr["DATE"] = (
        _datetime.datetime.now(_datetime.UTC).strftime("%Y-%m-%dT%H:%M:%S"),
        "file creation date (UTC)",
    )
    hdr["ORIGIN"] = (f"mavispm {__version__}", "simulated by the mavispm pipeline")
    hdr["EXPTIME"] = (sub * nexp, "[s] total integration of the stack")
    hdr["NCOMBINE"] = (nexp, "sub-exposures summed")
    hdr["SUBEXPT"] = (sub, "[s] one sub-exposure")
    hdr["MVEPOCH"] = (epoch, "[yr] epoch after the simulation's epoch zero")
    hdr["PIXSCALE"] = (u.Quantity(attrs["pixel_scale"], u.mas).to_value(u.arcsec), "[arcsec/pixel]")
    hdr.extend(frame_wcs(attrs, shape).to_header(), update=True)
    hdr["EQUINOX"] = (2000.0, "[yr] equinox of the coordinates (ICRS)")
    return hdr


def frame_header(
    attrs: Mapping, shape: tuple[int, int], scene: Mapping | None = None
) -> fits.Header:
    """Build the FITS header of a frame's image.

    Parameters
    ----------
    attrs : mapping
        Frame attributes (``pixel_scale``, ``exptime``, ``nexp``, ``epoch``, ``gain``,
        ``read_noise``, ``saturation``, ``sky``, ``ra_center``, ``dec_center``), quantities.
    shape : tuple (ny, nx)
    scene : mapping, optional
        Scene settings written as HIERARCH keywords.

    Returns
    -------
    astropy.io.fits.Header
        :func:`standard_cards` plus ``BUNIT``, ``GAIN``, ``RDNOISE``,
        ``SATURATE``, ``SKYLEVEL`` and the scene.
    """
    hdr = fits.Header()
    hdr["BUNIT"] = ("adu", "stacked sub-exposures")
    hdr.extend(standard_cards(attrs, shape))
    hdr["GAIN"] = (u.Quantity(attrs["gain"]).to_value(u.electron / u.adu), "[e-/adu]")
    hdr["RDNOISE"] = (u.Quantity(attrs["read_noise"]).to_value(u.electron), "[e-] per sub-exp")
    hdr["SATURATE"] = (u.Quantity(attrs["saturation"]).to_value(u.adu), "[adu] per sub-exp")
    hdr["SKYLEVEL"] = (u.Quantity(attrs["sky"]).to_value(u.electron), "[e-/pixel] whole stack")
    for name, value in _flatten(scene or {}):
        if isinstance(value, (list, tuple, dict)):
            value = json.dumps(value)
        if value is None:
            continue
        key = "HIERARCH MAVISPM " + name.upper()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", VerifyWarning)
            try:
                card = fits.Card(key, value)
                card.verify("exception")
                str(card)
            except (ValueError, fits.VerifyError):
                continue
        hdr.append(card)
    return hdr


def write_frame_fits(
    path: str | os.PathLike,
    image: np.ndarray,
    attrs: Mapping,
    scene: Mapping | None = None,
    saturated: np.ndarray | None = None,
) -> Path:
    """Write the frame image (and the saturation mask as a second HDU) atomically.

    Parameters
    ----------
    path : str or os.PathLike
        The FITS file.
    image : ndarray (ny, nx)
        The stack [adu].
    attrs : mapping
        Frame attributes (see :func:`frame_header`).
    scene : mapping, optional
        Scene settings, written as ``HIERARCH MAVISPM`` cards.
    saturated : ndarray of bool, optional
        Saturation mask, written as the ``SATURATED`` extension with the same WCS.

    Returns
    -------
    pathlib.Path
    """
    hdr = frame_header(attrs, image.shape, scene)
    hdus = [fits.PrimaryHDU(np.asarray(image, dtype=np.float32), header=hdr)]
    if saturated is not None:
        mask_hdr = standard_cards(attrs, image.shape)
        mask_hdr["BUNIT"] = ("", "1 = saturated in at least one sub-exposure")
        hdus.append(
            fits.ImageHDU(np.asarray(saturated, dtype=np.uint8), header=mask_hdr, name="SATURATED")
        )
    path = Path(path)
    with atomic_path(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True)
    return path
