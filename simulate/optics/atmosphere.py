"""Atmospheric turbulence: layered Cn^2 profile and the von Karman phase spectrum.

All lengths in metres, angles in radians unless a name says otherwise. The
Fried parameter scales with wavelength as lambda^(6/5) and with zenith angle
as cos(z)^(3/5); layer altitudes are stretched by the airmass.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mavispm.core.config import unit_field

__all__ = [
    "ARCSEC_PER_RAD",
    "AtmosphereSettings",
    "Layers",
    "MAS_PER_RAD",
    "REFERENCE_WAVELENGTH",
    "VON_KARMAN_CONSTANT",
    "airmass",
    "fried_parameter",
    "layers",
    "von_karman_covariance",
    "von_karman_psd",
    "von_karman_variance_beyond",
]

#: arcseconds per radian
ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0
#: milli-arcseconds per radian
MAS_PER_RAD = ARCSEC_PER_RAD * 1000.0
#: von Karman spectrum constant 0.0229 = (24/5 Gamma(6/5))^(5/6) Gamma(11/6)^2 / (2 pi^(11/3))
VON_KARMAN_CONSTANT = 0.022896
#: Fried-parameter reference wavelength (m)
REFERENCE_WAVELENGTH = 500e-9

# The atmosphere of TIPTOP's MAVIS.ini (astro-tiptop/TIPTOP, perfTest/MAVIS.ini,
# [atmosphere]): the ESO Paranal median profile reduced to 10 layers, 0.8" seeing
# at 500 nm, L0 = 25 m, observed at 30 deg zenith angle.
_HEIGHTS = (30.0, 140.0, 281.0, 562.0, 1125.0, 2250.0, 4500.0, 7750.0, 11000.0, 14000.0)
_WEIGHTS = (0.59, 0.02, 0.04, 0.06, 0.01, 0.05, 0.09, 0.04, 0.05, 0.05)
_SPEEDS = (6.6, 5.9, 5.1, 4.5, 5.1, 8.3, 16.3, 10.2, 14.3, 17.5)
_DIRECTIONS = (0.0, 0.0, 0.0, 0.0, 90.0, -90.0, -90.0, 90.0, 0.0, 0.0)


@dataclass(frozen=True)
class AtmosphereSettings:
    """Turbulence conditions (TOML table ``[scene.optics.atmosphere]``).

    Parameters
    ----------
    seeing : float
        Zenith seeing FWHM at 500 nm (arcsec); r0 = 0.98 lambda / seeing.
    zenith_angle : float
        Observing zenith angle (deg).
    outer_scale : float
        von Karman outer scale L0 (m).
    layer_heights : tuple of float
        Layer altitudes above the telescope at zenith (m).
    layer_weights : tuple of float
        Fractional Cn^2 of each layer (normalised to sum 1).
    wind_speeds : tuple of float
        Wind speed of each layer (m/s).
    wind_directions : tuple of float
        Wind direction of each layer (deg, from +x towards +y).
    """

    seeing: float = unit_field(0.8, "arcsec", "zenith seeing FWHM at 500 nm")
    zenith_angle: float = unit_field(30.0, "deg", "zenith angle")
    outer_scale: float = unit_field(25.0, "m", "von Karman outer scale L0")
    layer_heights: tuple[float, ...] = field(default=_HEIGHTS)
    layer_weights: tuple[float, ...] = field(default=_WEIGHTS)
    wind_speeds: tuple[float, ...] = field(default=_SPEEDS)
    wind_directions: tuple[float, ...] = field(default=_DIRECTIONS)

    def __post_init__(self):
        n = len(self.layer_heights)
        if n == 0:
            raise ValueError("layer_heights must list at least one layer")
        for name in ("layer_weights", "wind_speeds", "wind_directions"):
            if len(getattr(self, name)) != n:
                raise ValueError(
                    f"{name} has {len(getattr(self, name))} values but layer_heights has {n}"
                )
        if not self.seeing > 0:
            raise ValueError(f"seeing must be > 0 arcsec, got {self.seeing}")
        if not 0 <= self.zenith_angle < 80:
            raise ValueError(f"zenith_angle must be in [0, 80) deg, got {self.zenith_angle}")
        if not self.outer_scale > 0:
            raise ValueError(f"outer_scale must be > 0 m, got {self.outer_scale}")
        w = np.asarray(self.layer_weights, float)
        if np.any(w < 0) or not w.sum() > 0:
            raise ValueError("layer_weights must be >= 0 with a positive sum")
        if np.any(np.asarray(self.layer_heights) < 0):
            raise ValueError("layer_heights must be >= 0 m")


@dataclass(frozen=True)
class Layers:
    """Turbulent layers along the line of sight (airmass applied).

    Parameters
    ----------
    heights : ndarray
        Distance along the line of sight (m).
    weights : ndarray
        Fractional Cn^2 (sum 1).
    velocities : ndarray, shape (L, 2)
        Wind velocity vectors (m/s).
    """

    heights: np.ndarray
    weights: np.ndarray
    velocities: np.ndarray


def airmass(settings: AtmosphereSettings) -> float:
    """Airmass sec(z) of the observation (dimensionless).

    Parameters
    ----------
    settings : AtmosphereSettings
        ``zenith_angle`` [deg].

    Returns
    -------
    float
        sec(z).
    """
    return 1.0 / np.cos(np.radians(settings.zenith_angle))


def fried_parameter(settings: AtmosphereSettings, wavelength: float) -> float:
    """Line-of-sight Fried parameter r0 (m) at ``wavelength`` (m).

    ``r0 = 0.98 lambda_ref / seeing`` at the reference wavelength and zenith, scaled as
    ``lambda^1.2`` and ``airmass^-0.6``.

    Parameters
    ----------
    settings : AtmosphereSettings
        ``seeing`` [arcsec] and ``zenith_angle`` [deg].
    wavelength : float
        Wavelength [m].

    Returns
    -------
    float
        r0 [m].
    """
    r0_zenith = 0.98 * REFERENCE_WAVELENGTH / (settings.seeing / ARCSEC_PER_RAD)
    return r0_zenith * (wavelength / REFERENCE_WAVELENGTH) ** 1.2 * airmass(settings) ** -0.6


def layers(settings: AtmosphereSettings) -> Layers:
    """The turbulent layers with airmass-stretched distances and wind vectors.

    Parameters
    ----------
    settings : AtmosphereSettings
        Layer heights [m], Cn^2 weights, wind speeds [m/s] and directions [deg].

    Returns
    -------
    Layers
        Distances along the line of sight [m], normalised weights, velocities [m/s].
    """
    w = np.asarray(settings.layer_weights, float)
    ang = np.radians(np.asarray(settings.wind_directions, float))
    speed = np.asarray(settings.wind_speeds, float)
    return Layers(
        heights=np.asarray(settings.layer_heights, float) * airmass(settings),
        weights=w / w.sum(),
        velocities=np.stack([speed * np.cos(ang), speed * np.sin(ang)], axis=-1),
    )


def von_karman_psd(f2: np.ndarray, r0: float, outer_scale: float) -> np.ndarray:
    """von Karman phase power spectral density.

    Parameters
    ----------
    f2 : ndarray
        Squared spatial frequency |f|^2 (m^-2).
    r0 : float
        Fried parameter (m) at the wavelength of the phase.
    outer_scale : float
        Outer scale L0 (m).

    Returns
    -------
    ndarray
        W(f) in rad^2 m^2; finite at f = 0 thanks to the outer scale.
    """
    return VON_KARMAN_CONSTANT * r0 ** (-5.0 / 3.0) * (f2 + outer_scale**-2) ** (-11.0 / 6.0)


def von_karman_variance_beyond(f_min: float, r0: float, outer_scale: float) -> float:
    """Phase variance (rad^2) of the von Karman spectrum at |f| > ``f_min`` (m^-1).

    Closed form of 2 pi int_fmin^inf W(f) f df.

    Parameters
    ----------
    f_min : float
        Lower frequency limit [1/m].
    r0 : float
        Fried parameter [m].
    outer_scale : float
        Outer scale L0 [m].

    Returns
    -------
    float
        Phase variance [rad^2].
    """
    a = f_min**2 + outer_scale**-2
    return float(
        VON_KARMAN_CONSTANT * r0 ** (-5.0 / 3.0) * 2 * np.pi * 0.5 * (6.0 / 5.0) * a ** (-5.0 / 6.0)
    )


def von_karman_covariance(r: np.ndarray, r0: float, outer_scale: float) -> np.ndarray:
    """von Karman phase covariance ``B(r)`` (rad^2) at separations ``r`` (m).

    ``B(r) = (L0 / r0)^(5/3) c x^(5/6) K_(5/6)(x)``, ``x = 2 pi r / L0``, with
    ``c = 2^(-5/6) Gamma(11/6) pi^(-8/3) (24/5 Gamma(6/5))^(5/6)``, the transform of
    :func:`von_karman_psd` (variance ``0.0863 (L0 / r0)^(5/3)``; ``2 [B(0) - B(r)]``
    tends to ``6.88 (r / r0)^(5/3)`` for ``r << L0``).

    Parameters
    ----------
    r : ndarray
        Separations [m], >= 0.
    r0 : float
        Fried parameter [m].
    outer_scale : float
        Outer scale L0 [m].

    Returns
    -------
    ndarray
        Covariance [rad^2].
    """
    from scipy.special import gamma, kv

    c = 2 ** (-5 / 6) * gamma(11 / 6) / np.pi ** (8 / 3) * (24 / 5 * gamma(6 / 5)) ** (5 / 6)
    x = 2 * np.pi * np.maximum(np.asarray(r, float), 1e-12 * outer_scale) / outer_scale
    return (outer_scale / r0) ** (5 / 3) * c * x ** (5 / 6) * kv(5 / 6, x)
