"""Test doubles for the optics contract and an independent brute-force renderer.

The doubles implement the protocol the renderer consumes from
``mavispm.simulate.optics.model`` (``psf_grid``, ``halo``, ``tiptilt``, ``blur_sigma``,
``kernel_covariance``, ``distortion``) with analytic PSFs, so tests can compare
against closed forms and a direct real-space evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import astropy.units as u
import numpy as np
import scipy.special

LAMBDA_OVER_D_MAS = 0.55e-6 / 8.0 * 206264806.247  # 14.18 mas at 550 nm on the VLT


def airy(r_mas, lam_over_d=LAMBDA_OVER_D_MAS, obscuration=0.14):
    """Obscured Airy intensity (peak 1) at radius ``r_mas``."""
    xx = np.pi * np.asarray(r_mas, dtype=float) / lam_over_d
    xs = np.where(xx == 0, 1.0, xx)
    eps = obscuration

    def jinc(z):
        zs = np.where(z == 0, 1.0, z)
        return np.where(z == 0, 1.0, 2 * scipy.special.j1(zs) / zs)

    amp = (jinc(xs) - eps**2 * jinc(eps * xs)) / (1 - eps**2)
    return np.where(xx == 0, 1.0, amp**2)


def elliptical_gaussian(dx, dy, sx, sy):
    return np.exp(-0.5 * ((dx / sx) ** 2 + (dy / sy) ** 2))


@dataclass
class AnalyticPSFGrid:
    """A PSF grid whose nodes sample analytic functions (the optics ``psf_grid`` protocol).

    Parameters
    ----------
    profile : callable (dx_mas, dy_mas, node_x_arcsec, node_y_arcsec) -> intensity
    nodes_x, nodes_y : ndarray (arcsec)
    n : int (odd), pixel_scale : float (mas)
    """

    profile: object
    nodes_x: np.ndarray
    nodes_y: np.ndarray
    n: int = 129
    pixel_scale: float = 1.0
    cube: np.ndarray = field(init=False)
    norms: np.ndarray = field(init=False)

    def __post_init__(self):
        off = (np.arange(self.n) - (self.n - 1) / 2) * self.pixel_scale
        dy, dx = np.meshgrid(off, off, indexing="ij")
        cube = np.empty((len(self.nodes_y), len(self.nodes_x), self.n, self.n))
        for j, ny in enumerate(self.nodes_y):
            for i, nx in enumerate(self.nodes_x):
                cube[j, i] = self.profile(dx, dy, nx, ny)
        self.norms = cube.sum(axis=(2, 3))
        self.cube = cube / self.norms[:, :, None, None]

    @property
    def is_static(self):
        return len(self.nodes_x) == 1 and len(self.nodes_y) == 1

    def bilinear_weights(self, x, y):
        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        fx = _fractional_index(self.nodes_x, x)
        fy = _fractional_index(self.nodes_y, y)
        ix0 = np.clip(np.floor(fx).astype(int), 0, max(len(self.nodes_x) - 2, 0))
        iy0 = np.clip(np.floor(fy).astype(int), 0, max(len(self.nodes_y) - 2, 0))
        tx = np.clip(fx - ix0, 0, 1)
        ty = np.clip(fy - iy0, 0, 1)
        ix1 = np.minimum(ix0 + 1, len(self.nodes_x) - 1)
        iy1 = np.minimum(iy0 + 1, len(self.nodes_y) - 1)
        iy = np.stack([iy0, iy0, iy1, iy1], axis=1)
        ix = np.stack([ix0, ix1, ix0, ix1], axis=1)
        w = np.stack([(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx], axis=1)
        return iy, ix, w

    def psf_at(self, x, y):
        iy, ix, w = self.bilinear_weights(x, y)
        return np.einsum("k,kab->ab", w[0], self.cube[iy[0], ix[0]])

    def continuous(self, dx, dy, x, y):
        """The bilinear mix of the analytic node functions, same normalisation as the cube
        (per PSF pixel), at offsets ``dx, dy`` (mas) for a star at field (x, y) arcsec."""
        iy, ix, w = self.bilinear_weights([x], [y])
        out = 0.0
        for k in range(4):
            j, i = iy[0, k], ix[0, k]
            out = (
                out
                + w[0, k]
                * self.profile(dx, dy, self.nodes_x[i], self.nodes_y[j])
                / (self.norms[j, i])
            )
        return out


def _fractional_index(nodes, v):
    if len(nodes) == 1:
        return np.zeros_like(v)
    return np.interp(v, nodes, np.arange(len(nodes)))


@dataclass
class ConstantTipTilt:
    """Tip-tilt covariance constant, or linear in x, across the field (mas^2)."""

    sxx: float = 9.0
    syy: float = 6.0
    sxy: float = 1.5
    slope: float = 0.0  # added to sxx per arcsec of x

    def covariance(self, x, y):
        x = np.atleast_1d(np.asarray(x, dtype=float))
        cov = np.zeros((len(x), 2, 2))
        cov[:, 0, 0] = self.sxx + self.slope * np.abs(x)
        cov[:, 1, 1] = self.syy
        cov[:, 0, 1] = cov[:, 1, 0] = self.sxy
        return cov * u.mas**2


@dataclass
class PolynomialDistortion:
    """dx = a*x*y, dy = b*(x^2 - y^2) + c * epoch (arcsec, epoch in yr)."""

    a: float = 2e-6
    b: float = 1e-6
    c: float = 0.0
    enabled: bool = True

    def displacement(self, x, y, epoch):
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        t = u.Quantity(epoch, u.yr).value
        return self.a * x * y * u.arcsec, (self.b * (x**2 - y**2) + self.c * t) * u.arcsec


@dataclass
class RingHalo:
    """A smooth halo kernel: Moffat-like wings beyond ``r_c`` (mas), summing to ``fraction``."""

    fraction: float = 0.2
    r_c: float = 280.0
    extent: float = 3000.0

    def kernel(self, pixel_scale_mas):
        half = int(np.ceil(self.extent / pixel_scale_mas))
        off = np.arange(-half, half + 1) * pixel_scale_mas
        yy, xx = np.meshgrid(off, off, indexing="ij")
        r = np.hypot(xx, yy)
        ramp = 0.5 * (1 + np.tanh((r - self.r_c) / (0.2 * self.r_c)))
        k = ramp * (1 + (r / self.r_c) ** 2) ** -1.5
        return k / k.sum() * self.fraction


@dataclass
class FakeOptics:
    """The optics protocol assembled from the doubles above."""

    psf_grid: AnalyticPSFGrid
    tiptilt: ConstantTipTilt = field(default_factory=ConstantTipTilt)
    distortion: PolynomialDistortion = field(
        default_factory=lambda: PolynomialDistortion(enabled=False)
    )
    halo: RingHalo | None = None
    blur_sigma: float = 4.6  # mas: 3 charge diffusion (+) 3.5 vibration

    def kernel_covariance(self, x, y):
        cov = self.tiptilt.covariance(x, y).to_value(u.mas**2)
        cov[:, 0, 0] += self.blur_sigma**2
        cov[:, 1, 1] += self.blur_sigma**2
        return cov * u.mas**2


def airy_profile(stretch=0.0):
    """Airy profile, optionally elongated radially by ``stretch`` per arcsec of node x."""

    def profile(dx, dy, nx, ny):
        sx = 1.0 + stretch * abs(nx)
        return airy(np.hypot(dx / sx, dy))

    return profile


def gaussian_profile(sigma=5.0):
    def profile(dx, dy, nx, ny):
        return elliptical_gaussian(dx, dy, sigma, sigma)

    return profile


def make_optics(kind="airy", nodes=3, half_field=2.0, n=129, psf_scale=1.0, **kw):
    """A FakeOptics with an ``nodes x nodes`` PSF grid over +-half_field arcsec."""
    prof = airy_profile(kw.pop("stretch", 0.0)) if kind == "airy" else gaussian_profile()
    grid_nodes = np.linspace(-half_field, half_field, nodes)
    grid = AnalyticPSFGrid(prof, grid_nodes, grid_nodes, n=n, pixel_scale=psf_scale)
    return FakeOptics(psf_grid=grid, **kw)


def brute_force_stamp(grid, x, y, cov, x_pix, y_pix, pixel_scale, m, sub=15, sensitivity=None):
    """Independent reference: direct evaluation of PSF (x) Gaussian, integrated over pixels.

    The continuous PSF (bilinear mix of the analytic node functions, truncated to the
    cube's square) is evaluated on the lattice of ``sub x sub`` midpoints of every
    detector pixel of an ``m x m`` stamp (corner at ``round(x_pix) - m//2``), convolved
    on that lattice with the sampled 2-D Gaussian (linear FFT convolution with zero
    padding, no wrap-around), and each pixel is integrated by the midpoint rule.
    ``sensitivity``: optional function of the sub-pixel position in (-1/2, 1/2) pixel
    giving the relative response along each axis (separable); default uniform.
    """
    import scipy.signal

    h = pixel_scale / sub
    half_cube = (grid.n - 1) / 2 * grid.pixel_scale + grid.pixel_scale / 2
    cov = np.asarray(cov, dtype=float)
    sig = np.sqrt(max(cov[0, 0], cov[1, 1], 1e-12))
    k_half = int(np.ceil(6 * sig / h))
    ko = np.arange(-k_half, k_half + 1) * h
    ky, kx = np.meshgrid(ko, ko, indexing="ij")
    if np.linalg.det(cov) <= 1e-12:
        kern = ((kx == 0) & (ky == 0)).astype(float)
    else:
        inv = np.linalg.inv(cov)
        kern = np.exp(-0.5 * (inv[0, 0] * kx**2 + 2 * inv[0, 1] * kx * ky + inv[1, 1] * ky**2))
    kern /= kern.sum()
    # lattice of sub-pixel midpoints, extended by the kernel half-width on each side
    x0, y0 = round(x_pix) - m // 2, round(y_pix) - m // 2
    t = (np.arange(-k_half, m * sub + k_half) + 0.5) / sub - 0.5  # in pixels from corner
    ox = (x0 + t - x_pix) * pixel_scale
    oy = (y0 + t - y_pix) * pixel_scale
    py, px = np.meshgrid(oy, ox, indexing="ij")
    psf = grid.continuous(px, py, x, y)
    psf = np.where((np.abs(px) <= half_cube) & (np.abs(py) <= half_cube), psf, 0.0)
    psf = psf / grid.pixel_scale**2  # per mas^2
    img = scipy.signal.fftconvolve(psf, kern, mode="valid")  # (m*sub, m*sub)
    w = np.ones(sub)
    if sensitivity is not None:
        w = sensitivity((np.arange(sub) + 0.5) / sub - 0.5)
        w = w / w.mean()
    pix = (img.reshape(m, sub, m, sub) * w[None, :, None, None] * w[None, None, None, :]).mean(
        axis=(1, 3)
    )
    return pix * pixel_scale**2


def epoch_table(x, y, mag, epoch=0.0):
    """A catalogue epoch table (QTable) with positions (arcsec) and V magnitudes."""
    from astropy.table import QTable

    n = len(x)
    t = QTable(
        {
            "id": np.arange(n),
            "x": np.asarray(x, dtype=float) * u.arcsec,
            "y": np.asarray(y, dtype=float) * u.arcsec,
            "pm_x": np.zeros(n) * u.mas / u.yr,
            "pm_y": np.zeros(n) * u.mas / u.yr,
            "mag": np.asarray(mag, dtype=float) * u.mag,
        }
    )
    t.meta["epoch"] = epoch * u.yr
    return t


def tiptilt_halo_optics():
    """The small test optics with every frame term the renderer adds around the PSF grid.

    A constant elliptical tip-tilt kernel (16 / 9 / 2 mas^2) and a ring halo holding 20 %
    of the light (core 100 mas, extent 600 mas), on :func:`make_optics`'s Airy grid.
    """
    return make_optics(
        tiptilt=ConstantTipTilt(sxx=16.0, syy=9.0, sxy=2.0),
        halo=RingHalo(fraction=0.2, r_c=100.0, extent=600.0),
    )


def random_epoch(n, half_x, half_y=None, seed=3, mags=(15.0, 23.0)):
    """``n`` stars uniform in +-``half_x`` x +-``half_y`` arcsec, V uniform in ``mags``."""
    r = np.random.default_rng(seed)
    half_y = half_x if half_y is None else half_y
    return epoch_table(
        r.uniform(-half_x, half_x, n), r.uniform(-half_y, half_y, n), r.uniform(*mags, n)
    )


def chunk_normals(rng, n):
    """The standard normals the detector's noise draw takes from ``rng`` for ``n`` pixels.

    Drawn through the production path (``detector._draw_chunk``) at zero mean and unit
    read-noise variance, where the Gaussian draw is the normal itself (checked).
    """
    from mavispm.simulate.render import detector

    out = np.empty(n, np.float32)
    z = detector._draw_chunk(np.zeros(n, np.float32), rng, 1, 1.0, np.inf, out)
    np.testing.assert_array_equal(out, z)
    return z
