"""Residual-phase power spectral density of the MAVIS MCAO correction.

Fourier-domain model (Rigaut et al. 1998; Jolissaint 2010; Neichel et al.
2008): the residual phase spectrum is the sum of

* fitting error: the full turbulence spectrum outside the DM control region
  ``|fx|, |fy| < fc = n_act / (2 D)``;
* WFS aliasing: high frequencies folded into the control region by the
  Shack-Hartmann sampling (pitch d = D / n_act);
* WFS noise: white slope noise propagated through the reconstructor, the
  tomography and the closed loop;
* servo lag and LGS tomography, jointly: per spatial frequency an MMSE
  tomographic reconstruction from the LGS directions, projected on the DMs
  optimised over a set of fitting directions, with each layer's correction
  filtered by the closed-loop transfer function at its temporal frequency
  ``f . v``. The error for a science direction alpha is
  ``e_l = B_l(alpha) - h_l (A(alpha) P W M)_l``;
* the LGS cone effect: see ``simulate.optics.cone_effect`` (added per
  direction by ``psf_grid``).

Frequencies in m^-1, PSDs in rad^2 m^2 at the science wavelength.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mavispm.core.config import unit_field
from mavispm.simulate.optics.atmosphere import ARCSEC_PER_RAD, Layers, von_karman_psd

__all__ = [
    "AOSettings",
    "MAVIS_FITTING_RINGS",
    "TomographicOperator",
    "aliasing_psd",
    "aliasing_temporal_gain",
    "closed_loop_transfer",
    "control_mask",
    "correction_residual_psd",
    "fitting_directions",
    "fitting_psd",
    "fitting_weights",
    "lgs_directions",
    "noise_gain",
    "noise_psd",
    "shack_hartmann_noise",
    "tomographic_operator",
]

#: DM optimisation directions and weights of TIPTOP's MAVIS.ini ([DM] OptimizationZenith /
#: Azimuth / Weight): the centre, and rings of 8 at 5", 15", 37.5" and 60".
MAVIS_FITTING_RINGS = ((0.0, 1), (5.0, 8), (15.0, 8), (37.5, 8), (60.0, 8))
MAVIS_FITTING_WEIGHTS = (1.0, 2.0, 30.0, 0.25, 0.25)


@dataclass(frozen=True)
class AOSettings:
    """The MCAO system and which residual terms to include (``[scene.optics.ao]``).

    Parameters
    ----------
    n_actuators : int
        Actuators (and WFS sub-apertures) across the pupil diameter.
    dm_heights : tuple of float
        Conjugation altitudes of the deformable mirrors (m).
    dm_pitches : tuple of float
        Actuator pitch of each DM projected on the pupil (m); a DM corrects
        only ``|fx|, |fy| < 1 / (2 pitch)``. The WFS sampling and the overall
        control region follow ``n_actuators``.
    n_lgs : int
        Number of laser guide stars, evenly spaced on a circle.
    lgs_radius : float
        Radius of the LGS constellation (arcsec).
    lgs_height : float
        Sodium-layer altitude above the telescope at zenith (m); the range along
        the line of sight is ``lgs_height sec(z)``.
    lgs_angle : float
        Position angle of the first LGS (deg, from +x towards +y).
    lgs_slope_noise : float or None
        RMS noise on one sub-aperture's wavefront difference (nm of OPD per
        frame); None computes it from the LGS photometry below with
        :func:`shack_hartmann_noise`.
    lgs_photons : float
        Detected photons per sub-aperture per frame.
    lgs_read_noise : float
        Read-out noise (e- RMS per pixel).
    lgs_excess_noise : float
        Excess-noise factor of the detector.
    lgs_pixel_scale : float
        WFS pixel (mas).
    lgs_pixels : int
        Pixels across one sub-aperture's field (centre of gravity window).
    lgs_spot_fwhm : float
        Intrinsic LGS spot FWHM without turbulence (mas).
    lgs_wavelength : float
        LGS wavelength (nm).
    loop_frequency : float
        HO loop rate (Hz).
    loop_gain : float
        Integrator gain.
    loop_delay : float
        Pure loop delay (frames), WFS read-out plus computation.
    fitting_field : float
        Diameter of the circular field the DM correction is optimised over (arcsec).
    n_fitting : int
        Fitting directions per side of the square grid sampling that circle.
    fitting_weights : tuple of float
        Optional weights of rings of fitting directions (see ``fitting_rings``);
        empty for the uniform square grid of ``n_fitting`` per side.
    fitting_rings : tuple of (float, int)
        Optional rings of fitting directions: (radius arcsec, number of
        directions); a radius 0 ring has one direction. Empty for the square grid.
    control_region : {"circle", "square"}
        Shape of the corrected spatial frequencies: ``|f| < fc`` or ``|fx|, |fy| < fc``.
    layer_stretch : {"none", "lgs", "all"}
        Cone stretch ``1 / (1 - h / H)`` of the layer distances in the tomography.
        "none" (default): the LGS phasors use the footprint centres ``h theta_g``
        and the footprint compression is the cone-effect term; "lgs": the LGS
        phasors use ``h / (1 - h/H)`` (the footprint-centre shift in pupil
        coordinates); "all": every layer phasor, DM projector and science
        directions included, as P3 / TIPTOP do (``strechFactor``): a peer-code
        convention for cross-checks, not physics for a science star at infinity
        (with "all" the cone-effect term also sees the stretched distances).
    servo_model : {"integrator", "pure_delay"}
        Temporal filter of the tomographic correction: the closed-loop
        integrator (default) or P3 / TIPTOP's tomographic pure delay of
        ``loop_delay / loop_frequency`` (a peer-code convention).
    fitting, aliasing, noise, servo_lag, tomography, cone_effect : bool
        Switches of the residual terms. With ``tomography`` off the correction
        is perfect in every direction apart from the other terms (and the cone
        effect is not modelled).
    cone_remove_tilt : bool
        Leave the pupil piston and tilt of the cone-effect residual out of the
        high-order PSD (default): the LGS do not sense tilt, the NGS tip-tilt
        model handles it. False keeps them (the former model, a cross-check).
    cone_model : {"kriging", "gap"}
        Multi-LGS cone effect: "kriging" (default), each layer's power is the MMSE
        extrapolation error of the layer beyond the LGS footprints
        (``cone_effect.extrapolation_variance``); "gap", the former footprint-gap and
        area heuristic (2-8x larger, a cross-check).
    """

    n_actuators: int = 40
    dm_heights: tuple[float, ...] = field(default=(0.0, 6000.0, 13500.0))
    dm_pitches: tuple[float, ...] = field(default=(0.21, 0.25, 0.32))
    n_lgs: int = 8
    lgs_radius: float = unit_field(17.5, "arcsec", "LGS constellation radius")
    lgs_height: float = unit_field(90000.0, "m", "sodium layer altitude")
    lgs_angle: float = unit_field(22.5, "deg", "position angle of the first LGS")
    lgs_slope_noise: float | None = unit_field(
        None, "nm", "sub-aperture wavefront-difference noise"
    )
    lgs_photons: float = 75.0
    lgs_read_noise: float = 0.2
    lgs_excess_noise: float = 2.0
    lgs_pixel_scale: float = unit_field(833.0, "mas", "LGS WFS pixel")
    lgs_pixels: int = 6
    lgs_spot_fwhm: float = unit_field(0.0, "mas", "intrinsic LGS spot FWHM")
    lgs_wavelength: float = unit_field(589.0, "nm", "LGS wavelength")
    loop_frequency: float = unit_field(1000.0, "Hz", "HO loop rate")
    loop_gain: float = 0.3
    loop_delay: float = 2.0
    fitting_field: float = unit_field(30.0, "arcsec", "DM optimisation field width")
    n_fitting: int = 5
    fitting_rings: tuple[tuple[float, int], ...] = field(default=MAVIS_FITTING_RINGS)
    fitting_weights: tuple[float, ...] = field(default=MAVIS_FITTING_WEIGHTS)
    fitting: bool = True
    aliasing: bool = True
    noise: bool = True
    servo_lag: bool = True
    tomography: bool = True
    cone_effect: bool = True
    cone_remove_tilt: bool = True
    cone_model: Literal["kriging", "gap"] = "kriging"
    control_region: Literal["square", "circle"] = "circle"
    layer_stretch: Literal["none", "lgs", "all"] = "none"
    servo_model: Literal["integrator", "pure_delay"] = "integrator"

    def __post_init__(self):
        if self.n_actuators < 2:
            raise ValueError(f"n_actuators must be >= 2, got {self.n_actuators}")
        if len(self.dm_heights) < 1 or any(h < 0 for h in self.dm_heights):
            raise ValueError("dm_heights must list >= 1 altitude >= 0 m")
        if len(self.dm_pitches) != len(self.dm_heights) or any(p <= 0 for p in self.dm_pitches):
            raise ValueError("dm_pitches must give one pitch > 0 m per DM height")
        if any(h >= self.lgs_height for h in self.dm_heights):
            raise ValueError("every DM must be conjugated below the LGS altitude")
        if self.n_lgs < 1:
            raise ValueError(f"n_lgs must be >= 1, got {self.n_lgs}")
        if not 0 < self.loop_gain < 1.5:
            raise ValueError(f"loop_gain must be in (0, 1.5), got {self.loop_gain}")
        if self.loop_delay < 0 or self.loop_frequency <= 0:
            raise ValueError("loop_delay must be >= 0 frames and loop_frequency > 0 Hz")
        if self.lgs_slope_noise is not None and self.lgs_slope_noise < 0:
            raise ValueError("lgs_slope_noise must be >= 0 nm")
        if not self.lgs_photons > 0 or self.lgs_read_noise < 0 or self.lgs_excess_noise < 1:
            raise ValueError("lgs_photons must be > 0, lgs_read_noise >= 0, lgs_excess_noise >= 1")
        if not self.lgs_pixel_scale > 0 or self.lgs_pixels < 1 or self.lgs_spot_fwhm < 0:
            raise ValueError("lgs_pixel_scale must be > 0 mas, lgs_pixels >= 1, lgs_spot_fwhm >= 0")
        if self.control_region not in ("square", "circle"):
            raise ValueError(
                f"control_region must be 'square' or 'circle', got {self.control_region!r}"
            )
        if self.n_fitting < 1:
            raise ValueError("n_fitting must be >= 1")
        if self.layer_stretch not in ("none", "lgs", "all"):
            raise ValueError(
                f"layer_stretch must be 'none', 'lgs' or 'all', got {self.layer_stretch!r}"
            )
        if self.servo_model not in ("integrator", "pure_delay"):
            raise ValueError(
                f"servo_model must be 'integrator' or 'pure_delay', got {self.servo_model!r}"
            )
        if self.fitting_weights and len(self.fitting_weights) != len(self.fitting_rings):
            raise ValueError("fitting_weights needs one weight per fitting_rings entry")
        if any(w < 0 for w in self.fitting_weights) or (
            self.fitting_weights and not sum(self.fitting_weights) > 0
        ):
            raise ValueError("fitting_weights must be >= 0 with a positive sum")
        for ring in self.fitting_rings:
            if len(ring) != 2 or ring[0] < 0 or int(ring[1]) < 1:
                raise ValueError("fitting_rings entries must be [radius >= 0 arcsec, count >= 1]")

    def pitch(self, diameter: float) -> float:
        """Actuator / sub-aperture pitch d = D / n_act (m).

        Parameters
        ----------
        diameter : float
            Telescope diameter D [m].

        Returns
        -------
        float
            Pitch [m].
        """
        return diameter / self.n_actuators

    def control_frequency(self, diameter: float) -> float:
        """Cut-off spatial frequency fc = 1 / (2 d) (m^-1).

        Parameters
        ----------
        diameter : float
            Telescope diameter D [m].

        Returns
        -------
        float
            fc [1/m].
        """
        return 1.0 / (2.0 * self.pitch(diameter))


def shack_hartmann_noise(settings: AOSettings, pitch: float, r0_wfs: float) -> float:
    """RMS wavefront-difference noise of one LGS sub-aperture (nm) from its photometry.

    Centre-of-gravity noise of Thomas et al. (2006, MNRAS 371, 323), the
    phase-difference variance across a sub-aperture at the WFS wavelength:
    ``sigma^2 = F [pi^2 / (2 ln2 N_ph) (N_T / N_D)^2 + pi^2 / 3 (RON / N_ph)^2 (N_s^2 / N_D)^2]``
    (the ``2 ln 2`` of the Gaussian-spot photon term, as in P3's ``sensor.NoiseVariance``)
    with ``N_D = max(1, lambda / d / pixel)`` (diffraction spot FWHM in pixels),
    ``N_T = max(1, hypot(spot, lambda / r0) / pixel)`` (turbulent spot FWHM),
    ``N_s`` the pixels across the window and F the excess-noise factor.

    Parameters
    ----------
    settings : AOSettings
        LGS photometry and WFS: ``lgs_photons``, ``lgs_read_noise`` [electron],
        ``lgs_excess_noise``, ``lgs_pixel_scale`` [mas], ``lgs_pixels``, ``lgs_spot_fwhm``
        [mas], ``lgs_wavelength`` [nm], or ``lgs_slope_noise`` [nm] when set.
    pitch : float
        Sub-aperture size d (m).
    r0_wfs : float
        Fried parameter at the LGS wavelength along the line of sight (m).

    Returns
    -------
    float
        RMS wavefront-difference noise per frame [nm].
    """
    s = settings
    if s.lgs_slope_noise is not None:
        return float(s.lgs_slope_noise)
    lam = s.lgs_wavelength * 1e-9
    pix = s.lgs_pixel_scale / 1000.0  # arcsec
    n_d = max(1.0, lam / pitch * ARCSEC_PER_RAD / pix)
    n_t = max(1.0, np.hypot(s.lgs_spot_fwhm / 1000.0, lam / r0_wfs * ARCSEC_PER_RAD) / pix)
    shot = np.pi**2 / (2 * np.log(2) * s.lgs_photons) * (n_t / n_d) ** 2
    ron = np.pi**2 / 3 * (s.lgs_read_noise / s.lgs_photons) ** 2 * (s.lgs_pixels**2 / n_d) ** 2
    var = s.lgs_excess_noise * (shot + ron)  # rad^2 at the LGS wavelength
    return float(np.sqrt(var) * lam / (2 * np.pi) * 1e9)


def lgs_directions(settings: AOSettings) -> np.ndarray:
    """LGS directions (rad), shape (n_lgs, 2), evenly spaced on the circle.

    Parameters
    ----------
    settings : AOSettings
        ``n_lgs``, ``lgs_radius`` [arcsec] and ``lgs_angle`` [deg].

    Returns
    -------
    ndarray, shape (n_lgs, 2)
        Directions [rad].
    """
    ang = 2 * np.pi * np.arange(settings.n_lgs) / settings.n_lgs + np.radians(settings.lgs_angle)
    r = settings.lgs_radius / ARCSEC_PER_RAD
    return np.stack([r * np.cos(ang), r * np.sin(ang)], axis=-1)


def fitting_directions(settings: AOSettings) -> np.ndarray:
    """DM optimisation directions (rad), shape (K, 2).

    Rings from ``fitting_rings`` when given, else a square grid cut to the circle.

    Parameters
    ----------
    settings : AOSettings
        ``fitting_rings`` (radius [arcsec], count), or ``fitting_field`` [arcsec] and
        ``n_fitting``.

    Returns
    -------
    ndarray, shape (K, 2)
        Directions [rad].
    """
    if settings.fitting_rings:
        out = []
        for radius, count in settings.fitting_rings:
            count = 1 if radius == 0 else int(count)
            ang = 2 * np.pi * np.arange(count) / count
            out.append(np.stack([radius * np.cos(ang), radius * np.sin(ang)], -1))
        return np.concatenate(out) / ARCSEC_PER_RAD
    half = settings.fitting_field / 2 / ARCSEC_PER_RAD
    g = np.linspace(-half, half, settings.n_fitting) if settings.n_fitting > 1 else np.zeros(1)
    gx, gy = np.meshgrid(g, g)
    keep = np.hypot(gx, gy) <= half * (1 + 1e-9)  # the circular science field
    return np.stack([gx[keep], gy[keep]], axis=-1)


def fitting_weights(settings: AOSettings) -> np.ndarray:
    """Weight of each fitting direction (sum 1), aligned with :func:`fitting_directions`.

    Parameters
    ----------
    settings : AOSettings
        ``fitting_rings`` and their ``fitting_weights`` (per ring; equal when absent).

    Returns
    -------
    ndarray, shape (K,)
        Weights (equal for the square grid).
    """
    if not settings.fitting_rings:
        n = fitting_directions(settings).shape[0]
        return np.full(n, 1.0 / n)
    per_ring = settings.fitting_weights or (1.0,) * len(settings.fitting_rings)
    w = np.concatenate(
        [
            np.full(1 if r == 0 else int(c), float(wt))
            for (r, c), wt in zip(settings.fitting_rings, per_ring)
        ]
    )
    return w / w.sum()


def control_mask(fx: np.ndarray, fy: np.ndarray, fc: float, shape: str = "square") -> np.ndarray:
    """True inside the DM control region: ``|fx|, |fy| < fc`` ("square") or ``|f| < fc`` ("circle").

    Parameters
    ----------
    fx, fy : ndarray
        Spatial frequencies [1/m].
    fc : float
        Cut-off frequency [1/m].
    shape : {"square", "circle"}
        Shape of the region.

    Returns
    -------
    ndarray of bool
        The mask.
    """
    if shape == "circle":
        return fx**2 + fy**2 < fc**2
    return (np.abs(fx) < fc) & (np.abs(fy) < fc)


def fitting_psd(
    fx, fy, fc: float, r0: float, outer_scale: float, shape: str = "square"
) -> np.ndarray:
    """Fitting-error PSD: the turbulence spectrum outside the control region.

    Parameters
    ----------
    fx, fy : ndarray
        Spatial frequencies [1/m].
    fc : float
        Cut-off frequency [1/m].
    r0 : float
        Fried parameter at the science wavelength [m].
    outer_scale : float
        Outer scale L0 [m].
    shape : {"square", "circle"}
        Shape of the control region.

    Returns
    -------
    ndarray
        Phase PSD [rad^2 m^2]; 0 inside the control region.
    """
    w = von_karman_psd(fx**2 + fy**2, r0, outer_scale)
    return np.where(control_mask(fx, fy, fc, shape), 0.0, w)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den with 1 where both vanish (the limit used for the m = 0 terms)."""
    out = np.ones_like(num)
    ok = den != 0
    out[ok] = num[ok] / den[ok]
    return out


def aliasing_psd(
    fx,
    fy,
    pitch: float,
    r0: float,
    outer_scale: float,
    n_fold: int = 2,
    temporal=None,
) -> np.ndarray:
    """Shack-Hartmann aliasing PSD inside the control region.

    A least-squares reconstructor from sub-aperture-averaged slopes folds the
    turbulence at ``f' = f - (m, n) / d`` into ``f`` with transfer
    ``(fx^2 fy / f'y + fy^2 fx / f'x) / |f|^2`` (Rigaut et al. 1998).

    Parameters
    ----------
    fx, fy : ndarray
        Spatial frequencies inside the control region (m^-1).
    pitch : float
        Sub-aperture size d (m).
    r0 : float
        Fried parameter at the science wavelength (m).
    outer_scale : float
        Outer scale L0 (m).
    n_fold : int
        Folded orders summed in each direction (|m|, |n| <= n_fold).
    temporal : callable, optional
        ``temporal(fpx, fpy)`` -> power gain (same shape) with which the aliased
        turbulence at ``f'`` reaches the DMs (the closed-loop |H|^2 at each layer's
        temporal frequency ``f' . v``, Cn^2-weighted); 1 when None.
    """
    f2 = fx**2 + fy**2
    safe = np.where(f2 > 0, f2, 1.0)
    out = np.zeros_like(fx, dtype=float)
    for m in range(-n_fold, n_fold + 1):
        for n in range(-n_fold, n_fold + 1):
            if m == 0 and n == 0:
                continue
            fpx = fx - m / pitch
            fpy = fy - n / pitch
            rx = _ratio(np.asarray(fx, float), fpx) if m else np.ones_like(fx, float)
            ry = _ratio(np.asarray(fy, float), fpy) if n else np.ones_like(fy, float)
            transfer = (fx**2 * ry + fy**2 * rx) / safe
            gain = 1.0 if temporal is None else temporal(fpx, fpy)
            out += von_karman_psd(fpx**2 + fpy**2, r0, outer_scale) * transfer**2 * gain
    return np.where(f2 > 0, out, 0.0)


def noise_psd(fx, fy, pitch: float, sigma_rad: float) -> np.ndarray:
    """Single-WFS noise PSD (rad^2 m^2) of a least-squares SH reconstruction.

    ``sigma_rad`` is the RMS noise of one sub-aperture's phase difference (rad
    at the science wavelength); the white slope noise has density
    ``sigma^2 d^2`` and is divided by ``|Gx|^2 + |Gy|^2`` with
    ``Gx = 2 i sin(pi d fx) sinc(d fy)``.

    Parameters
    ----------
    fx, fy : ndarray
        Spatial frequencies [1/m].
    pitch : float
        Sub-aperture pitch d [m].
    sigma_rad : float
        RMS phase-difference noise of one sub-aperture [rad].

    Returns
    -------
    ndarray
        Noise PSD [rad^2 m^2].
    """
    gx2 = (2 * np.sin(np.pi * pitch * fx) * np.sinc(pitch * fy)) ** 2
    gy2 = (2 * np.sin(np.pi * pitch * fy) * np.sinc(pitch * fx)) ** 2
    g2 = gx2 + gy2
    return np.where(g2 > 0, sigma_rad**2 * pitch**2 / np.where(g2 > 0, g2, 1.0), 0.0)


def closed_loop_transfer(nu: np.ndarray, settings: AOSettings) -> np.ndarray:
    """Closed-loop transfer H = OL / (1 + OL) of the integrator at temporal frequency ``nu`` (Hz).

    ``OL(z) = g z^-delay / (1 - z^-1)``, ``z = exp(2 pi i nu / f_loop)``.
    H -> 1 at nu -> 0 (perfect tracking of slow turbulence).

    Parameters
    ----------
    nu : ndarray
        Temporal frequencies [Hz].
    settings : AOSettings
        ``loop_gain``, ``loop_delay`` [frames] and ``loop_frequency`` [Hz].

    Returns
    -------
    ndarray, complex
        H(nu).
    """
    nu = np.asarray(nu, float)
    zinv = np.exp(-2j * np.pi * nu / settings.loop_frequency)
    num = settings.loop_gain * zinv**settings.loop_delay
    den = 1.0 - zinv
    small = np.abs(den) < 1e-12
    h = np.where(small, 1.0 + 0j, num / np.where(small, 1.0, den + num))
    return h


def aliasing_temporal_gain(settings: AOSettings, atmosphere: Layers):
    """``g(fx, fy) = sum_l c_l |H(f . v_l)|^2``: closed-loop power gain of frozen-flow layers.

    Aliased turbulence at ``f`` moves with each layer's wind and reaches the DMs
    through the loop like the turbulence itself (not like white noise).

    Parameters
    ----------
    settings : AOSettings
        The loop (see :func:`closed_loop_transfer`).
    atmosphere : Layers
        Cn^2 fractions ``c_l`` and wind velocities ``v_l`` [m/s].

    Returns
    -------
    callable
        ``gain(fx, fy)`` of spatial frequencies [1/m], returning the dimensionless gain.
    """

    def gain(fx, fy):
        out = np.zeros(np.shape(fx))
        for w, (vx, vy) in zip(atmosphere.weights, atmosphere.velocities):
            out += w * np.abs(closed_loop_transfer(fx * vx + fy * vy, settings)) ** 2
        return out

    return gain


def noise_gain(settings: AOSettings, n: int = 4096) -> float:
    """Closed-loop noise gain: mean of |H|^2 over (0, f_loop/2) (white noise).

    Parameters
    ----------
    settings : AOSettings
        The loop.
    n : int
        Frequency samples (midpoints).

    Returns
    -------
    float
        The gain (dimensionless).
    """
    nu = (np.arange(n) + 0.5) / n * settings.loop_frequency / 2
    return float(np.mean(np.abs(closed_loop_transfer(nu, settings)) ** 2))


@dataclass
class TomographicOperator:
    """Per-frequency MCAO correction operators on the control-region frequencies.

    Parameters
    ----------
    fx, fy : ndarray, shape (F,)
        Frequencies (m^-1), zero frequency excluded.
    turbulence : ndarray, shape (F, L)
        Layer phase PSDs c_l W(f) (rad^2 m^2).
    correction : ndarray, shape (F, D, L)
        P W M: DM commands per unit layer phase.
    command_noise : ndarray, shape (F, D, G)
        P W: DM commands per unit WFS phase (noise propagation).
    noise : ndarray, shape (F,)
        Single-WFS noise PSD after the loop noise gain (rad^2 m^2); 0 if off.
    temporal : ndarray, shape (F, L), complex
        Closed-loop transfer h_l at nu = f . v_l (1 when servo lag is off).
    dm_heights, layer_heights : ndarray
    """

    fx: np.ndarray
    fy: np.ndarray
    turbulence: np.ndarray
    correction: np.ndarray
    command_noise: np.ndarray
    noise: np.ndarray
    temporal: np.ndarray
    dm_heights: np.ndarray
    layer_heights: np.ndarray
    dm_mask: np.ndarray | None = None


def _dm_mask(fx, fy, settings: AOSettings) -> np.ndarray:
    """(F, D) 1 where each DM can correct the frequency, else 0."""
    fc = 1.0 / (2.0 * np.asarray(settings.dm_pitches, float))
    return control_mask(fx[:, None], fy[:, None], fc[None, :], settings.control_region).astype(
        float
    )


def _phasor(fx, fy, heights, directions):
    """exp(2 pi i h f . theta): shape (F, K, H) for K directions and H heights."""
    proj = fx[:, None] * directions[None, :, 0] + fy[:, None] * directions[None, :, 1]
    return np.exp(2j * np.pi * proj[:, :, None] * heights[None, None, :])


def tomographic_operator(
    fx: np.ndarray,
    fy: np.ndarray,
    settings: AOSettings,
    atmosphere: Layers,
    r0: float,
    outer_scale: float,
    noise_psd_single: np.ndarray,
    lgs_range: float = np.inf,
) -> TomographicOperator:
    """Build the MMSE tomography + DM projection for the given frequencies.

    Parameters
    ----------
    fx, fy : ndarray, shape (F,)
        Control-region frequencies, none equal to (0, 0) (m^-1).
    settings : AOSettings
        DMs, LGS asterism, fitting directions and loop.
    atmosphere : Layers
        Turbulent layers (distances [m], Cn^2 fractions, winds [m/s]).
    r0 : float
        Fried parameter at the science wavelength (m).
    outer_scale : float
        Outer scale L0 (m).
    noise_psd_single : ndarray, shape (F,)
        Noise PSD of one WFS (rad^2 m^2) before the loop gain; zeros when noise is off.
    lgs_range : float
        LGS distance along the line of sight (m), for ``settings.layer_stretch``.
    """
    h_l = atmosphere.heights
    stretched = h_l / (1.0 - h_l / lgs_range) if np.isfinite(lgs_range) else h_l
    h_lgs = h_l if settings.layer_stretch == "none" else stretched
    if settings.layer_stretch == "all":
        h_l = stretched
    h_d = np.asarray(settings.dm_heights, float)
    w = von_karman_psd(fx**2 + fy**2, r0, outer_scale)
    turb = w[:, None] * atmosphere.weights[None, :]
    # temporal frequency of a frozen-flow layer: phi(x, t) = phi0(x - v t) has the
    # Fourier phase exp(-2 pi i f.v t) in the convention of the direction phasors
    # exp(+2 pi i h f.theta), so the DM command, which lags, sees nu = -f.v (the sign
    # sets on which side of the field anisoplanatism and lag add up: the science
    # direction displaced downwind, h theta = v delay, is the better one)
    nu = -(
        fx[:, None] * atmosphere.velocities[None, :, 0]
        + fy[:, None] * atmosphere.velocities[None, :, 1]
    )
    if not settings.servo_lag:
        temporal = np.ones_like(nu, complex)
    elif settings.servo_model == "pure_delay":
        temporal = np.exp(-2j * np.pi * nu * settings.loop_delay / settings.loop_frequency)
    else:
        temporal = closed_loop_transfer(nu, settings)
    ngain = noise_gain(settings)
    noise = noise_psd_single * ngain if settings.noise else np.zeros_like(fx)
    if not settings.tomography:
        noise = noise / settings.n_lgs  # the LGS average their independent noise
        empty = np.zeros((fx.size, 0, 0), complex)
        return TomographicOperator(fx, fy, turb, empty, empty, noise, temporal, h_d, h_l)
    # LGS measurement M: (F, G, L); MMSE reconstructor W = C M^H (M C M^H + Cn)^-1
    m = _phasor(fx, fy, h_lgs, lgs_directions(settings))
    n_g = m.shape[1]
    mc = m * turb[:, None, :]
    cmm = np.einsum("fgl,fkl->fgk", mc, m.conj())
    # regularise with the noise (or a tiny fraction of the signal when noise is off)
    reg = np.maximum(noise_psd_single, 1e-6 * turb.sum(axis=1))
    cmm += reg[:, None, None] * np.eye(n_g)[None]
    # W^H = solve(cmm, M C)  (cmm is Hermitian)
    wh = np.linalg.solve(cmm, mc)  # (F, G, L)
    recon = np.conj(np.swapaxes(wh, 1, 2))  # (F, L, G)
    # DM projection over fitting directions: P = (sum A^H A)^-1 sum A^H B
    fit = fitting_directions(settings)
    wfit = fitting_weights(settings)
    dm_mask = _dm_mask(fx, fy, settings)
    a = _phasor(fx, fy, h_d, fit) * dm_mask[:, None, :]  # (F, K, D)
    b = _phasor(fx, fy, h_l, fit)  # (F, K, L)
    aa = np.einsum("fkd,k,fke->fde", a.conj(), wfit, a)
    aa += 1e-3 * np.eye(h_d.size)[None]
    ab = np.einsum("fkd,k,fkl->fdl", a.conj(), wfit, b)
    proj = np.linalg.solve(aa, ab)  # (F, D, L)
    command_noise = np.einsum("fdl,flg->fdg", proj, recon)
    correction = np.einsum("fdg,fgl->fdl", command_noise, m)
    return TomographicOperator(
        fx, fy, turb, correction, command_noise, noise, temporal, h_d, h_l, dm_mask
    )


def correction_residual_psd(
    op: TomographicOperator, directions: np.ndarray, split: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Servo-lag + tomography + noise PSD for science directions.

    Parameters
    ----------
    op : TomographicOperator
    directions : ndarray, shape (K, 2)
        Science directions (rad).
    split : bool
        Return the (servo-lag + tomography, noise) parts separately.

    Returns
    -------
    ndarray, shape (K, F)
        Residual PSD (rad^2 m^2) on the operator's frequencies (or a pair).
    """
    out = np.empty((directions.shape[0], op.fx.size))
    out_noise = np.empty_like(out)
    for k, theta in enumerate(directions):
        proj = op.fx * theta[0] + op.fy * theta[1]
        b = np.exp(2j * np.pi * proj[:, None] * op.layer_heights[None, :])  # (F, L)
        if op.correction.shape[1] == 0:
            err = b * (1.0 - op.temporal)
            noise = op.noise
        else:
            a = np.exp(2j * np.pi * proj[:, None] * op.dm_heights[None, :]) * op.dm_mask
            applied = np.einsum("fd,fdl->fl", a, op.correction)
            err = b - op.temporal * applied
            gn = np.einsum("fd,fdg->fg", a, op.command_noise)
            noise = op.noise * np.sum(np.abs(gn) ** 2, axis=1)
        out[k] = np.sum(np.abs(err) ** 2 * op.turbulence, axis=1)
        out_noise[k] = noise
    if split:
        return out, out_noise
    return out + out_noise
