"""Tip-tilt residual kernels from the NGS asterism (paper section 3.1.2).

Per field position the atmospheric TT residual is a 2-D Gaussian with
covariance ``C = s^2 (C_tomo + C_noise + sigma_ws^2 I)``:

* ``C_tomo + C_noise``: MMSE estimate of the science-direction tilt from the
  NGS tilts. Tilt covariances between directions follow from the layered von
  Karman spectrum filtered by the G-tilt of the annular pupil,
  ``K_ij(rho) = a(rho) delta_ij - b(rho) rho_i rho_j / rho^2`` with
  ``a = pi int f^3 S (J0 + J2) df`` and ``b = 2 pi int f^3 S J2 df`` at the
  separation ``rho = h_l |alpha - theta|`` of each layer, so the kernels are
  elongated along the NGS-target axes (anisoplanatism). ``tilt = "G"``
  (default): the gradient-averaged tilt, whose filter is the pupil's Fourier
  transform ``(jinc(x) - eps^2 jinc(eps x)) / (1 - eps^2)``, ``x = pi D f``: the
  centroid of the image moves by exactly the pupil-averaged phase gradient.
  ``tilt = "Z"``: the Zernike (least-squares plane) tilt,
  ``8 (J2(x) - eps^2 J2(eps x)) / (x^2 (1 - eps^4))``, what TIPTOP's ``mastsel``
  computes (its Zernike covariances); a cross-check.
* NGS noise: photon and read noise of a centroid per loop frame from the H
  magnitude, reduced by the closed-loop noise gain g / (2 - g).
* MCAO filter (optional, TIPTOP's ``[sensor_LO] filtZernikeCov``; off by default
  because the paper's maps are reproduced without it, docs/optics.md): the
  LGS tomography and the DMs correct every spatial frequency of the turbulence
  except the lowest radial orders of the meta-pupil (piston, tilt, focus /
  astigmatism: the modes the LGS cannot register, whose field derivatives are
  the TT anisoplanatism), within the HO loop bandwidth. The tilt covariances
  are computed from the turbulence spectrum times the rejection
  ``1 - lpf(f) filt(f)`` of ``mastsel``'s ``zernikeCovarianceDfiltered``
  (Sasiela 1993 radial-order filters on a meta-pupil of radius
  ``D / 2 + h_mean tan(fov / 2)``; ``lpf = c / (f^2 + c)``,
  ``c = 0.8 f_HO / v_mean^2``), so the NGS handle only what MCAO leaves.
* ``sigma_ws``: residual windshake / telescope vibration of the TT loop.
* ``s``: the scale factor (the x3 cases of the paper's simulation table).

All outputs are in mas^2 (covariances) and arcsec (positions).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mavispm.core.config import unit_field
from mavispm.simulate.optics.atmosphere import (
    ARCSEC_PER_RAD,
    MAS_PER_RAD,
    REFERENCE_WAVELENGTH,
    AtmosphereSettings,
    fried_parameter,
    layers,
    von_karman_psd,
)
from mavispm.simulate.optics.pupil import PupilSettings

__all__ = [
    "KernelMap",
    "PRESETS",
    "TiltCovariance",
    "TipTiltField",
    "TipTiltSettings",
    "atmospheric_cross_covariance",
    "field_average_sigma",
    "kernel_map",
    "ngs_noise_variance",
    "ngs_positions",
    "tilt_covariance_function",
]

#: NGS constellations of the paper's table tab:ttjitter: (radius arcsec, angle deg, H mag)
PRESETS: dict[str, tuple[tuple[float, float, float], ...]] = {
    "good": ((10.0, 0.0, 15.0), (10.0, 120.0, 15.0), (10.0, 240.0, 15.0)),
    "typical": ((30.0, 330.0, 16.0), (40.0, 90.0, 18.0), (10.0, 150.0, 18.0)),
    "bad": ((40.0, 0.0, 18.0), (40.0, 120.0, 18.0), (40.0, 240.0, 18.0)),
}


@dataclass(frozen=True)
class TipTiltSettings:
    """NGS tip-tilt residual (TOML table ``[scene.optics.tiptilt]``).

    Parameters
    ----------
    enabled : bool
        Off gives zero covariance everywhere.
    asterism : {"good", "typical", "bad", "custom"}
        A preset of the paper's table, or ``custom`` to use ``ngs``.
    ngs : tuple of (radius arcsec, angle deg, H mag)
        Custom asterism, polar coordinates about the field centre.
    scale_factor : float
        Multiplies the residual sigma (covariance by its square).
    windshake : float
        Residual windshake / vibration of the TT loop, per axis (mas).
    frame_rate : float
        LO loop rate (Hz).
    loop_gain : float
        LO integrator gain; noise gain g / (2 - g).
    zeropoint : float
        Detected photons per second from an H = 0 star, whole pupil and
        throughput included (ph/s).
    spot_fwhm : float
        Partially corrected NGS spot FWHM on the LO WFS (mas).
    read_noise : float
        Detector read noise (e- per pixel per frame).
    n_pixels : int
        Pixels in the centroiding window.
    wfs_pixel : float
        LO WFS pixel (mas).
    mcao_filter : bool
        Remove from the tilt covariances what the MCAO high-order loop corrects
        (see the module docstring); False for an NGS-only tip-tilt tomography of
        the open-loop turbulence.
    technical_fov : float
        Diameter of the technical field that sets the meta-pupil (arcsec,
        MAVIS.ini ``TechnicalFoV``).
    ho_frame_rate : float
        HO loop rate (Hz) of the MCAO filter's temporal rejection.
    tilt : {"G", "Z"}
        Tilt definition of the covariances: "G" (default) the gradient (centroid)
        tilt, "Z" the Zernike tilt of TIPTOP's ``mastsel`` (a cross-check).
    """

    enabled: bool = True
    asterism: Literal["good", "typical", "bad", "custom"] = "typical"
    ngs: tuple[tuple[float, float, float], ...] = field(default=())
    scale_factor: float = 1.0
    windshake: float = unit_field(0.0, "mas", "residual TT windshake per axis")
    frame_rate: float = unit_field(500.0, "Hz", "LO loop rate")
    loop_gain: float = 0.3
    zeropoint: float = 4.0e10
    spot_fwhm: float = unit_field(50.0, "mas", "NGS spot FWHM")
    read_noise: float = 0.5
    n_pixels: int = 16
    wfs_pixel: float = unit_field(25.0, "mas", "LO WFS pixel")
    mcao_filter: bool = False
    technical_fov: float = unit_field(120.0, "arcsec", "technical field diameter")
    ho_frame_rate: float = unit_field(1000.0, "Hz", "HO loop rate")
    tilt: Literal["G", "Z"] = "G"

    def __post_init__(self):
        if self.asterism == "custom" and not self.ngs:
            raise ValueError("asterism = 'custom' needs at least one star in ngs")
        for i, star in enumerate(self.ngs):
            r, _, mag = star
            if not (np.isfinite(r) and r >= 0 and np.isfinite(mag)):
                raise ValueError(f"ngs[{i}] must be (radius >= 0 arcsec, angle deg, H mag)")
        if self.scale_factor < 0:
            raise ValueError("scale_factor must be >= 0")
        if not 0 < self.loop_gain < 2:
            raise ValueError("loop_gain must be in (0, 2)")
        if self.frame_rate <= 0 or self.zeropoint <= 0 or self.spot_fwhm <= 0:
            raise ValueError("frame_rate, zeropoint and spot_fwhm must be > 0")
        if self.windshake < 0 or self.read_noise < 0 or self.n_pixels < 1:
            raise ValueError("windshake, read_noise must be >= 0 and n_pixels >= 1")
        if self.technical_fov < 0 or not self.ho_frame_rate > 0:
            raise ValueError("technical_fov must be >= 0 arcsec and ho_frame_rate > 0 Hz")
        if self.tilt not in ("G", "Z"):
            raise ValueError(f"tilt must be 'G' or 'Z', got {self.tilt!r}")

    def stars(self) -> tuple[tuple[float, float, float], ...]:
        """The asterism in use: (radius arcsec, angle deg, H mag) per NGS."""
        return self.ngs if self.asterism == "custom" else PRESETS[self.asterism]


def ngs_positions(settings: TipTiltSettings) -> tuple[np.ndarray, np.ndarray]:
    """NGS Cartesian positions (arcsec), shape (n, 2), and H magnitudes (n,).

    Parameters
    ----------
    settings : TipTiltSettings
        The asterism (a preset, or ``ngs`` as radius [arcsec], angle [deg], H [mag]).

    Returns
    -------
    xy : ndarray, shape (n, 2)
        NGS positions [arcsec].
    mag : ndarray, shape (n,)
        H magnitudes [mag].
    """
    s = np.asarray(settings.stars(), float).reshape(-1, 3)
    ang = np.radians(s[:, 1])
    return np.stack([s[:, 0] * np.cos(ang), s[:, 0] * np.sin(ang)], -1), s[:, 2]


def ngs_noise_variance(settings: TipTiltSettings, magnitudes: np.ndarray) -> np.ndarray:
    """Closed-loop centroid noise variance per axis (mas^2) for NGS of H ``magnitudes``.

    Photon and read noise of a Gaussian spot per frame, times the integrator's noise gain
    ``g / (2 - g)``.

    Parameters
    ----------
    settings : TipTiltSettings
        Zero point [photon/s at H = 0], frame rate [Hz], spot FWHM [mas], window pixels,
        read noise [electron per pixel per frame], WFS pixel [mas] and loop gain.
    magnitudes : ndarray
        NGS H magnitudes [mag].

    Returns
    -------
    ndarray
        Variance per axis [mas^2].
    """
    photons = (
        settings.zeropoint * 10 ** (-0.4 * np.asarray(magnitudes, float)) / settings.frame_rate
    )
    photons = np.maximum(photons, 1e-30)
    sigma_spot = settings.spot_fwhm / (2 * np.sqrt(2 * np.log(2)))
    photon_term = sigma_spot**2 / photons
    read_term = settings.n_pixels * (settings.read_noise * settings.wfs_pixel) ** 2 / photons**2
    gain = settings.loop_gain / (2 - settings.loop_gain)
    return gain * (photon_term + read_term)


@dataclass(frozen=True, eq=False)
class TiltCovariance:
    """Layer-summed tilt covariance function of angular separation.

    Parameters
    ----------
    rho : ndarray
        Tabulated layer-plane separations (m).
    a, b : ndarray
        ``K_ij(rho) = a delta_ij - b rho_i rho_j / rho^2`` for one unit-weight layer (rad^2).
    heights, weights : ndarray
        Layer distances (m) and Cn^2 fractions.
    """

    rho: np.ndarray
    a: np.ndarray
    b: np.ndarray
    heights: np.ndarray
    weights: np.ndarray

    def __call__(self, delta: np.ndarray) -> np.ndarray:
        """Covariance blocks (..., 2, 2) in rad^2 for angular separations ``delta`` (..., 2) rad.

        The layers' ``a`` and ``b`` are summed first (two scalars per separation), then
        the 2 x 2 blocks are built once: the same sum as adding each layer's block, a
        few times cheaper for 1e6 stars (tested against the per-layer sum).
        """
        delta = np.asarray(delta, float)
        sep = np.hypot(delta[..., 0], delta[..., 1])
        a = np.zeros(sep.shape)
        b = np.zeros(sep.shape)
        for h, w in zip(self.heights, self.weights):
            rho = h * sep
            a += w * np.interp(rho, self.rho, self.a)
            b += w * np.interp(rho, self.rho, self.b)
        safe = np.where(sep > 0, sep, 1.0)
        ux, uy = delta[..., 0] / safe, delta[..., 1] / safe
        out = np.empty(delta.shape[:-1] + (2, 2))
        out[..., 0, 0] = a - b * (ux * ux)
        out[..., 1, 1] = a - b * (uy * uy)
        out[..., 0, 1] = -b * (ux * uy)
        out[..., 1, 0] = out[..., 0, 1]
        return out


def mcao_rejection(
    f: np.ndarray, meta_radius: float, ho_frame_rate: float, wind_speed: float
) -> np.ndarray:
    """Fraction of the turbulence spectrum the MCAO high-order loop leaves to the NGS.

    ``1 - lpf(f) filt(f)`` (``mastsel`` ``zernikeCovarianceDfiltered``, TIPTOP
    ``filtZernikeCov``): ``filt = 1 - [(2 J1(x))^2 + (4 J2(x))^2 + 9 (2 J3(x))^2] / x^2``,
    ``x = 2 pi f R``, removes the piston, tilt and second radial order of the
    meta-pupil of radius R (Sasiela 1993), the modes the LGS cannot register;
    ``lpf = c / (f^2 + c)``, ``c = 0.8 f_HO / v^2``, is the HO loop's rejection
    mapped to spatial frequency through the mean wind v.

    Parameters
    ----------
    f : ndarray
        Spatial frequency (m^-1), > 0.
    meta_radius : float
        Meta-pupil radius R (m).
    ho_frame_rate : float
        HO loop rate (Hz).
    wind_speed : float
        Turbulence-weighted mean wind speed (m/s).

    Returns
    -------
    ndarray
        In [0, 1]: 1 where the HO loop corrects nothing (low meta-pupil orders).
    """
    from scipy.special import j1, jv

    x = 2 * np.pi * np.asarray(f, float) * meta_radius
    x = np.where(x > 1e-8, x, 1e-8)
    low = ((2 * j1(x)) ** 2 + (4 * jv(2, x)) ** 2 + 9 * (2 * jv(3, x)) ** 2) / x**2
    c = 0.8 * ho_frame_rate / wind_speed**2
    lpf = c / (np.asarray(f, float) ** 2 + c)
    return np.clip(1.0 - lpf * (1.0 - low), 0.0, 1.0)


@functools.lru_cache(maxsize=16)
def tilt_covariance_function(
    atmosphere: AtmosphereSettings,
    pupil: PupilSettings,
    max_separation: float,
    mcao: tuple[float, float] | None = None,
    tilt: str = "G",
) -> TiltCovariance:
    """Tabulate the tilt covariance of the layered atmosphere.

    Parameters
    ----------
    atmosphere : AtmosphereSettings
        Turbulence profile, seeing and zenith angle.
    pupil : PupilSettings
        Pupil diameter and obscuration (the annular tilt averaging aperture).
    max_separation : float
        Largest angular separation needed (rad).
    mcao : (float, float) or None
        (technical field diameter arcsec, HO loop rate Hz) of the MCAO filter
        :func:`mcao_rejection`; None for the open-loop turbulence.
    tilt : {"G", "Z"}
        Gradient (centroid) tilt or Zernike tilt (module docstring).
    """
    from scipy.special import j0, j1  # ~0.3-0.5 s to import: a warm process loads the table

    lay = layers(atmosphere)
    r0 = fried_parameter(atmosphere, REFERENCE_WAVELENGTH)
    opd2 = (REFERENCE_WAVELENGTH / (2 * np.pi)) ** 2  # rad^2 -> m^2 of OPD
    # from 1e-8 m^-1: with L0 >> D the tilt variance converges slowly at low frequency
    # (starting at 1e-4 missed 6% / 12% of the Kolmogorov variance for D = 1 / 8 m)
    f = np.geomspace(1e-8, 50.0, 2500)
    x = np.pi * pupil.diameter * f
    eps = pupil.obscuration_ratio
    if tilt == "Z":
        from scipy.special import jv

        filt = 8 * (jv(2, x) - eps**2 * jv(2, eps * x)) / (x**2 * (1 - eps**4))
    else:
        jinc = 2 * j1(x) / x
        jinc_small = 2 * j1(eps * x) / (eps * x) if eps > 0 else np.zeros_like(x)
        filt = (jinc - eps**2 * jinc_small) / (1 - eps**2)
    s = (2 * np.pi) ** 2 * filt**2 * von_karman_psd(f**2, r0, atmosphere.outer_scale) * opd2
    if mcao is not None:
        fov, ho_rate = mcao
        speed = np.hypot(lay.velocities[:, 0], lay.velocities[:, 1])
        v_mean = float(np.sum(lay.weights * speed ** (5 / 3)) ** (3 / 5))
        h_mean = float(np.sum(lay.weights * lay.heights ** (5 / 3)) ** (3 / 5))
        meta = pupil.diameter / 2 + h_mean * np.tan(fov / 2 / ARCSEC_PER_RAD)
        s = s * mcao_rejection(f, meta, ho_rate, v_mean)
    w = f**3 * s * np.gradient(f)
    rho_max = max(float(lay.heights.max()) * max_separation * 1.05, 1e-3)
    rho = np.linspace(0.0, rho_max, 400)
    arg = 2 * np.pi * rho[:, None] * f[None, :]
    # J2 by the recurrence 2 J1(x) / x - J0(x) (equal to scipy's jv(2, x) to 1e-14
    # absolute here; jv of integer order 2 costs ~10x more: ~0.25 s per process)
    j0a = j0(arg)
    j2 = np.where(arg > 0, 2.0 * j1(arg) / np.where(arg > 0, arg, 1.0) - j0a, 0.0)
    a = np.pi * ((j0a + j2) @ w)
    b = 2 * np.pi * (j2 @ w)
    return TiltCovariance(rho, a, b, lay.heights, lay.weights)


#: Version of the tilt-covariance table computation (part of its disk-cache key).
TILT_CACHE_VERSION = 2


def cached_tilt_covariance(
    atmosphere: AtmosphereSettings,
    pupil: PupilSettings,
    max_separation: float,
    mcao: tuple[float, float] | None = None,
    cache_dir=None,
    tilt: str = "G",
) -> TiltCovariance:
    """:func:`tilt_covariance_function`, kept in ``cache_dir`` (when given).

    The table is a pure function of its arguments (the cache key); loading it spares a
    frames process the Bessel functions and the ``scipy.special`` import (~0.3-0.5 s).

    Parameters
    ----------
    atmosphere, pupil, max_separation, mcao, tilt
        As :func:`tilt_covariance_function`.
    cache_dir : path, optional
        Folder of the cache file ``tiltcov-<key>.npz``; None: computed.

    Returns
    -------
    TiltCovariance
    """
    if cache_dir is None:
        return tilt_covariance_function(atmosphere, pupil, max_separation, mcao, tilt)
    import dataclasses
    from pathlib import Path

    from mavispm.core.array_cache import content_key, load_arrays, save_arrays

    key = content_key(
        TILT_CACHE_VERSION,
        dataclasses.asdict(atmosphere),
        dataclasses.asdict(pupil),
        float(max_separation),
        None if mcao is None else [float(v) for v in mcao],
        tilt,
    )
    path = Path(cache_dir) / f"tiltcov-{key}.npz"
    names = [f.name for f in dataclasses.fields(TiltCovariance)]
    stored = load_arrays(path)
    if stored is not None and set(stored) == set(names):
        return TiltCovariance(**{n: np.array(stored[n]) for n in names})
    table = tilt_covariance_function(atmosphere, pupil, max_separation, mcao, tilt)
    save_arrays(path, {n: np.asarray(getattr(table, n)) for n in names})
    return table


class TipTiltField:
    """Field-dependent TT residual covariance for one asterism.

    Parameters
    ----------
    settings : TipTiltSettings
    atmosphere : AtmosphereSettings
    pupil : PupilSettings
    cache_dir : path, optional
        Keep the tilt-covariance table there (:func:`cached_tilt_covariance`).
    """

    def __init__(
        self,
        settings: TipTiltSettings,
        atmosphere: AtmosphereSettings,
        pupil: PupilSettings,
        cache_dir=None,
    ):
        self.settings = settings
        self.ngs_xy, self.ngs_mag = ngs_positions(settings)
        if not settings.enabled:
            return
        theta = self.ngs_xy * 1000 / MAS_PER_RAD  # rad
        reach = np.hypot(*theta.T).max() if theta.size else 0.0
        # tabulate to a generous, rounded separation so asterisms share the table
        needed = 2 * reach + 60.0 / 206265.0
        step = 100.0 / 206265.0
        mcao = (settings.technical_fov, settings.ho_frame_rate) if settings.mcao_filter else None
        self._cov = cached_tilt_covariance(
            atmosphere, pupil, step * np.ceil(needed / step), mcao, cache_dir, settings.tilt
        )
        n = theta.shape[0]
        self._theta = theta
        css = np.zeros((2 * n, 2 * n))
        for i in range(n):
            for j in range(n):
                css[2 * i : 2 * i + 2, 2 * j : 2 * j + 2] = self._cov(theta[i] - theta[j])
        noise = ngs_noise_variance(settings, self.ngs_mag) / MAS_PER_RAD**2
        css += np.diag(np.repeat(noise, 2))
        css += np.eye(2 * n) * 1e-12 * np.trace(css) / (2 * n)
        self._css_inv = np.linalg.inv(css)
        self._c0 = self._cov(np.zeros(2))

    def covariance(self, x, y) -> np.ndarray:
        """TT residual covariance (N, 2, 2) in mas^2 at field positions (arcsec).

        Symmetric positive semi-definite; zeros when disabled.

        Parameters
        ----------
        x, y : array_like
            Field positions [arcsec], 1-D, equal length, finite.

        Returns
        -------
        ndarray, shape (N, 2, 2)
            Covariance [mas^2].

        Raises
        ------
        ValueError
            For positions of different shapes or non-finite positions.
        """
        x = np.atleast_1d(np.asarray(x, float))
        y = np.atleast_1d(np.asarray(y, float))
        if x.shape != y.shape or x.ndim != 1:
            raise ValueError("x and y must be 1-D arrays of equal length (arcsec)")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise ValueError("field positions must be finite")
        if not self.settings.enabled:
            return np.zeros((x.size, 2, 2))
        alpha = np.stack([x, y], -1) * 1000 / MAS_PER_RAD
        delta = alpha[:, None, :] - self._theta[None, :, :]  # (N, n, 2)
        blocks = self._cov(delta)  # (N, n, 2, 2): cov(alpha tilt, ngs tilt)
        cas = np.concatenate(list(np.moveaxis(blocks, 1, 0)), axis=-1)  # (N, 2, 2n)
        res = self._c0[None] - np.matmul(cas @ self._css_inv, np.swapaxes(cas, 1, 2))
        res = 0.5 * (res + np.swapaxes(res, 1, 2)) * MAS_PER_RAD**2
        res += np.eye(2) * self.settings.windshake**2
        # clip tiny negative eigenvalues from round-off; blocks whose smaller eigenvalue
        # (closed form) is clearly positive are already positive semi-definite
        half_tr = 0.5 * (res[:, 0, 0] + res[:, 1, 1])
        disc = np.hypot(0.5 * (res[:, 0, 0] - res[:, 1, 1]), res[:, 0, 1])
        suspect = half_tr - disc <= 1e-9 * np.maximum(half_tr, 0.0)
        if np.any(suspect):
            vals, vecs = np.linalg.eigh(res[suspect])
            vals = np.clip(vals, 0.0, None)
            res[suspect] = np.einsum("nij,nj,nkj->nik", vecs, vals, vecs)
        return res * self.settings.scale_factor**2


def atmospheric_cross_covariance(field: TipTiltField, xy1, xy2) -> np.ndarray:
    """Covariance of the atmospheric TT residuals at two sets of field positions.

    ``cov(r(a), r(b)) = K(a - b) - K(a, NGS) C_ss^-1 K(NGS, b)`` in mas^2, shape
    (N, M, 2, 2), for positions ``xy1`` (N, 2) and ``xy2`` (M, 2) in arcsec. The
    diagonal ``a = b`` is :meth:`TipTiltField.covariance` without windshake and
    scale factor (the NGS noise enters through ``C_ss``). Zeros when disabled.

    Parameters
    ----------
    field : TipTiltField
        The tip-tilt model.
    xy1 : array_like, shape (N, 2)
        First positions [arcsec].
    xy2 : array_like, shape (M, 2)
        Second positions [arcsec].

    Returns
    -------
    ndarray, shape (N, M, 2, 2)
        Cross-covariance [mas^2].
    """
    xy1 = np.atleast_2d(np.asarray(xy1, float))
    xy2 = np.atleast_2d(np.asarray(xy2, float))
    if not field.settings.enabled:
        return np.zeros((xy1.shape[0], xy2.shape[0], 2, 2))
    a = xy1 * 1000 / MAS_PER_RAD
    b = xy2 * 1000 / MAS_PER_RAD
    kab = field._cov(a[:, None, :] - b[None, :, :])  # (N, M, 2, 2)
    ka = np.concatenate(list(np.moveaxis(field._cov(a[:, None, :] - field._theta[None]), 1, 0)), -1)
    kb = np.concatenate(list(np.moveaxis(field._cov(b[:, None, :] - field._theta[None]), 1, 0)), -1)
    # ka: (N, 2, 2n), kb: (M, 2, 2n)
    proj = np.einsum("nij,jk,mlk->nmil", ka, field._css_inv, kb)
    return (kab - proj) * MAS_PER_RAD**2


def field_average_sigma(field: TipTiltField, half_width: float = 15.0, n: int = 11) -> float:
    """Mean semi-major sigma (mas) over an n x n grid of the field (the paper's sigma_TT_ave).

    Parameters
    ----------
    field : TipTiltField
        The tip-tilt model.
    half_width : float
        Half-width of the grid [arcsec].
    n : int
        Grid points per side.

    Returns
    -------
    float
        Mean semi-major 1-sigma axis [mas].
    """
    g = np.linspace(-half_width, half_width, n)
    gx, gy = np.meshgrid(g, g)
    cov = field.covariance(gx.ravel(), gy.ravel())
    return float(np.mean(np.sqrt(np.linalg.eigvalsh(cov)[:, -1])))


@dataclass(frozen=True)
class KernelMap:
    """TT kernel shapes at field positions.

    Parameters
    ----------
    sigma_major, sigma_minor : ndarray
        1-sigma semi-axes of the Gaussian kernel (mas), major >= minor >= 0.
    angle : ndarray
        Position angle of the major axis (deg, from +x towards +y, in [0, 180)).
    """

    sigma_major: np.ndarray
    sigma_minor: np.ndarray
    angle: np.ndarray


def kernel_map(field: TipTiltField, x, y) -> KernelMap:
    """Semi-axes (mas) and major-axis angle (deg) of the TT kernels at positions (arcsec).

    ``x`` and ``y`` may have any equal shape; the outputs have that shape.

    Parameters
    ----------
    field : TipTiltField
        The tip-tilt model.
    x, y : array_like
        Field positions [arcsec].

    Returns
    -------
    KernelMap
        Semi-axes [mas] and major-axis angle [deg] at each position.

    Raises
    ------
    ValueError
        When ``x`` and ``y`` differ in shape.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if x.shape != y.shape:
        raise ValueError("x and y must have the same shape (arcsec)")
    cov = field.covariance(x.ravel(), y.ravel())
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    angle = np.degrees(np.arctan2(vecs[:, 1, 1], vecs[:, 0, 1])) % 180.0
    angle = np.where(np.isclose(angle, 180.0), 0.0, angle)
    return KernelMap(
        np.sqrt(vals[:, 1]).reshape(x.shape),
        np.sqrt(vals[:, 0]).reshape(x.shape),
        angle.reshape(x.shape),
    )
