"""Long-exposure PSF from a residual-phase PSD: PSD -> structure function -> OTF -> PSF.

``PSF = FT{ OTF_tel x exp(-D_phi / 2) }`` (Roddier 1981). The PSD lives on a
periodic grid of ``n_psd`` points of pitch ``df = 1 / (n_psd dx)``; its FFT
gives the phase covariance and structure function on the pupil-separation
grid of pitch ``dx``, the same grid as the telescope OTF (pupil
autocorrelation). The product is embedded in an ``n_fft`` grid chosen so that
one PSF pixel is exactly ``pixel_scale`` (``lambda / (n_fft dx)``), and
transformed with a real FFT; the optical axis lands on the centre pixel of
the odd-sized stamp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavispm.simulate.optics.atmosphere import MAS_PER_RAD
from mavispm.simulate.optics.pupil import PupilSettings, pupil_mask

__all__ = [
    "FourierSampling",
    "fourier_sampling",
    "psf_from_otf",
    "strehl_ratio",
    "structure_function",
    "telescope_otf",
]


@dataclass(frozen=True)
class FourierSampling:
    """Sampling of one monochromatic Fourier PSF computation.

    Parameters
    ----------
    wavelength : float
        Science wavelength (m).
    pixel_scale : float
        PSF pixel (mas).
    dx : float
        Pupil-plane sampling (m).
    n_fft : int
        FFT size giving ``pixel_scale = lambda / (n_fft dx)``.
    n_psd : int
        PSD / OTF grid size (period ``n_psd dx`` >= 2 D).
    n_stamp : int
        Odd output stamp size (pixels).
    """

    wavelength: float
    pixel_scale: float
    dx: float
    n_fft: int
    n_psd: int
    n_stamp: int

    @property
    def df(self) -> float:
        """PSD frequency pitch (m^-1)."""
        return 1.0 / (self.n_psd * self.dx)

    @property
    def f_max(self) -> float:
        """Highest frequency on the PSD grid (m^-1)."""
        return 1.0 / (2.0 * self.dx)

    def frequencies(self) -> tuple[np.ndarray, np.ndarray]:
        """(fx, fy) on the centred PSD grid, zero frequency at ``n_psd // 2``."""
        f = (np.arange(self.n_psd) - self.n_psd // 2) * self.df
        return np.meshgrid(f, f)


def fourier_sampling(
    wavelength: float,
    pixel_scale_mas: float,
    diameter: float,
    pupil_sampling: int,
    psd_padding: float,
    stamp_size_mas: float,
) -> FourierSampling:
    """Choose grids for a PSF of exact pixel scale.

    Parameters
    ----------
    wavelength : float
        Wavelength (m).
    pixel_scale_mas : float
        Output PSF pixel (mas); must be <= lambda / (2 D) (Nyquist).
    diameter : float
        Pupil diameter D (m).
    pupil_sampling : int
        Nominal pupil-plane samples across D.
    psd_padding : float
        PSD grid period in units of D (>= 2 so the OTF does not wrap).
    stamp_size_mas : float
        Output stamp width (mas); rounded to an odd number of pixels.
    """
    p_rad = pixel_scale_mas / MAS_PER_RAD
    nyquist = wavelength / (2 * diameter)
    if p_rad > nyquist * (1 + 1e-9):
        raise ValueError(
            f"PSF pixel_scale {pixel_scale_mas} mas is coarser than Nyquist "
            f"{nyquist * MAS_PER_RAD:.3f} mas at {wavelength * 1e9:.0f} nm"
        )
    n_fft = max(int(round(wavelength / (p_rad * diameter / pupil_sampling))), 8)
    dx = wavelength / (n_fft * p_rad)
    n_psd = int(np.ceil(psd_padding * diameter / dx / 2)) * 2
    n_psd = min(max(n_psd, int(np.ceil(2 * diameter / dx)) + 4), max(n_fft, 16))
    n_stamp = int(round(stamp_size_mas / pixel_scale_mas)) // 2 * 2 + 1
    n_stamp = min(n_stamp, n_fft - 1 if n_fft % 2 == 0 else n_fft)
    return FourierSampling(wavelength, pixel_scale_mas, dx, n_fft, n_psd, n_stamp)


def telescope_otf(pupil: PupilSettings, sampling: FourierSampling) -> np.ndarray:
    """Telescope OTF (pupil autocorrelation) on the wrapped ``n_psd`` grid, 1 at r = 0.

    Parameters
    ----------
    pupil : PupilSettings
        Diameter [m], obscuration and spiders.
    sampling : FourierSampling
        Grid size ``n_psd`` and pupil sampling ``dx`` [m].

    Returns
    -------
    ndarray, shape (n_psd, n_psd)
        The OTF (dimensionless), zero separation at index 0.
    """
    import scipy.fft  # here, not at the top: a frames process reading a cached grid never needs it

    p = pupil_mask(pupil, sampling.n_psd, sampling.dx)
    spec = scipy.fft.rfft2(np.fft.ifftshift(p))
    otf = scipy.fft.irfft2(np.abs(spec) ** 2, s=p.shape)
    return otf / otf[0, 0]


def structure_function(psd: np.ndarray, df: float) -> np.ndarray:
    """Phase structure function D(r) (rad^2) on the wrapped separation grid.

    Parameters
    ----------
    psd : ndarray, shape (n, n)
        Centred PSD (zero frequency at ``n // 2``), rad^2 m^2, real and even.
    df : float
        Frequency pitch (m^-1).
    """
    cov = _covariance(psd, df)
    return 2.0 * (cov[0, 0] - cov)


def _covariance(psd: np.ndarray, df: float) -> np.ndarray:
    """Phase covariance C(r) = sum_f PSD(f) cos(2 pi f r) df^2 on the wrapped grid."""
    import scipy.fft

    return scipy.fft.fft2(np.fft.ifftshift(psd), workers=-1).real * df**2


def psf_from_otf(otf: np.ndarray, sampling: FourierSampling) -> np.ndarray:
    """Centred, odd-sized PSF stamp (sums to 1) from a wrapped, real, even OTF.

    The OTF (on the ``n_psd`` grid, zero separation at index 0) is embedded in
    an ``n_fft`` grid and transformed with a real FFT in float32; the stamp's
    centre pixel is the optical axis.

    Parameters
    ----------
    otf : ndarray, shape (n_psd, n_psd)
        The OTF (dimensionless).
    sampling : FourierSampling
        ``n_fft`` and the output stamp size ``n_stamp``.

    Returns
    -------
    ndarray, shape (n_stamp, n_stamp)
        The PSF (sums to 1).
    """
    import scipy.fft

    n_psd, n_fft, n_out = otf.shape[0], sampling.n_fft, sampling.n_stamp
    h = (n_out - 1) // 2
    centred = np.fft.fftshift(otf)
    big = np.zeros((n_fft, n_fft), np.float32)
    half = min(n_psd, n_fft) // 2 - 1
    src = centred[
        n_psd // 2 - half : n_psd // 2 + half + 1, n_psd // 2 - half : n_psd // 2 + half + 1
    ]
    c = n_fft // 2
    big[c - half : c + half + 1, c - half : c + half + 1] = src
    spec = scipy.fft.rfft2(np.fft.ifftshift(big), workers=-1)
    rows = np.arange(-h, h + 1)
    right = spec[rows % n_fft][:, : h + 1].real
    left = spec[(-rows) % n_fft][:, h:0:-1].real
    psf = np.hstack([left, right]).astype(np.float64)
    psf = np.clip(psf, 0.0, None)
    total = psf.sum()
    if not np.isfinite(total) or total <= 0:
        raise FloatingPointError("PSF has no positive flux (check the PSD)")
    return psf / total


def strehl_ratio(otf_tel: np.ndarray, otf_ao: np.ndarray) -> float:
    """Strehl ratio = sum(OTF_tel OTF_AO) / sum(OTF_tel) (peak of the long-exposure PSF).

    Parameters
    ----------
    otf_tel : ndarray
        Telescope OTF.
    otf_ao : ndarray
        AO-residual OTF on the same grid.

    Returns
    -------
    float
        Strehl ratio (dimensionless).
    """
    return float(np.sum(otf_tel * otf_ao) / np.sum(otf_tel))
