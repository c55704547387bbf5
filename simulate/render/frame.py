"""Assemble one frame: stars (AO field) + seeing halo + sky, then the detector.

:func:`render_frame` is the pure pipeline behind ``mavispm simulate frames``: it
takes one epoch table, the scene settings and an optics model (see the optics
contract in ``docs/render.md``) and returns the stacked image with its truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.errors import InputError
from mavispm.core.frame import Frame
from mavispm.simulate.optics.broadband import colour_bins, slice_spectrum
from mavispm.simulate.optics.refraction import star_displacement
from mavispm.simulate.optics.telescope import telescope_displacement
from mavispm.simulate.render.detector import expose_stack
from mavispm.simulate.render.halo_convolution import halo_field
from mavispm.simulate.render.pixel_response import flat_field_residual
from mavispm.simulate.render.scene import SceneSettings
from mavispm.simulate.render.stamps import StarRenderer
from mavispm.simulate.render.symmetric2x2 import eigvals_2x2
from mavispm.simulate.render.thread_count import frame_threads
from mavispm.simulate.render.zero_point import (
    photometric_zero_point,
    sky_electrons_per_pixel,
    star_electrons,
)

__all__ = [
    "HALO_COARSE_PIXEL_MAS",
    "RenderedStack",
    "make_renderer",
    "noise_sigma_per_subexposure",
    "render_frame",
    "render_stack",
]

#: The frame's sky, halo and stars are accumulated in float32 (the noise draw reads float32
#: and the product stores float32): half the 128 MB of fresh memory of a 4000 x 4000 frame
#: and faster stamp adds; the round-off (a few float32 spacings of a pixel's value) is below
#: 1e-3 of the pixel's photon noise (``tests/test_render_frame.py``, docs/render.md rev. 16).
FRAME_DTYPE = np.float32

#: Automatic halo down-sampling aims at coarse pixels of about this size (mas).
HALO_COARSE_PIXEL_MAS = 60.0


def make_renderer(optics, scene: SceneSettings, cache_dir=None) -> StarRenderer:
    """A star renderer for ``optics`` at the scene's pixel scale (reuse it across epochs).

    Parameters
    ----------
    optics : Optics
        Its ``psf_grid`` is rendered.
    scene : SceneSettings
        Pixel scale, render knobs and intra-pixel response.
    cache_dir : path, optional
        Also keep the stamp plans (PSF-node transforms) in this folder
        (see :class:`~mavispm.simulate.render.stamps.StarRenderer`).

    Returns
    -------
    StarRenderer
    """
    return StarRenderer(
        optics.psf_grid,
        scene.detector.pixel_scale,
        scene.render,
        cache_dir,
        intrapixel_amplitude=scene.detector.intrapixel_amplitude,
        slice_cubes=getattr(optics, "psf_slices", None),
    )


def _values(q, unit) -> np.ndarray:
    """Float array of ``q`` in ``unit``; plain numbers are taken to be in ``unit`` already."""
    return np.asarray(u.Quantity(q, unit).value, dtype=float)


def noise_sigma_per_subexposure(scene: SceneSettings) -> float:
    """Per-pixel noise sigma of the stack from sky and read noise, in electrons per sub-exposure.

    Parameters
    ----------
    scene : SceneSettings
        Exposure, detector and photometry.

    Returns
    -------
    float
        [electron] per sub-exposure.
    """
    sky = sky_electrons_per_pixel(
        scene.photometry, scene.detector.pixel_scale * u.mas, scene.exptime * u.s
    ).value
    return float(np.sqrt(scene.nexp * (sky + scene.detector.read_noise**2)) / scene.nexp)


#: Most electrons of one star in one sub-exposure that the noise model can draw
#: (numpy's Poisson sampler stops near 9e18; real detectors saturate far below).
MAX_STAR_ELECTRONS = 1e15


def check_drawable(stars, scene) -> None:
    """Refuse catalogues that cannot make a meaningful frame, naming the column.

    Cheap (no optics needed), so the frames stage calls it before building a PSF grid.

    Parameters
    ----------
    stars : astropy.table.QTable
        The epoch's star table (``x``, ``y`` [arcsec], ``mag`` [mag]).
    scene : SceneSettings
        Detector and noise settings.

    Raises
    ------
    InputError
        A star too bright for the noise model (``mag``), or no star on the
        detector or within one detector size of it (``x``/``y``: an empty frame
        is not a simulation).
    """
    if "luminous" in stars.colnames:
        stars = stars[np.asarray(stars["luminous"], dtype=bool)]
    det, nexp = scene.detector, scene.nexp
    mag = np.asarray(u.Quantity(stars["mag"], u.mag).value, dtype=float)
    flux_sub = star_electrons(mag, scene.photometry, scene.exptime * u.s).value
    x_pix = _values(stars["x"], u.arcsec) * 1000.0 / det.pixel_scale + (det.nx - 1) / 2
    y_pix = _values(stars["y"], u.arcsec) * 1000.0 / det.pixel_scale + (det.ny - 1) / 2
    if len(mag) and np.max(flux_sub) * nexp > MAX_STAR_ELECTRONS:
        i = int(np.argmax(flux_sub))
        raise InputError(
            f"star {stars['id'][i]} with mag {mag[i]:g} gives {flux_sub[i] * nexp:.3g} electrons, "
            f"beyond the {MAX_STAR_ELECTRONS:.0e} the detector model can draw; expected "
            "magnitudes of stars in a cluster field",
            column="mag",
        )
    # stars just off the edge light the frame with their wings: only a catalogue with
    # no star within one detector size of it cannot put any light on it
    m = max(det.nx, det.ny)
    near = (x_pix > -m) & (x_pix < det.nx + m) & (y_pix > -m) & (y_pix < det.ny + m)
    if len(mag) and not np.any(near):
        raise InputError(
            f"none of the {len(mag)} stars falls on or near the {det.nx} x {det.ny} pixel detector "
            f"(star pixels x {np.min(x_pix):.0f}..{np.max(x_pix):.0f}, "
            f"y {np.min(y_pix):.0f}..{np.max(y_pix):.0f}); expected positions in arcsec "
            "from the field centre",
            column="x",
        )


@dataclass
class RenderedStack:
    """The arrays of one rendered stack, as written to the ``frames`` product.

    Parameters
    ----------
    adu : ndarray (ny, nx) float32
        The stacked image [adu].
    saturated : ndarray (ny, nx) bool
        Pixels saturated in at least one sub-exposure.
    noiseless : ndarray (ny, nx) float64 or None
        The noise-free stack [electron] (None: not kept, see :func:`render_stack`).
    truth : QTable
        The rendered stars (``TRUTH_SPEC`` columns).
    attrs : dict
        The ``frames`` root attributes.
    """

    adu: np.ndarray
    saturated: np.ndarray
    noiseless: np.ndarray | None
    truth: QTable
    attrs: dict

    def frame(self) -> Frame:
        """The :class:`~mavispm.core.frame.Frame` (image in electrons, float64)."""
        return Frame.from_attrs(
            self.adu, self.saturated, self.attrs, self.truth, noiseless=self.noiseless
        )


def render_frame(
    stars: QTable,
    epoch: u.Quantity,
    scene: SceneSettings,
    optics,
    rng: np.random.Generator,
    renderer: StarRenderer | None = None,
    progress: bool = False,
) -> Frame:
    """Render one epoch of a catalogue into a stacked frame.

    :func:`render_stack` wrapped in a :class:`~mavispm.core.frame.Frame` (see there for
    the parameters).

    Parameters
    ----------
    stars : QTable
        Epoch table of the catalogue.
    epoch : Quantity
        Epoch [yr].
    scene : SceneSettings
        Exposure, detector, photometry and render knobs.
    optics : Optics
        The scene's optics.
    rng : numpy.random.Generator
        Source of the photon and read noise.
    renderer : StarRenderer, optional
        Reuse a renderer (cached PSF transforms) across epochs.
    progress : bool
        Progress bar (on a terminal only).

    Returns
    -------
    Frame
        The stack in electrons (``frame.adu``: in adu, as written), its
        saturation mask, the noise-free stack (``noiseless``), the truth table of
        the rendered stars and the ``frames`` root attributes; the frame that
        :func:`mavispm.measure.stars.measure_frame.measure_frame` measures.
    """
    return render_stack(stars, epoch, scene, optics, rng, renderer, progress).frame()


def render_stack(
    stars: QTable,
    epoch: u.Quantity,
    scene: SceneSettings,
    optics,
    rng: np.random.Generator,
    renderer: StarRenderer | None = None,
    progress: bool = False,
    noiseless: bool = True,
) -> RenderedStack:
    """Render one epoch of a catalogue into the arrays of a stacked frame.

    The frames command writes these directly: building a
    :class:`~mavispm.core.frame.Frame` (image in float64 electrons) and converting it
    back to float32 adu costs four passes over the frame and 330 MB of fresh memory
    at 4000 x 4000 pixels.

    Parameters
    ----------
    stars : QTable
        Epoch table of the catalogue: ``id``, ``x``, ``y`` [arcsec], ``mag`` [mag],
        optional ``luminous`` (False rows are skipped).
    epoch : Quantity
        Epoch (yr), passed to the dynamic distortion.
    scene : SceneSettings
    optics : object
        Optics model (``psf_grid``, ``halo``, ``kernel_covariance``, ``distortion``).
    rng : numpy.random.Generator
        Source of the photon and read noise.
    renderer : StarRenderer, optional
        Reuse a renderer (cached PSF transforms) across epochs.
    progress : bool
        Show progress bars.
    noiseless : bool
        Keep the noise-free stack (False: ``RenderedStack.noiseless`` is None, the
        pass over the frame that scales it to the stack is left out, and the noise is
        drawn over the image itself: no second full-frame array).

    Returns
    -------
    RenderedStack
        The stack in adu (float32), its saturation mask, the noise-free stack
        [electron], the truth table of the rendered stars and the root attributes.
    """
    for col in ("id", "x", "y", "mag"):
        if col not in stars.colnames:
            raise InputError(f"epoch table has no '{col}' column; cannot render", column=col)
    det, phot, par = scene.detector, scene.photometry, scene.render
    if "luminous" in stars.colnames:
        stars = stars[np.asarray(stars["luminous"], dtype=bool)]
    renderer = renderer or make_renderer(optics, scene)
    s = det.pixel_scale
    x_cat = _values(stars["x"], u.arcsec)
    y_cat = _values(stars["y"], u.arcsec)
    mag = np.asarray(u.Quantity(stars["mag"], u.mag).value, dtype=float)
    if np.any(~np.isfinite(mag)):
        raise InputError("non-finite magnitudes; every luminous star needs a flux", column="mag")
    x, y = x_cat.copy(), y_cat.copy()
    if getattr(optics.distortion, "enabled", False) and len(x):
        dx, dy = optics.distortion.displacement(x_cat, y_cat, u.Quantity(epoch, u.yr).value)
        x = x + _values(dx, u.arcsec)
        y = y + _values(dy, u.arcsec)
    tel = getattr(getattr(optics, "settings", None), "telescope", None)
    if tel is not None and tel.enabled and len(x):
        tx, ty = telescope_displacement(x_cat, y_cat, u.Quantity(epoch, u.yr).value, tel)
        x, y = x + tx, y + ty
    dar = _refraction_shift(stars, optics, u.Quantity(epoch, u.yr).value)
    if dar is not None:
        x, y = x + dar[0], y + dar[1]
    x_pix = x * 1000.0 / s + (det.nx - 1) / 2
    y_pix = y * 1000.0 / s + (det.ny - 1) / 2
    # per-exposure image motion: each star is drawn at its mean displacement over the
    # stack, blurred by the displacements' covariance (truth keeps the true position)
    motion = getattr(optics, "image_motion", None)
    motion_mean = motion_cov = None
    if motion is not None and motion.enabled and len(x):
        motion_mean, motion_cov = motion.stack(
            x, y, scene.nexp, scene.exptime, u.Quantity(epoch, u.yr).value
        )
    sub_exposure = scene.exptime * u.s
    flux_sub = star_electrons(mag, phot, sub_exposure).value
    check_drawable(stars, scene)
    halo = optics.halo if par.halo else None
    core_fraction = 1.0 - (halo.fraction if halo is not None else 0.0)
    cov = _values(optics.kernel_covariance(x, y), u.mas**2) if len(x) else np.zeros((0, 2, 2))
    render_x_pix, render_y_pix = x_pix, y_pix
    if motion_mean is not None:
        cov = cov + motion_cov
        render_x_pix = x_pix + motion_mean[:, 0] / s
        render_y_pix = y_pix + motion_mean[:, 1] / s
    colour = spectra = None
    if getattr(renderer, "n_slices", 1) > 1 and len(x):
        colour, spectra, spread, extent = _broadband_kernels(
            stars, optics, u.Quantity(epoch, u.yr).value
        )
        cov = cov + spread
    sigma_max = np.sqrt(np.clip(eigvals_2x2(cov)[1], 0, None)) if len(x) else x
    if spectra is not None:
        sigma_max = sigma_max + extent / 4  # the slices' shifts widen the wing
    noise = noise_sigma_per_subexposure(scene)
    threads = frame_threads(par.threads, len(x))  # 0: one thread for small frames
    sizes = renderer.stamp_sizes(flux_sub * core_fraction, noise, sigma_max, x, y)
    sky = sky_electrons_per_pixel(phot, s * u.mas, sub_exposure).value
    # the sky fills the frame in one sequential pass (touching a fresh 128 MB array
    # first in the scattered order of the stamps costs ~0.5 s of page faults); with a
    # halo, the same pass writes sky + halo (halo_field's ``fill``)
    if halo is not None and len(x):
        b = par.halo_downsample or max(1, int(round(HALO_COARSE_PIXEL_MAS / s)))
        image = halo_field(
            render_x_pix,
            render_y_pix,
            flux_sub,
            (det.ny, det.nx),
            halo,
            s,
            b,
            threads,
            out=np.empty((det.ny, det.nx), dtype=FRAME_DTYPE),
            fill=sky,
            cache_dir=getattr(renderer, "cache_dir", None),
        )
    else:
        image = np.full((det.ny, det.nx), sky, dtype=FRAME_DTYPE)
    rendered = renderer.render(
        image,
        render_x_pix,
        render_y_pix,
        x,
        y,
        cov,
        flux_sub * core_fraction,
        sizes,
        noise_sigma=noise,
        progress=progress,
        colour=colour,
        spectra=spectra,
        threads=threads,
    )
    flat = flat_field_residual(image.shape, det.flat_residual, det.flat_seed)
    if flat is not None:
        image *= flat
    img_adu, saturated = expose_stack(
        image,
        scene.nexp,
        det,
        rng,
        noise=scene.noise,
        skew_limit=par.gaussian_skew_limit,
        threads=threads,
        poisson_skew_limit=par.poisson_skew_limit,
        # without the noise-free stack, the noise is drawn over the image itself: no
        # fresh 64 MB for a 4000 x 4000 stack (the same values)
        out=None if noiseless else image,
    )
    if noiseless:
        image *= scene.nexp  # in place: the noise-free stack (electron)
    else:
        image = None
    keep = rendered
    truth = QTable()
    truth["id"] = np.asarray(stars["id"], dtype=np.int64)[keep]
    truth["x_pix"] = x_pix[keep]
    truth["y_pix"] = y_pix[keep]
    truth["x"] = x[keep] * u.arcsec
    truth["y"] = y[keep] * u.arcsec
    truth["x_cat"] = x_cat[keep] * u.arcsec
    truth["y_cat"] = y_cat[keep] * u.arcsec
    truth["flux"] = flux_sub[keep] * scene.nexp * u.electron
    truth["mag"] = mag[keep] * u.mag
    if dar is not None:
        truth["dar_x"] = dar[0][keep] * u.arcsec
        truth["dar_y"] = dar[1][keep] * u.arcsec
    if motion_mean is not None:  # the stack's mean image motion (an astrometric error)
        truth["dx_motion"] = motion_mean[keep, 0] * u.mas
        truth["dy_motion"] = motion_mean[keep, 1] * u.mas
    attrs = {
        "epoch": u.Quantity(epoch, u.yr),
        "pixel_scale": s * u.mas,
        "exptime": scene.exptime * u.s,
        "nexp": int(scene.nexp),
        "gain": det.gain * u.electron / u.adu,
        "read_noise": det.read_noise * u.electron,
        "saturation": det.saturation_adu * u.adu,
        "sky": sky * scene.nexp * u.electron,
        "halo_fraction": (1.0 - core_fraction),
        "zero_point": photometric_zero_point(phot),
    }
    return RenderedStack(img_adu, saturated, image, truth, attrs)


def _teff(stars: QTable) -> np.ndarray:
    """Effective temperatures [K] of the stars (NaN where the table has no ``teff``)."""
    if "teff" in stars.colnames:
        return _values(stars["teff"], u.K)
    return np.full(len(stars), np.nan)


def _broadband_kernels(stars: QTable, optics, epoch: float):
    """Colour bins and broadband kernels of the stars (``[scene.optics.broadband]``).

    Returns
    -------
    colour : numpy.ndarray (N,) int
        Bin of each star.
    spectra : list of (weights (K,), shifts (K, 2) [mas])
        Each bin's kernel: the slices of its median star, shifted relative to that
        star's mean refraction (each star is placed at its own mean, ``dar``).
    spread : numpy.ndarray (N, 2, 2)
        Each star's in-sub-band refraction spread along the zenith [mas^2].
    extent : numpy.ndarray (N,)
        Largest slice shift of each star's kernel [mas].
    """
    settings = optics.settings
    teff = _teff(stars)
    teff = np.where(np.isfinite(teff), teff, settings.refraction.default_teff)
    spec = slice_spectrum(teff, settings.refraction, settings.broadband.slices, epoch)
    # equal-count bins of temperature (the mean shift is monotonic in it, and the slice
    # weights follow it with refraction off too)
    index, rep = colour_bins(teff, settings.broadband.colour_bins)
    e = np.asarray(spec.direction)
    rel = (spec.shifts - spec.mean[:, None]) * 1000.0  # mas
    spectra = [(spec.weights[r], rel[r][:, None] * e[None, :]) for r in rep]
    spread = spec.variance[:, None, None] * 1e6 * np.outer(e, e)[None]
    extent = np.abs(rel[rep]).max(axis=1)[index]
    return index, spectra, spread, extent


def _refraction_shift(stars: QTable, optics, epoch: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Colour-dependent atmospheric refraction of each star [arcsec], or None when off.

    Uses the epoch table's ``teff`` column [K] where present (else the settings'
    ``default_teff``); see ``simulate/optics/refraction.py``.
    """
    refr = getattr(getattr(optics, "settings", None), "refraction", None)
    if refr is None or not refr.enabled or len(stars) == 0:
        return None
    return star_displacement(_teff(stars), refr, epoch)
