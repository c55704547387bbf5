"""Differential atmospheric refraction (DAR) of broadband star images, after an ADC.

The atmosphere lifts every image towards the zenith by ``R(lambda) ~ (n(lambda) - 1)
tan z`` (plane-parallel atmosphere, good to ~0.1% below z = 60 deg); blue light is
lifted more than red. Through a filter each star's image is therefore the
photon-weighted sum of monochromatic images spread along the zenith direction, and its
centroid sits at the photon-weighted mean refraction of its spectrum: hot and cool stars
land at different places (paper tab:astrobudget, "Atmospheric Differential Refraction").
An atmospheric dispersion corrector (ADC) removes most of the spread; the fraction left,
``adc_residual``, scales both the centroid shift and the spread.

The refractive index of moist air is that of Filippenko (1982, PASP 94, 715), eqs. 1-3:
Edlén's dry-air dispersion at 15 C and 760 mmHg, scaled to temperature ``T`` and pressure
``P``, minus the water-vapour term. The vapour pressure follows from the relative
humidity by the Magnus formula (Alduchov & Eskridge 1996). The stellar spectrum is a
black body of the star's effective temperature; the filter is the Bessell (1990, PASP 102,
1181) V band, a top-hat band, or one wavelength.

Everything is relative to ``reference_wavelength``, the wavelength whose image the
telescope guiding holds fixed: a common shift of all stars is absorbed by the alignment
of every epoch, the colour-dependent part is not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from mavispm.core.config import unit_field

__all__ = [
    "RefractionSettings",
    "air_refractivity",
    "at_epoch",
    "band_refraction",
    "band_response",
    "photon_weights",
    "refraction",
    "saturation_vapour_pressure",
    "star_displacement",
]

#: arcsec per radian
_ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0
#: hPa per mmHg
_HPA_PER_MMHG = 1.333224
#: h c / k [m K]
_HC_OVER_K = 1.438776877e-2

#: Bessell (1990) V passband: wavelength [nm], relative response
BESSELL_V = np.array(
    [
        (470, 0.000), (480, 0.030), (490, 0.163), (500, 0.458), (510, 0.780),
        (520, 0.967), (530, 1.000), (540, 0.973), (550, 0.898), (560, 0.792),
        (570, 0.684), (580, 0.574), (590, 0.461), (600, 0.359), (610, 0.270),
        (620, 0.197), (630, 0.135), (640, 0.081), (650, 0.045), (660, 0.025),
        (670, 0.017), (680, 0.013), (690, 0.009), (700, 0.000),
    ]
)  # fmt: skip


@dataclass(frozen=True)
class RefractionSettings:
    """Atmospheric refraction of a scene (TOML table ``[scene.optics.refraction]``).

    Parameters
    ----------
    enabled : bool
        Apply the colour-dependent shift (off: no displacement at all).
    zenith_angle : float
        Zenith angle of the observation [deg].
    zenith_direction : float
        Direction towards the zenith on the detector, counter-clockwise from +x [deg]
        (the parallactic angle plus the field rotation).
    temperature : float
        Air temperature [deg_C]; Paranal median 10 C.
    pressure : float
        Air pressure [hPa]; Paranal ~743 hPa.
    relative_humidity : float
        Relative humidity, 0 to 1.
    adc_residual : float
        Fraction of the dispersion the ADC leaves (0: perfect ADC, 1: no ADC).
    reference_wavelength : float
        Wavelength held fixed by the guiding [nm].
    band : {"V", "tophat", "monochromatic"}
        Filter: Bessell V, a flat band ``band_min``-``band_max``, or ``reference_wavelength``.
    band_min, band_max : float
        Edges of the top-hat band [nm].
    default_teff : float
        Effective temperature of stars without a ``teff`` column [K].
    epochs : tuple of (float, float, float)
        Per-epoch pointing ``(epoch [yr], zenith_angle [deg], zenith_direction [deg])``
        overriding the two angles at that epoch (each epoch is taken at its own hour
        angle, so the colour shifts differ between epochs and enter proper motions).
    """

    enabled: bool = False
    zenith_angle: float = unit_field(30.0, "deg", "zenith angle")
    zenith_direction: float = unit_field(90.0, "deg", "towards the zenith, from +x")
    temperature: float = unit_field(10.0, "deg_C", "air temperature")
    pressure: float = unit_field(743.0, "hPa", "air pressure")
    relative_humidity: float = 0.15
    adc_residual: float = 0.05
    reference_wavelength: float = unit_field(550.0, "nm", "held fixed by the guiding")
    band: Literal["V", "tophat", "monochromatic"] = "V"
    band_min: float = unit_field(470.0, "nm", "top-hat band edge")
    band_max: float = unit_field(700.0, "nm", "top-hat band edge")
    default_teff: float = unit_field(5500.0, "K", "stars without teff")
    epochs: tuple[tuple[float, float, float], ...] = ()

    def __post_init__(self):
        if not 0 <= self.zenith_angle <= 70:
            raise ValueError(
                f"zenith_angle must be 0 to 70 deg (plane-parallel refraction), got {self.zenith_angle}"
            )
        if not -60 <= self.temperature <= 50:
            raise ValueError(f"temperature must be -60 to 50 deg_C, got {self.temperature}")
        if not 0 < self.pressure <= 1100:
            raise ValueError(f"pressure must be 0 to 1100 hPa, got {self.pressure}")
        if not 0 <= self.relative_humidity <= 1:
            raise ValueError(f"relative_humidity must be 0 to 1, got {self.relative_humidity}")
        if not 0 <= self.adc_residual <= 1:
            raise ValueError(f"adc_residual must be 0 to 1, got {self.adc_residual}")
        if not 300 <= self.reference_wavelength <= 2500:
            raise ValueError("reference_wavelength must be 300 to 2500 nm")
        if not 300 <= self.band_min < self.band_max <= 2500:
            raise ValueError("band_min < band_max must lie within 300 to 2500 nm")
        if not 1000 <= self.default_teff <= 100000:
            raise ValueError("default_teff must be 1000 to 100000 K")
        for row in self.epochs:
            if len(row) != 3 or not 0 <= row[1] <= 70:
                raise ValueError(
                    "epochs rows must be [epoch yr, zenith_angle 0-70 deg, zenith_direction deg]"
                )
        if self.band not in ("V", "tophat", "monochromatic"):
            raise ValueError(f"band must be 'V', 'tophat' or 'monochromatic', got {self.band!r}")


def saturation_vapour_pressure(temperature: float) -> float:
    """Saturation vapour pressure of water over liquid [hPa] at ``temperature`` [deg_C] (Magnus).

    Parameters
    ----------
    temperature : float
        Air temperature [deg_C].

    Returns
    -------
    float
        ``6.1094 exp(17.625 T / (T + 243.04))`` [hPa].
    """
    return 6.1094 * np.exp(17.625 * temperature / (temperature + 243.04))


def air_refractivity(wavelength, temperature: float, pressure: float, humidity: float):
    """``n - 1`` of moist air (Filippenko 1982, eqs. 1-3).

    Parameters
    ----------
    wavelength : float or array
        Vacuum wavelength [nm].
    temperature : float
        [deg_C].
    pressure : float
        [hPa].
    humidity : float
        Relative humidity, 0 to 1.
    """
    sigma2 = (1000.0 / np.asarray(wavelength, float)) ** 2  # (1/micron)^2
    dry_std = 64.328 + 29498.1 / (146.0 - sigma2) + 255.4 / (41.0 - sigma2)
    p = pressure / _HPA_PER_MMHG
    t = temperature
    dry = dry_std * p * (1.0 + (1.049 - 0.0157 * t) * 1e-6 * p) / (720.883 * (1.0 + 0.003661 * t))
    f = humidity * saturation_vapour_pressure(t) / _HPA_PER_MMHG
    wet = (0.0624 - 0.000680 * sigma2) / (1.0 + 0.003661 * t) * f
    return (dry - wet) * 1e-6


def refraction(wavelength, settings: RefractionSettings):
    """Refraction ``R = (n - 1) tan z`` [arcsec] at ``wavelength`` [nm].

    Parameters
    ----------
    wavelength : float or ndarray
        Vacuum wavelength [nm].
    settings : RefractionSettings
        Temperature [deg_C], pressure [hPa], relative humidity and zenith angle [deg].

    Returns
    -------
    float or ndarray
        Refraction [arcsec].
    """
    n1 = air_refractivity(
        wavelength, settings.temperature, settings.pressure, settings.relative_humidity
    )
    return n1 * np.tan(np.radians(settings.zenith_angle)) * _ARCSEC_PER_RAD


def band_response(settings: RefractionSettings) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths [nm] and relative filter response of the band on a fine grid.

    Parameters
    ----------
    settings : RefractionSettings
        ``band``: ``"V"`` (Bessell V), ``"tophat"`` (``band_min`` to ``band_max``) or
        monochromatic (``reference_wavelength``).

    Returns
    -------
    wavelength : ndarray
        Wavelengths [nm] (461 samples; one for a monochromatic band).
    response : ndarray
        Relative response (dimensionless).
    """
    if settings.band == "V":
        lam = np.linspace(BESSELL_V[0, 0], BESSELL_V[-1, 0], 461)
        return lam, np.interp(lam, BESSELL_V[:, 0], BESSELL_V[:, 1])
    if settings.band == "tophat":
        lam = np.linspace(settings.band_min, settings.band_max, 461)
        return lam, np.ones_like(lam)
    return np.array([settings.reference_wavelength]), np.ones(1)


def photon_weights(teff, settings: RefractionSettings) -> tuple[np.ndarray, np.ndarray]:
    """Detected-photon fractions of black bodies on the band's wavelength grid.

    Parameters
    ----------
    teff : float or array
        Effective temperature [K].
    settings : RefractionSettings
        The band.

    Returns
    -------
    lam : numpy.ndarray (L,)
        Wavelengths [nm] (:func:`band_response`).
    weights : numpy.ndarray (N, L)
        Fraction of each star's detected photons at each grid wavelength (rows sum to 1).
    """
    teff = np.atleast_1d(np.asarray(teff, float))
    lam, response = band_response(settings)
    x = _HC_OVER_K / (lam[None, :] * 1e-9 * teff[:, None])
    # photons per unit wavelength of a black body: B_lambda * lambda ~ lambda^-4 / (e^x - 1)
    with np.errstate(over="ignore"):
        photons = response[None, :] * lam[None, :] ** -4 / np.expm1(np.minimum(x, 700.0))
    return lam, photons / photons.sum(axis=1, keepdims=True)


def band_refraction(teff, settings: RefractionSettings) -> tuple[np.ndarray, np.ndarray]:
    """Photon-weighted mean refraction of a black body through the band, and its RMS spread.

    Parameters
    ----------
    teff : float or array
        Effective temperature [K].
    settings : RefractionSettings

    Returns
    -------
    mean, rms : numpy.ndarray
        [arcsec], absolute (not yet relative to the reference wavelength, no ADC).
    """
    lam, w = photon_weights(teff, settings)
    r = refraction(lam, settings)
    mean = w @ r
    rms = np.sqrt(np.maximum(w @ r**2 - mean**2, 0.0))
    return mean, rms


def at_epoch(settings: RefractionSettings, epoch: float | None) -> RefractionSettings:
    """The settings with the pointing of ``epoch`` [yr] from ``settings.epochs``, if listed.

    Parameters
    ----------
    settings : RefractionSettings
        The refraction settings with their per-epoch pointings.
    epoch : float or None
        Epoch [yr] (matched to 1e-9 yr).

    Returns
    -------
    RefractionSettings
        A copy with that epoch's zenith angle and direction, or ``settings`` unchanged.
    """
    import dataclasses

    for t, z, direction in settings.epochs:
        if epoch is not None and abs(t - epoch) < 1e-9:
            return dataclasses.replace(settings, zenith_angle=z, zenith_direction=direction)
    return settings


def star_displacement(
    teff, settings: RefractionSettings, epoch: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Colour-dependent DAR displacement of star images on the detector [arcsec].

    ``adc_residual * (R_band(teff) - R(reference_wavelength))`` along the zenith
    direction; exactly zero when disabled.

    Parameters
    ----------
    teff : float or array
        Effective temperatures [K] (NaN takes ``default_teff``).
    settings : RefractionSettings
    epoch : float, optional
        Epoch [yr], selecting a per-epoch pointing from ``settings.epochs``.

    Returns
    -------
    dx, dy : numpy.ndarray
        [arcsec] along the field x and y axes.
    """
    teff = np.atleast_1d(np.asarray(teff, float))
    if not settings.enabled:
        return np.zeros(teff.shape), np.zeros(teff.shape)
    settings = at_epoch(settings, epoch)
    teff = np.where(np.isfinite(teff), teff, settings.default_teff)
    mean, _ = band_refraction(teff, settings)
    shift = settings.adc_residual * (mean - refraction(settings.reference_wavelength, settings))
    theta = np.radians(settings.zenith_direction)
    return shift * np.cos(theta), shift * np.sin(theta)
