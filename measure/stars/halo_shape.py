"""The non-round shape of bright stars' light beyond their fitting stamps, from the PSF-R prior.

The fitter models a bright star's light outside its stamp as ``flux * profile(r)``, a
radial profile measured on the frame (:mod:`~mavispm.measure.stars.halo`). An AO PSF is
not round there: between the fitting stamp and the control radius its structure (the
DM's fitting-error ring, the aliasing and servo lobes) modulates the azimuthal mean by
-30 to +40 % (1st-99th percentile, MAVIS grid, 5-52 px), hundreds of times a faint
neighbour's pixel noise around a V < 15 star. The observer's PSF reconstruction (the
``psfgrid`` prior of the PSF-R model, :mod:`~mavispm.measure.stars.psf_reconstruction`)
knows that structure: this module turns each prior node's PSF, blurred by the kernel the
PSF-R fit found and sampled on the detector pixels, into a *modulation* map, the PSF
over its own azimuthal mean in 1-px annuli. The fitter multiplies the measured radial
profile by it (bilinear in the field between the nodes and in the offset from the
star), so the frame keeps the radial calibration and the prior adds only the shape
(docs/measure-scale.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates, uniform_filter

from mavispm.measure.stars.psf_reconstruction import PSFRPrior
from mavispm.measure.stars.stamp_kernel import deposit_radial

__all__ = ["HaloShape", "deposit_shaped", "modulation", "prior_halo_shape", "ring_means"]


@dataclass(frozen=True)
class HaloShape:
    """Modulation maps of the halo's azimuthal mean at a grid of field nodes.

    Parameters
    ----------
    maps : ndarray, shape (len(node_y), len(node_x), 2 R + 1, 2 R + 1)
        Light over its azimuthal mean (1 where not known), offsets ``-R..R`` [pixel]
        from the star, row (y) first.
    node_x, node_y : ndarray
        Node positions [pixel] of the frame, increasing.
    """

    maps: np.ndarray
    node_x: np.ndarray
    node_y: np.ndarray

    @property
    def radius(self) -> int:
        """Half-width ``R`` of the maps [pixel]."""
        return (self.maps.shape[-1] - 1) // 2

    def weights(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The four bracketing nodes (flat indices) and their bilinear weights per star."""

        def axis(nodes, v):
            if len(nodes) == 1:
                return np.zeros(len(v), np.int64), np.zeros(len(v))
            v = np.clip(v, nodes[0], nodes[-1])
            i = np.clip(np.searchsorted(nodes, v, side="right") - 1, 0, len(nodes) - 2)
            return i, (v - nodes[i]) / (nodes[i + 1] - nodes[i])

        nxn = len(self.node_x)
        ix, wx = axis(self.node_x, np.asarray(x, float))
        iy, wy = axis(self.node_y, np.asarray(y, float))
        jx1 = np.minimum(ix + 1, nxn - 1)
        jy1 = np.minimum(iy + 1, len(self.node_y) - 1)
        index = np.stack([iy * nxn + ix, iy * nxn + jx1, jy1 * nxn + ix, jy1 * nxn + jx1], 1)
        w = np.stack([(1 - wy) * (1 - wx), (1 - wy) * wx, wy * (1 - wx), wy * wx], 1)
        return index.astype(np.int64), w


def ring_means(image: np.ndarray) -> np.ndarray:
    """Azimuthal mean of an image (optical axis at its centre) in 1-px annuli, by
    ``round(r)``: index ``k`` is the mean at radius ``k`` [pixel]."""
    n = image.shape[0]
    half = (n - 1) // 2
    off = np.arange(n) - half
    ring = np.rint(np.hypot(off[None, :], off[:, None])).astype(int)
    return np.bincount(ring.ravel(), image.ravel()) / np.bincount(ring.ravel())


def modulation(image: np.ndarray, inner: float) -> np.ndarray:
    """An image (optical axis at its centre) over its azimuthal mean in 1-px annuli.

    Parameters
    ----------
    image : ndarray, shape (2 R + 1, 2 R + 1)
        Light per pixel around a star [any unit].
    inner : float
        Radius [pixel] up to which the map is 1 (the fitting stamp models that light).

    Returns
    -------
    ndarray
        The modulation; 1 within ``inner``, beyond ``R`` and where the mean is not
        positive.
    """
    n = image.shape[0]
    half = (n - 1) // 2
    off = np.arange(n) - half
    r = np.hypot(off[None, :], off[:, None])
    ring = np.rint(r).astype(int)
    mean = np.bincount(ring.ravel(), image.ravel()) / np.bincount(ring.ravel())
    m = mean[ring]
    ok = (r > inner) & (r <= half) & (m > 0)
    return np.where(ok, image / np.where(ok, m, 1.0), 1.0)


def prior_halo_shape(
    prior: PSFRPrior,
    to_pixel,
    pixel_scale: float,
    kernel: np.ndarray,
    radius: int,
    inner: float,
    field_radial: bool = False,
) -> HaloShape:
    """The halo's modulation maps from the PSF-R prior (:func:`modulation` per node).

    Parameters
    ----------
    prior : PSFRPrior
        The observer's PSF reconstruction (already degraded by its width error).
    to_pixel : callable
        ``(x_arcsec, y_arcsec) -> (x_pix, y_pix)`` of the frame.
    pixel_scale : float
        Detector pixel [mas].
    kernel : ndarray, shape (K, 4)
        The PSF-R fit's kernels ``(cxx, cyy, cxy, stretch)`` [mas^2, 1]: the median
        width (round, ``sqrt((cxx + cyy) / 2)``, 0 where not positive) and stretch blur
        and stretch the prior before it is sampled.
    radius : int
        Half-width of the maps [pixel] (at most the prior's half-width).
    inner : float
        Radius [pixel] within which the maps are 1.
    field_radial : bool
        Also carry the prior's *radial* variation over the field: each node's map times
        its azimuthal mean (per unit flux of the node's PSF) over the median of the
        nodes' means, ring by ring, so the frame's one measured profile becomes each
        star's own (between ``inner`` and the maps' edge). False: the maps have a unit
        azimuthal mean (only the shape).

    Returns
    -------
    HaloShape
    """
    k = np.median(np.asarray(kernel, float), axis=0)
    sigma = np.sqrt(max(0.5 * (k[0] + k[1]), 0.0)) / prior.pixel_scale
    ratio = pixel_scale / prior.pixel_scale
    n = prior.cube.shape[-1]
    centre = (n - 1) / 2.0
    # the stretch is applied to the sampling points, after the blur and the pixel box
    # (scaled by 1 / stretch, as a radial stretch of a convolution is the convolution of
    # the stretched parts): no spline resampling of each node's whole cube (stretch_psf
    # took ~2/3 of this function's 2.3 s CPU on the 11 x 11 x 427^2 default prior)
    stretch = float(k[3]) if k[3] > 0 else 1.0
    box = max(int(round(ratio / stretch)), 1)  # the detector pixel, in prior pixels
    # the sampled points and the blur's support (3 sigma, the box) stay inside the cube,
    # whose edge would otherwise enter the outermost maps (up to 0.6 off at 50-52 px)
    reach = centre - 3.0 * sigma / stretch - box
    radius = max(int(min(radius, np.floor(reach * stretch / ratio) - 1)), 0)
    d = np.arange(-radius, radius + 1.0) * ratio / stretch + centre
    rows, cols = np.meshgrid(d, d, indexing="ij")
    maps = np.empty(prior.cube.shape[:2] + (2 * radius + 1,) * 2)
    means = np.ones(prior.cube.shape[:2] + (int(np.rint(radius * np.sqrt(2))) + 1,))
    for j in range(maps.shape[0]):
        for i in range(maps.shape[1]):
            psf = prior.cube[j, i]
            if sigma > 0:
                psf = gaussian_filter(psf, sigma / stretch)
            # pixel integration (a box of the detector pixel), then bilinear sampling
            psf = uniform_filter(psf, size=box, mode="constant")
            sampled = map_coordinates(psf, [rows, cols], order=1)
            maps[j, i] = modulation(sampled, inner)
            if field_radial:
                means[j, i] = ring_means(sampled) / max(float(prior.cube[j, i].sum()), 1e-300)
    if field_radial and maps.shape[0] * maps.shape[1] > 1:
        typical = np.median(means.reshape(-1, means.shape[-1]), axis=0)
        ratio = np.where(typical > 0, means / np.where(typical > 0, typical, 1.0), 1.0)
        off = np.arange(-radius, radius + 1.0)
        r = np.hypot(off[None, :], off[:, None])
        ring = np.rint(r).astype(int)
        outside = (r > inner) & (r <= radius)
        maps = np.where(outside, maps * ratio[:, :, ring], maps)
    nx, _ = to_pixel(prior.nodes_x, np.full(len(prior.nodes_x), np.median(prior.nodes_y)))
    _, ny = to_pixel(np.full(len(prior.nodes_y), np.median(prior.nodes_x)), prior.nodes_y)
    nx, ny = np.asarray(nx, float), np.asarray(ny, float)
    if nx[-1] < nx[0]:
        nx, maps = nx[::-1], maps[:, ::-1]
    if ny[-1] < ny[0]:
        ny, maps = ny[::-1], maps[::-1]
    return HaloShape(np.ascontiguousarray(maps), nx, ny)


def deposit_shaped(pixels, shape, x, y, cx, cy, radius, flux, profile, r_in, halo_shape, out):
    """:func:`~mavispm.measure.stars.stamp_kernel.deposit_radial` times the halo's shape.

    Each star adds ``flux * profile(r) * m(dx, dy)`` to the pixels of ``pixels`` outside
    its own stamp, ``m`` the :class:`HaloShape` modulation at the star's field position
    (bilinear between the nodes) and offset (bilinear between pixels; 1 beyond the maps).

    Parameters
    ----------
    pixels, shape, x, y, cx, cy, radius, flux, profile, r_in
        As :func:`~mavispm.measure.stars.stamp_kernel.deposit_radial` [pixel, electron,
        1/pixel].
    halo_shape : HaloShape
    out : ndarray of float64, shape (P,)
        Added to in place.

    Returns
    -------
    ndarray
        ``out``.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    nodes, w = halo_shape.weights(x, y)
    maps = halo_shape.maps.reshape(-1, *halo_shape.maps.shape[-2:])
    return deposit_radial(
        pixels, shape, x, y, cx, cy, radius, flux, profile, r_in, out, modulation=(maps, nodes, w)
    )
