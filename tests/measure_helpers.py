"""Independent frame synthesiser for the measure tests (not the project's renderer).

Writes the ``frames`` product (docs/formats.md) for stars with an analytic,
pixel-integrated Gaussian PSF (exact, via the error function) or a Moffat PSF
(integrated by sub-pixel sampling), optionally field-variable, with Poisson and
read noise and saturation. The same PRF gives the exact truth ePSF for CRLB tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np
from astropy.table import QTable
from scipy.special import ndtr

from mavispm.core.products import write_product

ZERO_POINT = 31.0  # mag giving 1 electron in the whole stack


def mag_to_flux(mag):
    """Whole-stack flux [electron] of a star of magnitude ``mag``."""
    return 10 ** (-0.4 * (np.asarray(mag, float) - ZERO_POINT))


@dataclass(frozen=True)
class SynthPSF:
    """Analytic PSF with a linear field variation of its width.

    Attributes
    ----------
    sigma : float
        Gaussian sigma [pixel] at the frame centre (Moffat: alpha = sigma * 1.5).
    gradient : float
        Fractional change of the width from the centre to the frame edge along x
        (and ``gradient / 2`` along y, so the PSF also becomes elliptical).
    profile : str
        "gaussian" or "moffat" (beta 3.5).
    """

    sigma: float = 1.2
    gradient: float = 0.0
    profile: str = "gaussian"

    def widths(self, x, y, shape):
        ny, nx = shape
        ux = (np.asarray(x) - (nx - 1) / 2) / (nx / 2)
        uy = (np.asarray(y) - (ny - 1) / 2) / (ny / 2)
        sx = self.sigma * (1 + self.gradient * ux)
        sy = self.sigma * (1 + 0.5 * self.gradient * uy)
        return sx, sy

    def prf(self, dx, dy, sx, sy):
        """Fraction of the flux in a pixel centred at offset (dx, dy)."""
        if self.profile == "gaussian":
            fx = ndtr((dx + 0.5) / sx) - ndtr((dx - 0.5) / sx)
            fy = ndtr((dy + 0.5) / sy) - ndtr((dy - 0.5) / sy)
            return fx * fy
        beta = 3.5
        sub = (np.arange(6) + 0.5) / 6 - 0.5
        total = 0.0
        for ox in sub:
            for oy in sub:
                r2 = ((dx + ox) / (1.5 * sx)) ** 2 + ((dy + oy) / (1.5 * sy)) ** 2
                total = total + (beta - 1) / (np.pi * 1.5 * sx * 1.5 * sy) * (1 + r2) ** -beta
        return total / 36.0

    def prf_at(self, x, y, shape):
        """The PRF callable ``prf(dx, dy)`` of a star at (x, y)."""
        sx, sy = self.widths(x, y, shape)
        return lambda dx, dy: self.prf(dx, dy, sx, sy)


def render_image(shape, x, y, flux, psf: SynthPSF, radius=None):
    """Noiseless image [electron] of stars (no sky)."""
    ny, nx = shape
    img = np.zeros(shape)
    rad = int(radius or np.ceil(8 * psf.sigma * (1 + abs(psf.gradient)) + 3))
    sx, sy = psf.widths(x, y, shape)
    for xi, yi, fi, sxi, syi in zip(x, y, flux, sx, sy):
        cx, cy = int(np.rint(xi)), int(np.rint(yi))
        x_lo, x_hi = max(cx - rad, 0), min(cx + rad + 1, nx)
        y_lo, y_hi = max(cy - rad, 0), min(cy + rad + 1, ny)
        if x_lo >= x_hi or y_lo >= y_hi:
            continue
        cols = np.arange(x_lo, x_hi) - xi
        rows = np.arange(y_lo, y_hi) - yi
        img[y_lo:y_hi, x_lo:x_hi] += fi * psf.prf(cols[None, :], rows[:, None], sxi, syi)
    return img


@dataclass(frozen=True)
class Detector:
    gain: float = 2.0  # electron/adu
    read_noise: float = 3.0  # electron per sub-exposure
    sky: float = 60.0  # electron/pixel, whole stack
    nexp: int = 4
    saturation: float = 60000.0  # adu per sub-exposure
    pixel_scale: float = 7.36  # mas


def noisy_frame(noiseless, det: Detector, rng):
    """Stacked image [adu] and saturated mask from a noiseless star image [electron]."""
    expected = noiseless + det.sky
    electrons = rng.poisson(np.clip(expected, 0, None)).astype(float)
    electrons += rng.normal(0.0, det.read_noise * np.sqrt(det.nexp), size=expected.shape)
    per_exp_adu = expected / det.nexp / det.gain
    saturated = per_exp_adu >= det.saturation
    image = electrons / det.gain
    image[saturated] = det.saturation * det.nexp
    return image.astype(np.float32), saturated


def fit_noisy_frame(image, saturated, det: Detector, psf, x0, y0, **kwargs):
    """``fit_stars`` on a :func:`noisy_frame` (adu -> electron, the stack's read noise and
    sky); ``kwargs`` go to ``fit_stars`` (``options``, ``flux0``, ``hold_positions``)."""
    from mavispm.measure.stars.batched_fit import fit_stars

    return fit_stars(
        image * det.gain,
        psf,
        x0,
        y0,
        read_noise_var=det.read_noise**2 * det.nexp,
        sky0=det.sky,
        saturated=saturated,
        **kwargs,
    )


def write_frames(
    path,
    shape,
    x,
    y,
    mag,
    psf: SynthPSF,
    det: Detector = Detector(),
    seed=0,
    ids=None,
    epoch=0.0,
    with_mask=True,
    truth=True,
    background=None,
):
    """Render and write a frames product; returns the truth table.

    ``background``: extra noiseless light [electron / pixel] (e.g. an unresolved crowd's),
    added before the noise; the frame's ``sky`` attribute stays ``det.sky``."""
    rng = np.random.default_rng(seed)
    x, y, mag = (np.asarray(a, float) for a in (x, y, mag))
    flux = mag_to_flux(mag)
    noiseless = render_image(shape, x, y, flux, psf)
    if background is not None:
        noiseless = noiseless + background
    image, saturated = noisy_frame(noiseless, det, rng)
    ny, nx = shape
    scale = det.pixel_scale / 1000.0
    t = QTable()
    t["id"] = np.arange(len(x), dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
    t["x_pix"] = x
    t["y_pix"] = y
    t["x"] = (x - (nx - 1) / 2) * scale * u.arcsec
    t["y"] = (y - (ny - 1) / 2) * scale * u.arcsec
    t["x_cat"] = t["x"]
    t["y_cat"] = t["y"]
    t["flux"] = flux * u.electron
    t["mag"] = mag * u.mag
    arrays = {"image": image * u.adu}
    if with_mask:
        arrays["saturated"] = saturated
    write_product(
        path,
        "frames",
        tables={"truth": t} if truth else {},
        arrays=arrays,
        attrs={
            "epoch": epoch * u.yr,
            "pixel_scale": det.pixel_scale * u.mas,
            "exptime": 30.0 * u.s,
            "nexp": det.nexp,
            "gain": det.gain * u.electron / u.adu,
            "read_noise": det.read_noise * u.electron,
            "saturation": det.saturation * u.adu,
            "sky": det.sky * u.electron,
            "distance": 4.7 * u.kpc,
            "ra_center": 154.4 * u.deg,
            "dec_center": -46.4 * u.deg,
            "scene": "{}",
        },
        seed=seed,
    )
    return t


def grid_positions(shape, spacing, margin, rng, jitter=0.5):
    """Star positions on a jittered grid (isolated stars)."""
    ny, nx = shape
    gx = np.arange(margin, nx - margin, spacing, dtype=float)
    gy = np.arange(margin, ny - margin, spacing, dtype=float)
    xx, yy = np.meshgrid(gx, gy)
    x = xx.ravel() + rng.uniform(-jitter, jitter, xx.size)
    y = yy.ravel() + rng.uniform(-jitter, jitter, xx.size)
    return x, y


def true_epsf(psf: SynthPSF, shape, grid=1, size=25, oversampling=4):
    """The exact ePSF of ``psf``: constant (grid=1, at the centre) or gridded."""
    from mavispm.measure.stars.epsf import node_positions
    from mavispm.measure.stars.variable_psf import constant_epsf, gridded_epsf, sample_epsf

    if grid == 1:
        ny, nx = shape
        return constant_epsf(
            sample_epsf(psf.prf_at((nx - 1) / 2, (ny - 1) / 2, shape), size, oversampling),
            oversampling,
        )
    gx, gy = node_positions(shape, grid)
    stack = [sample_epsf(psf.prf_at(a, b, shape), size, oversampling) for b in gy for a in gx]
    return gridded_epsf(np.array(stack), gx, gy, oversampling)


def robust_sigma(values):
    """Normalised median absolute deviation (Gaussian-equivalent sigma)."""
    values = np.asarray(values, float)
    return 1.4826 * np.median(np.abs(values - np.median(values)))


#: Magnitude bins of the error-model checks (bench and tests).
ERROR_BINS = ((-np.inf, 20.0), (20.0, 22.0), (22.0, 24.0), (24.0, np.inf))


def normalised_residuals(stars, column="x_err", bins=ERROR_BINS):
    """(measured - true) / reported error of a measured ``stars`` table, x and y pooled.

    Stars flagged 16 or 32 are left out; the median offset of the stars brighter
    than m = 22 is removed per axis (a frame offset the epoch alignment absorbs).

    Returns
    -------
    dict
        ``(lo, hi) -> ndarray`` of normalised residuals per magnitude bin.
    """
    ok = (np.asarray(stars["flag"]) & (16 | 32)) == 0
    mag = stars["mag"].to_value(u.mag)
    err_x = stars[column].to_value(u.mas)
    err_y = stars[column.replace("x_", "y_")].to_value(u.mas)
    ok &= np.isfinite(err_x) & np.isfinite(err_y)
    dx = (stars["x"] - stars["x_true"]).to_value(u.mas)
    dy = (stars["y"] - stars["y_true"]).to_value(u.mas)
    ref = ok & (mag < 22)
    if ref.any():
        dx = dx - np.median(dx[ref])
        dy = dy - np.median(dy[ref])
    out = {}
    for lo, hi in bins:
        s = ok & (mag >= lo) & (mag < hi)
        out[(lo, hi)] = np.concatenate([dx[s] / err_x[s], dy[s] / err_y[s]])
    return out


# --- the halo tests' PSF (tests/test_measure_halo_rings.py, test_measure_halo_errors.py)

#: Gaussian core sigma [pixel] and the halo's share of the light.
HALO_TEST_CORE, HALO_TEST_FRAC = 1.2, 0.3


def halo_light(r, scale):
    """Halo per unit flux [1/pixel]: exponential of ``scale`` [pixel], HALO_TEST_FRAC of the light."""
    return HALO_TEST_FRAC * np.exp(-r / scale) / (2 * np.pi * scale**2)


def halo_test_core(dx, dy):
    """Pixel-integrated unit Gaussian core (sigma HALO_TEST_CORE) at offsets ``dx, dy`` [pixel]."""
    s = HALO_TEST_CORE
    return (ndtr((dx + 0.5) / s) - ndtr((dx - 0.5) / s)) * (
        ndtr((dy + 0.5) / s) - ndtr((dy - 0.5) / s)
    )


def halo_test_epsf(oversampling=2, half=12, scale=8.0):
    """The fitter's ePSF of the halo tests: the core (Gaussian with the pixel's variance)
    and a halo of ``scale`` tapered to zero between 6 and 12 px; no per-star structure."""
    from mavispm.measure.stars.variable_psf import constant_epsf

    off = np.arange(-half * oversampling, half * oversampling + 1) / oversampling
    r = np.hypot(off[None, :], off[:, None])
    s2 = HALO_TEST_CORE**2 + 1.0 / 12
    core = (1 - HALO_TEST_FRAC) * np.exp(-0.5 * r**2 / s2) / (2 * np.pi * s2)
    taper = np.where(r < 6, 1.0, np.cos(0.5 * np.pi * np.clip((r - 6) / 6, 0, 1)) ** 2)
    return constant_epsf(core + halo_light(r, scale) * taper, oversampling)


def halo_test_image(shape, sky, x, y, flux, scale, margin=60, lobes=0.0):
    """Noise-free image of stars with the halo tests' PSF, padded by ``margin`` [pixel]
    on every side (no star is cut): sky plus, per star, ``flux`` x (core + halo of
    ``scale``, one per star or one for all), over ``2 margin + 1`` pixels. ``lobes``
    (per star or one for all): the halo times ``1 + lobes cos(4 theta)``, a square
    pattern the same for every star (as an AO PSF's control-radius structure), absent
    from :func:`halo_test_epsf`."""
    scale = np.broadcast_to(np.asarray(scale, dtype=float), np.shape(x))
    lobes = np.broadcast_to(np.asarray(lobes, dtype=float), np.shape(x))
    m = int(margin)
    image = np.full((shape[0] + 2 * m, shape[1] + 2 * m), sky)
    off = np.arange(-m, m + 1)
    for k in range(len(x)):
        cx, cy = int(round(x[k])) + m, int(round(y[k])) + m
        dx, dy = off[None, :] + cx - m - x[k], off[:, None] + cy - m - y[k]
        halo = halo_light(np.hypot(dx, dy), scale[k])
        if lobes[k]:
            halo = halo * (1 + lobes[k] * np.cos(4 * np.arctan2(dy, dx)))
        image[cy - m : cy + m + 1, cx - m : cx + m + 1] += flux[k] * (
            (1 - HALO_TEST_FRAC) * halo_test_core(dx, dy) + halo
        )
    return image


def jittered_grid(rng, nodes, jitter=3.0):
    """Star positions on the square grid ``nodes`` x ``nodes`` [pix], each moved by up to
    ``jitter`` px (uniform) in x and y; x's jitters drawn first, then y's."""
    gx, gy = np.meshgrid(nodes, nodes)
    return tuple(a.ravel() + rng.uniform(-jitter, jitter, a.size) for a in (gx, gy))


def ring_scene(rng, bx, by, dist, field_nodes):
    """Faint stars around bright ones, and field stars far from them (the halo tests' scene).

    Around each bright star ``(bx, by)`` one faint star at each distance of ``dist`` [pix],
    at equally spaced angles turned by a random angle per bright star (drawn first); then
    field stars on the grid ``field_nodes`` (:func:`jittered_grid`, drawn after).

    Returns
    -------
    x, y : ndarray
        The bright stars, the ring stars (bright star by bright star), the field stars [pix].
    d : ndarray
        NaN for the bright stars, the ring stars' distance, inf for the field stars [pix].
    """
    dist = np.asarray(dist, float)
    angle = np.arange(len(dist)) * 2 * np.pi / len(dist)
    turns = [angle + rng.uniform(0, 2 * np.pi) for _ in range(len(bx))]
    fx, fy = jittered_grid(rng, field_nodes)
    x = np.concatenate([bx, *(b + dist * np.cos(a) for b, a in zip(bx, turns)), fx])
    y = np.concatenate([by, *(b + dist * np.sin(a) for b, a in zip(by, turns)), fy])
    d = np.concatenate([np.full(len(bx), np.nan), np.tile(dist, len(bx)), np.full(len(fx), np.inf)])
    return x, y, d


PRIOR_SUB = 7.36 / 4  # sampling [mas] of the Gaussian PSF-R priors (a quarter Detector pixel)


def gaussian_cube(sigma_mas: float, n: int = 101) -> np.ndarray:
    """A round Gaussian PSF sampled every PRIOR_SUB mas, centred, summing to 1."""
    r = (np.arange(n) - (n - 1) / 2) * PRIOR_SUB
    g = np.exp(-0.5 * (r / sigma_mas) ** 2)
    psf = g[:, None] * g[None, :]
    return psf / psf.sum()


def write_prior(path, sigma_mas: float, nodes=(-2.0, 0.0, 2.0), **extra) -> None:
    """A ``psfgrid`` product (PSF-R prior) with the same Gaussian at every node [arcsec]."""
    cube = np.broadcast_to(gaussian_cube(sigma_mas), (len(nodes), len(nodes), 101, 101))
    arrays = {
        "cube": np.array(cube),
        "nodes_x": np.array(nodes) * u.arcsec,
        "nodes_y": np.array(nodes) * u.arcsec,
    }
    arrays.update(extra)
    write_product(
        path, "psfgrid", arrays=arrays, attrs={"pixel_scale": PRIOR_SUB * u.mas, "static": False}
    )


#: The fast fitter's options of the halo tests, beside the halo knobs each test sets.
HALO_FIT = dict(wing_threshold=3.0, sky_gradient=True, iterations=40, relative_tolerance=0.2)


def binned_halo_errors(fit, x, y, flux, d, bins):
    """The faint stars' errors against the truth by distance from their bright star.

    Parameters
    ----------
    fit : FitResult
        The fast fitter's result.
    x, y, flux : ndarray
        True positions [pix] and fluxes.
    d : ndarray
        Distance to the bright star [pix] (:func:`ring_scene`: inf for field stars).
    bins : sequence of (lo, hi)
        Distance bins [pix].

    Returns
    -------
    far : float
        The field stars' median fitted / true flux.
    flux_off, pos_off : ndarray
        Per bin the median ``|fitted / true flux / far - 1|`` and median position error [pix].
    """
    ratio = fit.flux / flux
    far = np.median(ratio[np.isinf(d)])
    miss = np.hypot(fit.x - x, fit.y - y)
    inside = [(d >= lo) & (d < hi) for lo, hi in bins]
    flux_off = np.array([np.median(np.abs(ratio[b] / far - 1)) for b in inside])
    return far, flux_off, np.array([np.median(miss[b]) for b in inside])
