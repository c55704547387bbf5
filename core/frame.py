"""The one in-memory frame type: what rendering returns and what measuring takes.

:func:`mavispm.simulate.render.frame.render_frame` returns a :class:`Frame`;
:func:`mavispm.measure.stars.measure_frame.measure_frame` measures one, whether it
came straight from the renderer or from a ``frames`` product on disk
(:func:`mavispm.measure.stars.measure_frame.read_frame`). Both build it with
:meth:`Frame.from_attrs` from the image in adu and the product's root attributes,
so measuring in memory and measuring the written product give the same numbers.

Example
-------
>>> import numpy as np, astropy.units as u
>>> attrs = {"gain": 2.0 * u.electron / u.adu, "read_noise": 3.0 * u.electron,
...          "sky": 40.0 * u.electron, "saturation": 6e4 * u.adu,
...          "pixel_scale": 7.5 * u.mas, "epoch": 0.0 * u.yr, "nexp": 4}
>>> frame = Frame.from_attrs(np.full((5, 6), 20.0, np.float32), None, attrs)
>>> float(frame.image[0, 0]), frame.read_noise_var, frame.pixel_scale
(40.0, 36.0, 0.0075)
>>> frame.to_nddata().unit
Unit("adu")
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import astropy.units as u
import numpy as np
from astropy.table import QTable
from numpy.typing import ArrayLike

from mavispm.core.errors import InputError
from mavispm.core.products import TableSpec, validate_table

if TYPE_CHECKING:
    from astropy.nddata import NDData

__all__ = ["Frame", "FRAME_ATTRS", "TRUTH_SPEC", "frame_wcs", "on_detector"]

#: Root attributes every frame carries, with their units.
FRAME_ATTRS = {
    "gain": "electron/adu",
    "read_noise": "electron",
    "sky": "electron",
    "saturation": "adu",
    "pixel_scale": "mas",
    "epoch": "yr",
}

#: Truth table of a frame (the stars that were rendered).
TRUTH_SPEC = TableSpec(
    required={
        "id": "",
        "x_pix": "",
        "y_pix": "",
        "x": "arcsec",
        "y": "arcsec",
        "flux": "electron",
        "mag": "mag",
    },
    optional={"x_cat": "arcsec", "y_cat": "arcsec"},
)


def _attr(attrs: Mapping, key: str, unit: str, path) -> float:
    """Root attribute ``key`` as a float in ``unit`` (plain numbers are taken in ``unit``)."""
    if key not in attrs:
        raise InputError(f"root attribute '{key}' [{unit}] missing", path=path)
    value = attrs[key]
    try:
        if isinstance(value, u.Quantity):
            return float(value.to_value(unit))
        return float(u.Quantity(value, unit).value)
    except (TypeError, ValueError, u.UnitsError):
        raise InputError(
            f"root attribute '{key}' must be a number in {unit}, got {value!r}", path=path
        ) from None


def _plain_pixels(table: QTable) -> QTable:
    for col in ("x_pix", "y_pix"):
        if col in table.colnames and isinstance(table[col], u.Quantity):
            table[col] = np.asarray(
                table[col].to_value(u.pix) if table[col].unit == u.pix else table[col].value
            )
    return table


def validate_truth(truth: QTable, path=None) -> QTable:
    """A frame's truth table checked against :data:`TRUTH_SPEC` (pixel columns as plain numbers).

    Parameters
    ----------
    truth : QTable
        Rendered stars.
    path : path, optional
        Source file, for messages.

    Returns
    -------
    QTable

    Raises
    ------
    InputError
        A missing column or a column of the wrong unit.
    """
    return validate_table(_plain_pixels(truth), TRUTH_SPEC, path=path, table_name="truth")


def on_detector(x: ArrayLike, y: ArrayLike, shape: tuple[int, int]) -> np.ndarray:
    """Whether positions [pixel] lie on a detector of ``shape`` ``(ny, nx)``.

    Pixel ``i`` spans ``i - 0.5 .. i + 0.5``, so the detector spans ``-0.5 .. n - 0.5``
    on each axis (edges excluded); a NaN position is not on it.
    """
    ny, nx = shape
    x, y = np.asarray(x, float), np.asarray(y, float)
    return (x > -0.5) & (x < nx - 0.5) & (y > -0.5) & (y < ny - 0.5)


def frame_wcs(attrs: Mapping, shape: tuple[int, int]):
    """Gnomonic (TAN) WCS of a frame centred on the field centre.

    Parameters
    ----------
    attrs : mapping
        ``pixel_scale`` [mas or angle Quantity], optional ``ra_center``,
        ``dec_center`` [deg] (default 0, 0).
    shape : tuple of int
        Image shape (ny, nx).

    Returns
    -------
    astropy.wcs.WCS
        The field centre (x = y = 0) at the image centre, x (columns) towards the
        west (RA decreasing), y (rows) towards the north, ICRS.
    """
    from astropy.wcs import WCS

    ny, nx = shape
    scale = u.Quantity(attrs["pixel_scale"], u.mas).to_value(u.deg)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.cunit = ["deg", "deg"]
    w.wcs.crval = [
        u.Quantity(attrs.get("ra_center", 0.0 * u.deg), u.deg).value,
        u.Quantity(attrs.get("dec_center", 0.0 * u.deg), u.deg).value,
    ]
    w.wcs.crpix = [(nx + 1) / 2, (ny + 1) / 2]
    w.wcs.cd = [[-scale, 0.0], [0.0, scale]]
    w.wcs.radesys = "ICRS"
    w.wcs.equinox = 2000.0
    return w


@dataclass
class Frame:
    """A stacked frame in electrons with its detector description.

    Parameters
    ----------
    image : ndarray (ny, nx) of float
        Stacked frame [electron] (the sum of ``nexp`` sub-exposures).
    saturated : ndarray (ny, nx) of bool
        Pixels saturated in at least one sub-exposure.
    sky : float
        Sky [electron/pixel], whole stack.
    read_noise_var : float
        Read-noise variance of the stack per pixel [electron^2] (``nexp`` RN^2).
    pixel_scale : float
        [arcsec/pixel].
    truth : QTable or None
        The rendered stars (``id``, ``x_pix``, ``y_pix``, ``x``, ``y``, ``flux``,
        ``mag``, optional ``x_cat``, ``y_cat``), for forced photometry and scoring.
    attrs : dict
        Root attributes of the ``frames`` product (quantities).
    path : Path or None
        The product the frame was read from (None in memory).
    bad : ndarray (ny, nx) of bool, optional
        Unusable pixels; default: saturated or non-finite.
    noiseless : ndarray (ny, nx) of float or None
        Expected stack [electron] before noise and saturation (rendering only).
    """

    image: np.ndarray
    saturated: np.ndarray
    sky: float
    read_noise_var: float
    pixel_scale: float
    truth: QTable | None = None
    attrs: dict = field(default_factory=dict)
    path: Path | None = None
    bad: np.ndarray | None = None
    noiseless: np.ndarray | None = None

    def __post_init__(self):
        if self.bad is None:
            self.bad = self.saturated | ~np.isfinite(self.image)

    @classmethod
    def from_attrs(
        cls,
        image_adu: np.ndarray,
        saturated: np.ndarray | None,
        attrs: Mapping,
        truth: QTable | None = None,
        path: str | os.PathLike | None = None,
        noiseless: np.ndarray | None = None,
    ) -> Frame:
        """A frame from its image in adu and the ``frames`` root attributes.

        Parameters
        ----------
        image_adu : ndarray (ny, nx) or Quantity [adu]
            The stacked image.
        saturated : ndarray (ny, nx) of bool or None
            Saturation mask; None: pixels at >= 99.9 % of ``saturation * nexp``.
        attrs : mapping
            ``gain`` [electron/adu], ``read_noise`` [electron], ``sky`` [electron],
            ``saturation`` [adu], ``pixel_scale`` [mas], ``epoch`` [yr], ``nexp``.
        truth : QTable, optional
            Rendered stars; validated against :data:`TRUTH_SPEC`.
        path : path, optional
            Source file, for messages.
        noiseless : ndarray, optional
            Expected stack [electron].

        Returns
        -------
        Frame

        Raises
        ------
        InputError
            A non-2-D image, missing or malformed attributes, a mask of another
            shape, a malformed truth table.
        """
        if isinstance(image_adu, u.Quantity):
            image_adu = image_adu.to_value(u.adu)
        image_adu = np.asarray(image_adu)
        if image_adu.ndim != 2 or min(image_adu.shape) < 3:
            raise InputError(
                f"array 'image' must be a 2-D frame, got shape {image_adu.shape}", path=path
            )
        vals = {k: _attr(attrs, k, unit, path) for k, unit in FRAME_ATTRS.items()}
        nexp = int(attrs.get("nexp", 1))
        if nexp < 1 or vals["gain"] <= 0:
            raise InputError("attributes 'nexp' and 'gain' must be positive", path=path)
        # electrons in one pass (float64, as np.asarray(image_adu, float) * gain)
        image = np.multiply(image_adu, vals["gain"], dtype=np.float64)
        if saturated is None:
            saturated = np.asarray(image_adu, float) >= 0.999 * vals["saturation"] * nexp
        saturated = np.asarray(saturated, bool)
        if saturated.shape != image.shape:
            raise InputError(
                f"array 'saturated' has shape {saturated.shape}, image has {image.shape}",
                path=path,
            )
        if truth is not None:
            truth = validate_truth(truth, path=path)
        return cls(
            image=image,
            saturated=saturated,
            sky=vals["sky"],
            read_noise_var=vals["read_noise"] ** 2 * nexp,
            pixel_scale=vals["pixel_scale"] / 1000.0,
            truth=truth,
            attrs=dict(attrs),
            path=None if path is None else Path(path),
            noiseless=noiseless,
        )

    @classmethod
    def from_nddata(cls, data: NDData, truth: QTable | None = None) -> Frame:
        """A frame from :class:`astropy.nddata.NDData` (the inverse of :meth:`to_nddata`).

        Parameters
        ----------
        data : astropy.nddata.NDData
            ``data`` in adu (``unit`` adu or None), ``mask`` the saturated pixels
            (None: from ``saturation``), ``meta`` the ``frames`` attributes
            (``gain``, ``read_noise``, ``sky``, ``saturation``, ``pixel_scale``,
            ``epoch``, ``nexp``).
        truth : QTable, optional
            Rendered stars, for forced photometry (default ``meta["truth"]`` if any).

        Returns
        -------
        Frame

        Raises
        ------
        InputError
            Data not in adu, or missing attributes.
        """
        unit = getattr(data, "unit", None)
        if unit is not None and u.Unit(unit) != u.adu:
            raise InputError(f"NDData unit must be adu, got {unit}")
        meta = dict(data.meta or {})
        truth = meta.pop("truth", None) if truth is None else truth
        mask = None if data.mask is None else np.asarray(data.mask, bool)
        return cls.from_attrs(np.asarray(data.data), mask, meta, truth)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (ny, nx) [pixel]."""
        return self.image.shape

    @property
    def gain(self) -> float:
        """Detector gain [electron/adu] (1 when the frame has no ``gain`` attribute)."""
        g = self.attrs.get("gain")
        return 1.0 if g is None else float(u.Quantity(g, u.electron / u.adu).value)

    @property
    def adu(self) -> np.ndarray:
        """The stacked image in adu, float32 (as written to the products)."""
        return (self.image / self.gain).astype(np.float32)

    @property
    def epoch(self) -> u.Quantity:
        """Epoch of the frame [yr]."""
        return u.Quantity(self.attrs.get("epoch", 0.0), u.yr)

    def to_arcsec(self, xp: ArrayLike, yp: ArrayLike):
        """Field-frame position [arcsec] of pixel coordinates (0-based, centre = 0).

        Parameters
        ----------
        xp, yp : array-like
            Pixel coordinates (column, row).

        Returns
        -------
        x, y : ndarray
            [arcsec] from the field centre.
        """
        ny, nx = self.shape
        return (np.asarray(xp) - (nx - 1) / 2) * self.pixel_scale, (
            np.asarray(yp) - (ny - 1) / 2
        ) * self.pixel_scale

    def to_pixel(self, x: ArrayLike, y: ArrayLike):
        """Pixel coordinates (0-based) of field-frame positions [arcsec].

        Parameters
        ----------
        x, y : array-like
            [arcsec] from the field centre.

        Returns
        -------
        xp, yp : ndarray
            Pixel coordinates (column, row).
        """
        ny, nx = self.shape
        return np.asarray(x) / self.pixel_scale + (nx - 1) / 2, np.asarray(y) / self.pixel_scale + (
            ny - 1
        ) / 2

    @property
    def wcs(self):
        """The frame's TAN WCS (:func:`frame_wcs`)."""
        return frame_wcs(
            {"pixel_scale": self.pixel_scale * 1000.0 * u.mas, **self.attrs}, self.shape
        )

    def to_nddata(self):
        """The frame as :class:`astropy.nddata.NDData`.

        Returns
        -------
        astropy.nddata.NDData
            ``data`` in adu (float32), ``mask`` = unusable pixels, ``wcs``, and
            ``meta`` holding the root attributes (quantities).
        """
        from astropy.nddata import NDData

        return NDData(self.adu, unit=u.adu, mask=self.bad, wcs=self.wcs, meta=dict(self.attrs))
