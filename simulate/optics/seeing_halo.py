"""Seeing halo: the large (40") central PSF beyond the control radius, as a ramped kernel.

The renderer adds the light outside the core stamps by convolving the
"kernel field" with this halo (paper section 3.2). The large PSF is the
Hankel transform of ``OTF_tel(r) exp(-D(r)/2)`` with ``D(r)`` from the
azimuthally averaged on-axis residual PSD (the computed PSD inside the PSD
grid, the von Karman spectrum beyond). It is multiplied by a raised-cosine
ramp that rises from 0 at ``ramp_start`` (default: the control radius) to 1
at ``ramp_end`` (default: 95% of the stamp half-width); the core stamps are
tapered with ``1 - ramp`` so core + halo conserve flux.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mavispm.core.config import unit_field
from mavispm.simulate.optics.atmosphere import ARCSEC_PER_RAD, MAS_PER_RAD, von_karman_psd

__all__ = [
    "Halo",
    "HaloSettings",
    "build_halo",
    "ramp",
]


@dataclass(frozen=True)
class HaloSettings:
    """Seeing-wing kernel (TOML table ``[scene.optics.halo]``).

    Parameters
    ----------
    enabled : bool
        Whether to model the halo at all (None halo, untapered stamps when off).
    size : float
        Width of the large central PSF / kernel (arcsec).
    ramp_start : float or None
        Radius where the ramp starts (arcsec); None = the AO control radius.
    ramp_end : float or None
        Radius where the ramp reaches 1 (arcsec); None = 95% of the stamp half-width.
    """

    enabled: bool = True
    size: float = unit_field(40.0, "arcsec", "halo kernel width")
    ramp_start: float | None = unit_field(None, "arcsec", "ramp start radius")
    ramp_end: float | None = unit_field(None, "arcsec", "ramp end radius")

    def __post_init__(self):
        if not self.size > 0:
            raise ValueError(f"halo size must be > 0 arcsec, got {self.size}")
        if self.ramp_start is not None and self.ramp_start < 0:
            raise ValueError("ramp_start must be >= 0 arcsec")


def ramp(radius: ArrayLike, start: float, end: float) -> np.ndarray:
    """Raised-cosine ramp: 0 below ``start``, 1 above ``end`` (same units as radius).

    Parameters
    ----------
    radius : array_like
        Radii.
    start, end : float
        Ramp limits, same unit; ``end <= start`` gives a step at ``start``.

    Returns
    -------
    ndarray
        Ramp values in [0, 1].
    """
    r = np.asarray(radius, float)
    if end <= start:
        return (r >= start).astype(float)
    t = np.clip((r - start) / (end - start), 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * t)


def _annular_otf(r, diameter, eps):
    """Azimuthally symmetric OTF of an annular pupil at separation r (m), 1 at r = 0."""

    def overlap(rad, s):  # area of intersection of two discs of radius rad, centres s apart
        s = np.minimum(s, 2 * rad)
        return 2 * rad**2 * np.arccos(s / (2 * rad)) - 0.5 * s * np.sqrt(
            np.maximum(4 * rad**2 - s**2, 0)
        )

    def cross(r1, r2, s):  # intersection area of discs of radii r1, r2
        out = np.zeros_like(s)
        full = s <= abs(r1 - r2)
        out[full] = np.pi * min(r1, r2) ** 2
        part = (~full) & (s < r1 + r2)
        sp = s[part]
        a1 = r1**2 * np.arccos(np.clip((sp**2 + r1**2 - r2**2) / (2 * sp * r1), -1, 1))
        a2 = r2**2 * np.arccos(np.clip((sp**2 + r2**2 - r1**2) / (2 * sp * r2), -1, 1))
        a3 = 0.5 * np.sqrt(
            np.maximum((-sp + r1 + r2) * (sp + r1 - r2) * (sp - r1 + r2) * (sp + r1 + r2), 0)
        )
        out[part] = a1 + a2 - a3
        return out

    big, small = diameter / 2, eps * diameter / 2
    r = np.asarray(r, float)
    area = overlap(big, r)
    if small > 0:
        area = area + overlap(small, r) - 2 * cross(big, small, r)
    return area / (np.pi * (big**2 - small**2))


def _radius_grid(n: int, pixel_scale: float) -> np.ndarray:
    """Distance (in units of ``pixel_scale``) of each pixel of an n x n grid from its centre."""
    x = (np.arange(n) - (n - 1) / 2) * pixel_scale
    return np.hypot(x[None, :], x[:, None])


@dataclass(frozen=True, eq=False)
class Halo:
    """Radial profile of the large central PSF and its ramp.

    Parameters
    ----------
    radius : ndarray
        Radii (mas) of the tabulated profile.
    profile : ndarray
        PSF per unit solid angle (mas^-2), total light normalised to 1.
    ramp_start, ramp_end : float
        Ramp radii (mas).
    size : float
        Kernel width (mas).
    fraction : float
        Light in the ramped wings within the kernel (fraction of the total).
    """

    radius: np.ndarray
    profile: np.ndarray
    ramp_start: float
    ramp_end: float
    size: float
    fraction: float

    def kernel(self, pixel_scale_mas: float) -> np.ndarray:
        """The ramped halo on a pixel grid, odd-sized and centred, summing to ``fraction``.

        Parameters
        ----------
        pixel_scale_mas : float
            Pixel of the kernel (mas), for example the 7.5 mas detector pixel.
        """
        if not pixel_scale_mas > 0:
            raise ValueError(f"pixel_scale_mas must be > 0, got {pixel_scale_mas}")
        n = int(round(self.size / pixel_scale_mas)) // 2 * 2 + 1
        r = _radius_grid(n, pixel_scale_mas)
        k = np.interp(r, self.radius, self.profile * (self.radius <= self.size / 2), right=0.0)
        k *= ramp(r, self.ramp_start, self.ramp_end)
        s = k.sum()
        return k * (self.fraction / s) if s > 0 else k

    def core_taper(self, n: int, pixel_scale_mas: float) -> np.ndarray:
        """``1 - ramp`` on an ``n`` x ``n`` stamp grid (applied to the core PSFs).

        Parameters
        ----------
        n : int
            Stamp size [pixel] (centred on the middle pixel).
        pixel_scale_mas : float
            Stamp pixel [mas].

        Returns
        -------
        ndarray, shape (n, n)
            Taper in [0, 1].
        """
        return 1.0 - ramp(_radius_grid(n, pixel_scale_mas), self.ramp_start, self.ramp_end)


def build_halo(
    settings: HaloSettings,
    psd_frequency: np.ndarray,
    psd_profile: np.ndarray,
    wavelength: float,
    diameter: float,
    obscuration_ratio: float,
    r0: float,
    outer_scale: float,
    control_radius_mas: float,
    stamp_half_width_mas: float,
    oversampling: float = 1.0,
) -> Halo:
    """Compute the halo from the on-axis radial PSD.

    Parameters
    ----------
    settings : HaloSettings
        Kernel size and ramp radii.
    psd_frequency, psd_profile : ndarray
        Azimuthally averaged on-axis residual PSD (m^-1, rad^2 m^2); beyond
        its last frequency the von Karman spectrum is used.
    wavelength : float
        Wavelength (m).
    diameter : float
        Pupil diameter (m).
    obscuration_ratio : float
        Central obstruction over pupil diameter.
    r0, outer_scale : float
        Atmosphere at that wavelength (m).
    control_radius_mas : float
        AO control radius (mas); the default ramp start.
    stamp_half_width_mas : float
        Half-width of the core PSF stamps (mas); the default ramp end is 95 % of it.
    oversampling : float
        Sampling of the Hankel integrals relative to Nyquist (accuracy knob).
    """
    from scipy.special import j0  # ~0.3-0.5 s to import: only when the halo is computed

    # radial PSD over a wide log grid
    f_hi = 4 * (settings.size / 2 / ARCSEC_PER_RAD) / wavelength
    f = np.geomspace(1e-3, max(f_hi, 10.0), 6000)
    fmax = psd_frequency[-1] if psd_frequency.size else 0.0
    psd = von_karman_psd(f**2, r0, outer_scale)
    if psd_frequency.size:
        psd = np.where(f <= fmax, np.interp(f, psd_frequency, psd_profile), psd)
    # structure function D(r) = 2 int PSD (1 - J0(2 pi f r)) 2 pi f df (trapezoid in log f)
    w = psd * 2 * np.pi * f * np.gradient(f)
    r_coarse = diameter * np.linspace(0.0, 1.0, 400) ** 2  # dense near the r -> 0 cusp
    d_coarse = 2 * ((1 - j0(2 * np.pi * r_coarse[:, None] * f[None, :])) @ w)
    alpha_max = settings.size / 2 * np.sqrt(2) / ARCSEC_PER_RAD
    # Nyquist in r for the largest angle, and in angle for the pupil size
    n_radius = int(np.ceil(oversampling * 2 * diameter * alpha_max / wavelength)) + 64
    n_alpha = int(np.ceil(oversampling * 2 * diameter * alpha_max / wavelength)) + 64
    r = np.linspace(0.0, diameter, n_radius)
    dfun = np.interp(r, r_coarse, d_coarse)
    otf = _annular_otf(r, diameter, obscuration_ratio) * np.exp(-0.5 * dfun)
    # PSF(alpha) = 2 pi int OTF(r) J0(2 pi r alpha / lambda) r dr / lambda^2, per rad^2
    alpha = np.linspace(0.0, alpha_max, n_alpha)
    dr = r[1] - r[0]
    wr = otf * r * dr
    wr[0] *= 0.5
    wr[-1] *= 0.5
    prof = np.empty_like(alpha)
    for i0 in range(0, alpha.size, 250):
        a = alpha[i0 : i0 + 250]
        prof[i0 : i0 + 250] = (
            2 * np.pi * (j0(2 * np.pi * a[:, None] * r[None, :] / wavelength) @ wr)
        )
    prof /= wavelength**2
    prof = np.clip(prof, 0.0, None) / MAS_PER_RAD**2  # per mas^2
    alpha_mas = alpha * MAS_PER_RAD
    start = control_radius_mas if settings.ramp_start is None else settings.ramp_start * 1000
    end = 0.95 * stamp_half_width_mas if settings.ramp_end is None else settings.ramp_end * 1000
    if end < start:
        start, end = end, start
    # fraction of the total light in the ramped wings within the kernel disc
    inside = alpha_mas <= settings.size * 1000 / 2
    integrand = prof * ramp(alpha_mas, start, end) * 2 * np.pi * alpha_mas
    fraction = float(np.trapezoid(integrand[inside], alpha_mas[inside]))
    fraction = min(max(fraction, 0.0), 1.0)
    return Halo(alpha_mas, prof, start, end, settings.size * 1000, fraction)
