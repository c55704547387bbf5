"""FITS copy of a frame: the image in adu with an honest header and a TAN WCS.

The header carries the detector and exposure (``PIXSCALE`` arcsec, ``EXPTIME`` of one
sub-exposure, ``NCOMBINE`` sub-exposures, ``TEXPTIME`` total, ``EPOCH``, ``GAIN``,
``RDNOISE``, ``SATURATE`` per sub-exposure), every scene parameter as a ``HIERARCH
MAVISPM ...`` keyword, and a gnomonic (TAN) WCS centred on the cluster: the field
centre (x = y = 0) is at ``CRPIX = ((nx+1)/2, (ny+1)/2)`` (1-based), x grows with
the column towards the west (RA decreasing, ``CD1_1 < 0``), y grows with the row
towards the north.
"""

from __future__ import annotations

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


def _flatten(mapping: Mapping, prefix: str = ""):
    for key, value in mapping.items():
        name = f"{prefix} {key}".strip()
        if isinstance(value, Mapping):
            yield from _flatten(value, name)
        else:
            yield name, value


def frame_header(attrs: Mapping, shape, scene: Mapping | None = None) -> fits.Header:
    """Build the FITS header of a frame.

    Parameters
    ----------
    attrs : mapping
        Frame attributes (``pixel_scale``, ``exptime``, ``nexp``, ``epoch``, ``gain``,
        ``read_noise``, ``saturation``, ``sky``, ``ra_center``, ``dec_center``), quantities.
    shape : tuple (ny, nx)
    scene : mapping, optional
        Scene settings written as HIERARCH keywords.
    """
    ny, nx = shape
    scale = u.Quantity(attrs["pixel_scale"]).to_value(u.arcsec)
    hdr = fits.Header()
    hdr["BUNIT"] = ("adu", "stacked sub-exposures")
    hdr["PIXSCALE"] = (scale, "[arcsec/pixel]")
    hdr["EXPTIME"] = (u.Quantity(attrs["exptime"]).to_value(u.s), "[s] one sub-exposure")
    hdr["NCOMBINE"] = (int(attrs["nexp"]), "sub-exposures summed")
    hdr["TEXPTIME"] = (
        u.Quantity(attrs["exptime"]).to_value(u.s) * int(attrs["nexp"]),
        "[s] total integration",
    )
    hdr["EPOCH"] = (u.Quantity(attrs["epoch"]).to_value(u.yr), "[yr] epoch of the catalogue")
    hdr["GAIN"] = (u.Quantity(attrs["gain"]).to_value(u.electron / u.adu), "[e-/adu]")
    hdr["RDNOISE"] = (u.Quantity(attrs["read_noise"]).to_value(u.electron), "[e-] per sub-exp")
    hdr["SATURATE"] = (u.Quantity(attrs["saturation"]).to_value(u.adu), "[adu] per sub-exp")
    hdr["SKYLEVEL"] = (u.Quantity(attrs["sky"]).to_value(u.electron), "[e-/pixel] whole stack")
    ra = u.Quantity(attrs.get("ra_center", 0.0 * u.deg), u.deg).value
    dec = u.Quantity(attrs.get("dec_center", 0.0 * u.deg), u.deg).value
    hdr["WCSAXES"] = 2
    hdr["CTYPE1"], hdr["CTYPE2"] = "RA---TAN", "DEC--TAN"
    hdr["CUNIT1"], hdr["CUNIT2"] = "deg", "deg"
    hdr["CRVAL1"], hdr["CRVAL2"] = ra, dec
    hdr["CRPIX1"] = ((nx + 1) / 2, "field centre (cluster), 1-based")
    hdr["CRPIX2"] = ((ny + 1) / 2, "field centre (cluster), 1-based")
    hdr["CD1_1"], hdr["CD1_2"] = -scale / 3600.0, 0.0
    hdr["CD2_1"], hdr["CD2_2"] = 0.0, scale / 3600.0
    hdr["RADESYS"] = "ICRS"
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

    Returns
    -------
    pathlib.Path
    """
    hdr = frame_header(attrs, image.shape, scene)
    hdus = [fits.PrimaryHDU(np.asarray(image, dtype=np.float32), header=hdr)]
    if saturated is not None:
        hdus.append(fits.ImageHDU(np.asarray(saturated, dtype=np.uint8), name="SATURATED"))
    path = Path(path)
    with atomic_path(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True)
    return path
