"""Photometry: V-band (Vega) magnitudes to detected electrons, and the sky.

The chain follows the MAVISIM paper (sections 3.1.4 and 4.1): a star of
apparent V magnitude ``m`` observed at airmass ``X`` delivers::

    N_e = F0 * 10**(-0.4 * (m + k X)) * A_tel * dlambda * T * QE * t_exp

electrons, with ``F0`` the Vega V-band photon flux density of a V = 0 star,
``k = 0.129`` mag/airmass the Paranal V extinction, ``A_tel`` the collecting
area of the VLT (8.2 m primary with a 1.116 m central obstruction), ``T ~ 45 %``
the telescope + AO throughput and ``QE = 89 %``. The sky (21.61 V mag/arcsec^2,
measured at the ground, so no extinction is applied to it) goes through the same
chain per pixel area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import astropy.units as u
import numpy as np

from mavispm.core.config import unit_field

__all__ = [
    "collecting_area",
    "electron_rate_zero_mag",
    "photometric_zero_point",
    "PhotometrySettings",
    "sky_electrons_per_pixel",
    "star_electrons",
]


@dataclass(frozen=True)
class PhotometrySettings:
    """Photometric calibration of a scene (TOML table ``[photometry]``).

    Parameters
    ----------
    zero_point : float
        Photon flux density of a V = 0 (Vega) star above the atmosphere,
        photon / (s cm^2 Angstrom). Default 1000 (3.63e-9 erg/s/cm^2/A at 550 nm).
    bandwidth : float
        Effective width of the V filter, Angstrom (default 880).
    extinction : float
        Atmospheric extinction coefficient, mag per airmass (0.129 at Paranal, V).
    airmass : float
        Airmass of the observation (1 = zenith).
    throughput : float
        Telescope + AO module + instrument throughput, excluding the detector QE (0.45).
    qe : float
        Detector quantum efficiency (0.89).
    sky_brightness : float
        Sky surface brightness, V mag/arcsec^2 (21.61, dark Paranal sky).
    telescope_diameter : float
        Primary mirror diameter, m (8.2).
    obscuration_diameter : float
        Central obscuration diameter, m (1.116).
    """

    zero_point: float = unit_field(1000.0, "ph / (s cm2 Angstrom)")
    bandwidth: float = unit_field(880.0, "Angstrom")
    extinction: float = 0.129
    airmass: float = 1.0
    throughput: float = 0.45
    qe: float = 0.89
    sky_brightness: float = 21.61
    telescope_diameter: float = unit_field(8.2, "m")
    obscuration_diameter: float = unit_field(1.116, "m")

    def __post_init__(self):
        for name in ("zero_point", "bandwidth", "telescope_diameter"):
            if not getattr(self, name) > 0:
                raise ValueError(f"photometry.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.throughput <= 1:
            raise ValueError(f"photometry.throughput must be in (0, 1], got {self.throughput}")
        if not 0 < self.qe <= 1:
            raise ValueError(f"photometry.qe must be in (0, 1], got {self.qe}")
        if self.airmass < 1:
            raise ValueError(f"photometry.airmass must be >= 1, got {self.airmass}")
        if self.extinction < 0:
            raise ValueError(f"photometry.extinction must be >= 0, got {self.extinction}")
        if not 0 <= self.obscuration_diameter < self.telescope_diameter:
            raise ValueError("photometry.obscuration_diameter must be in [0, telescope_diameter)")


def collecting_area(settings: PhotometrySettings) -> u.Quantity:
    """Unobscured collecting area of the telescope (cm^2).

    Parameters
    ----------
    settings : PhotometrySettings
        Telescope and obscuration diameters [m].

    Returns
    -------
    Quantity
        [cm^2]
    """
    d_out = settings.telescope_diameter * 100.0
    d_in = settings.obscuration_diameter * 100.0
    return math.pi / 4.0 * (d_out**2 - d_in**2) * u.cm**2


def electron_rate_zero_mag(settings: PhotometrySettings) -> u.Quantity:
    """Detected electrons per second from a V = 0 source above the atmosphere (electron/s).

    Parameters
    ----------
    settings : PhotometrySettings
        Vega zero point, bandwidth, collecting area, throughput and QE.

    Returns
    -------
    Quantity
        [electron/s]
    """
    rate = (
        settings.zero_point
        * settings.bandwidth
        * collecting_area(settings).to_value(u.cm**2)
        * settings.throughput
        * settings.qe
    )
    return rate * u.electron / u.s


def photometric_zero_point(settings: PhotometrySettings) -> u.Quantity:
    """Magnitude of a star that gives 1 detected electron per second (extinction included).

    Parameters
    ----------
    settings : PhotometrySettings

    Returns
    -------
    Quantity
        ``ZP`` [mag] such that ``mag = ZP - 2.5 log10(flux / exposure)`` with the
        flux in electrons and the exposure in seconds.
    """
    rate = electron_rate_zero_mag(settings).to_value(u.electron / u.s)
    return (2.5 * math.log10(rate) - settings.extinction * settings.airmass) * u.mag


def star_electrons(
    mag: np.ndarray | u.Quantity, settings: PhotometrySettings, exposure: u.Quantity
) -> u.Quantity:
    """Electrons detected from stars of apparent V magnitude ``mag`` (above the atmosphere).

    Parameters
    ----------
    mag : array-like or Quantity
        Apparent V (Vega) magnitudes, mag.
    settings : PhotometrySettings
    exposure : Quantity
        Total integration time (s); the whole stack for stack fluxes.

    Returns
    -------
    Quantity
        Electrons (float64), atmospheric extinction ``k X`` applied.
    """
    m = np.asarray(u.Quantity(mag, u.mag).value if hasattr(mag, "unit") else mag, dtype=float)
    extinct = settings.extinction * settings.airmass
    rate = electron_rate_zero_mag(settings).to_value(u.electron / u.s)
    return rate * exposure.to_value(u.s) * 10.0 ** (-0.4 * (m + extinct)) * u.electron


def sky_electrons_per_pixel(
    settings: PhotometrySettings, pixel_scale: u.Quantity, exposure: u.Quantity
) -> u.Quantity:
    """Sky electrons collected by one detector pixel in ``exposure``.

    The sky brightness is measured from the ground, so no extinction is applied.

    Parameters
    ----------
    settings : PhotometrySettings
    pixel_scale : Quantity
        Detector pixel size (angle).
    exposure : Quantity
        Integration time (s).
    """
    area = pixel_scale.to_value(u.arcsec) ** 2
    rate = electron_rate_zero_mag(settings).to_value(u.electron / u.s)
    return (
        rate
        * 10.0 ** (-0.4 * settings.sky_brightness)
        * area
        * exposure.to_value(u.s)
        * (u.electron)
    )
