"""PSF model from AO PSF reconstruction (PSF-R) plus an empirical correction.

An AO instrument reconstructs the high-order (HO) part of its PSF from the
wavefront-sensor telemetry (PSF-R; the MAVISIM paper, section 4.2). The
``measure`` stage may take such a prior: the ``psfgrid`` product of the optics
stage (docs/formats.md), a field-variable grid of HO PSFs. It is *not* the PSF
of the frame:

* the prior holds the HO part only: no tip-tilt residual (the realised TT kernel of
  the stack), no charge diffusion or vibration, no image motion, no intra-pixel
  response. These are all left to the empirical correction below;
* its width is wrong by ``width_error`` (PSF-R papers report Strehl / FWHM errors of a
  few per cent): the HO PSFs are stretched radially by ``1 + width_error``
  (:func:`stretch_psf`) before use; and its Strehl ratio by ``strehl_error``
  (:func:`blur_core`: that fraction of the light moved into a blurred copy);
* the measurement never reads the frame's rendered per-star PSF, the optics'
  tip-tilt map, the truth positions or fluxes.

The empirical correction is the part that the frame's own bright stars measure: at
each node of a ``grid x grid`` mesh a Gaussian convolution kernel of covariance
``C = [[cxx, cxy], [cxy, cyy]]`` [mas^2] (the TT + blur kernel of the stack, less
the prior's width error; ``C`` need not be positive definite), fitted to the node's
PSF stars (:func:`fit_kernel`). The model ePSF of a field position is then the
pixel-integrated ``prior (x) Gaussian(C)``, sampled ``oversampling`` times finer than
the detector pixels (:func:`model_epsf`): noise-free (the only parameters taken from
the frame are the three of ``C`` per node) and centred on the optical axis by
construction, so every epoch shares the same centre convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage, optimize
from threadpoolctl import threadpool_limits

from mavispm.core.errors import InputError
from mavispm.core.products import open_product
from mavispm.measure.stars.chunk_pool import ChunkPool, resolve_threads
from mavispm.measure.stars.variable_psf import (
    StampGeometry,
    VariableEPSF,
    constant_epsf,
    gridded_epsf,
)

__all__ = [
    "PSFRPrior",
    "check_prior",
    "fit_kernel",
    "model_epsf",
    "model_transforms",
    "read_prior",
    "stretch_psf",
]


@dataclass(frozen=True)
class PSFRPrior:
    """The HO PSF grid an observer's PSF-R delivers (already degraded).

    Parameters
    ----------
    cube : ndarray, shape (ny, nx, n, n)
        HO PSFs at the nodes, each summing to 1, optical axis at ``((n-1)/2, (n-1)/2)``.
    nodes_x, nodes_y : ndarray
        Node positions [arcsec], field frame.
    pixel_scale : float
        Sampling of the PSFs [mas].
    path : Path or None
        The product the grid came from.
    """

    cube: np.ndarray
    nodes_x: np.ndarray
    nodes_y: np.ndarray
    pixel_scale: float
    path: Path | None = None

    def psf_at(self, x: float, y: float) -> np.ndarray:
        """Bilinear mix of the node PSFs at field position ``(x, y)`` [arcsec] (clipped)."""
        ix, wx = _axis_weight(self.nodes_x, x)
        iy, wy = _axis_weight(self.nodes_y, y)
        out = np.zeros(self.cube.shape[2:])
        for jy, ay in ((iy, 1 - wy), (iy + 1, wy)):
            for jx, ax in ((ix, 1 - wx), (ix + 1, wx)):
                if ay * ax > 0:
                    out += (
                        ay
                        * ax
                        * self.cube[min(jy, len(self.nodes_y) - 1), min(jx, len(self.nodes_x) - 1)]
                    )
        return out


def _axis_weight(nodes: np.ndarray, v: float) -> tuple[int, float]:
    if len(nodes) == 1:
        return 0, 0.0
    v = float(np.clip(v, nodes[0], nodes[-1]))
    i = int(np.clip(np.searchsorted(nodes, v, side="right") - 1, 0, len(nodes) - 2))
    return i, (v - nodes[i]) / (nodes[i + 1] - nodes[i])


def stretch_psf(psf: np.ndarray, factor: float) -> np.ndarray:
    """Stretch a centred PSF radially by ``factor`` (FWHM x factor), renormalised to 1.

    Parameters
    ----------
    psf : ndarray, shape (n, n)
        PSF with its centre at ``((n-1)/2, (n-1)/2)``.
    factor : float
        Width factor (1: unchanged).

    Returns
    -------
    ndarray
        ``psf(r / factor)`` sampled on the same grid (cubic spline), summing to 1.
    """
    if factor == 1.0:
        return psf
    n = psf.shape[0]
    c = (n - 1) / 2.0
    yy, xx = np.mgrid[:n, :n]
    coords = np.array([c + (yy - c) / factor, c + (xx - c) / factor])
    out = ndimage.map_coordinates(psf, coords, order=3, mode="constant", cval=0.0)
    out = np.clip(out, 0.0, None)
    return out / out.sum()


def blur_core(psf: np.ndarray, fraction: float, sigma_pix: float) -> np.ndarray:
    """Move ``fraction`` of a PSF's light into a blurred copy (a Strehl error).

    Parameters
    ----------
    psf : ndarray (n, n)
        Centred PSF summing to 1.
    fraction : float
        Light moved (the Strehl ratio drops by about this fraction).
    sigma_pix : float
        Gaussian blur of the moved light [prior pixels].

    Returns
    -------
    ndarray
        ``(1 - fraction) psf + fraction psf (x) G(sigma)``, summing to 1.
    """
    if fraction == 0.0:
        return psf
    out = (1.0 - fraction) * psf + fraction * ndimage.gaussian_filter(
        psf, sigma_pix, mode="constant"
    )
    return out / out.sum()


#: Blur [mas] of the light moved by ``strehl_error`` (about the diffraction core width
#: at 550 nm, lambda / D = 14 mas).
STREHL_ERROR_BLUR = 15.0


def read_prior(
    path,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    width_error: float,
    strehl_error: float = 0.0,
) -> PSFRPrior:
    """Read the PSF-R prior from a ``psfgrid`` product: the nodes that cover the frame.

    Parameters
    ----------
    path : str or os.PathLike
        The ``psfgrid`` product (``mavispm simulate optics``, or a workflow's optics node).
    x_range, y_range : tuple of float
        Field extent of the frame [arcsec]; the nodes bracketing it are read.
    width_error : float
        Fractional width error of the reconstruction (the PSFs are stretched by
        ``1 + width_error``).
    strehl_error : float
        Fraction of each PSF's light moved into a copy blurred by
        :data:`STREHL_ERROR_BLUR` (:func:`blur_core`): a Strehl error of the
        reconstruction that no stretch and Gaussian kernel undo exactly.

    Returns
    -------
    PSFRPrior

    Raises
    ------
    InputError
        A file that is not a ``psfgrid`` product, a missing array or attribute, a cube
        of the wrong shape or with non-finite or negative values (the message names
        the file and the key).
    """
    path = Path(path)
    with open_product(path, "psfgrid") as f:
        nx, ny, scale = _header(f, path)
        jx = _bracket(nx, x_range)
        jy = _bracket(ny, y_range)
        cube = np.asarray(f["cube"][jy[0] : jy[1] + 1, jx[0] : jx[1] + 1], float)
    if not np.all(np.isfinite(cube)) or np.any(cube < -1e-6 * cube.max()):
        raise InputError("PSF-R prior: 'cube' holds NaN, infinite or negative values", path=path)
    sums = cube.sum(axis=(2, 3))
    if np.any(sums <= 0):
        raise InputError("PSF-R prior: a PSF of 'cube' has no positive flux", path=path)
    factor = 1.0 + float(width_error)
    blur = STREHL_ERROR_BLUR / scale
    cube = np.array(
        [
            [blur_core(stretch_psf(p / s, factor), strehl_error, blur) for p, s in zip(row, srow)]
            for row, srow in zip(cube, sums)
        ]
    )
    return PSFRPrior(cube, nx[jx[0] : jx[1] + 1], ny[jy[0] : jy[1] + 1], scale, path)


def _header(f, path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """Validated node positions [arcsec] and sampling [mas] of an open ``psfgrid`` product."""
    for key in ("cube", "nodes_x", "nodes_y"):
        if key not in f:
            raise InputError(f"PSF-R prior: array '{key}' missing", path=path)
    if "pixel_scale" not in f.attrs:
        raise InputError("PSF-R prior: attribute 'pixel_scale' missing", path=path)
    try:
        nx = np.asarray(f["nodes_x"], float).ravel()
        ny = np.asarray(f["nodes_y"], float).ravel()
        scale = float(np.asarray(f.attrs["pixel_scale"]))
    except (TypeError, ValueError):
        raise InputError(
            "PSF-R prior: 'nodes_x', 'nodes_y', 'pixel_scale' must be numbers", path=path
        ) from None
    shape = f["cube"].shape
    if (
        len(shape) != 4
        or shape[:2] != (ny.size, nx.size)
        or shape[2] != shape[3]
        or shape[2] % 2 == 0
    ):
        raise InputError(
            f"PSF-R prior: 'cube' has shape {shape}; expected (len(nodes_y), "
            "len(nodes_x), n, n) with n odd",
            path=path,
        )
    if not (np.all(np.isfinite(nx)) and np.all(np.isfinite(ny))):
        raise InputError("PSF-R prior: 'nodes_x', 'nodes_y' hold NaN or infinite values", path=path)
    if not (np.all(np.diff(nx) > 0) and np.all(np.diff(ny) > 0)):
        raise InputError("PSF-R prior: 'nodes_x', 'nodes_y' must increase", path=path)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"PSF-R prior: 'pixel_scale' must be > 0, got {scale}", path=path)
    return nx, ny, scale


def check_prior(path) -> None:
    """Refuse a PSF-R prior that is not a usable ``psfgrid`` product (before any work).

    Parameters
    ----------
    path : str or os.PathLike

    Raises
    ------
    InputError
        Naming the file and the key (see :func:`read_prior`).
    """
    path = Path(path)
    with open_product(path, "psfgrid") as f:
        _header(f, path)


def _bracket(nodes: np.ndarray, span: tuple[float, float]) -> tuple[int, int]:
    lo = int(np.clip(np.searchsorted(nodes, span[0], side="right") - 1, 0, len(nodes) - 1))
    hi = int(np.clip(np.searchsorted(nodes, span[1], side="left"), 0, len(nodes) - 1))
    return lo, max(lo, hi)


@dataclass
class NodeTransform:
    """The optical transfer function of the prior at one field position.

    Parameters
    ----------
    otf : ndarray (m, m) complex
        Transform of the centred HO PSF at the frequencies ``freq`` (those where it
        is not negligible: the optics' band limit).
    freq : ndarray (m,)
        Frequencies [1/mas].
    n : int
        Length of the full transform (its normalisation).
    """

    otf: np.ndarray
    freq: np.ndarray
    n: int

    @classmethod
    def of(cls, psf: np.ndarray, pixel_scale: float, tol: float = 1e-5) -> NodeTransform:
        """Transform of a centred PSF sampled every ``pixel_scale`` mas.

        Frequencies at which the transform stays below ``tol`` of its zero frequency
        along both axes (beyond the telescope's cut-off ``D / lambda``) are dropped:
        113 of 427 frequencies remain for the MAVIS grid, and the model ePSF changes by
        2e-8 of its peak.
        """
        n = psf.shape[0]
        otf = np.fft.fft2(np.fft.ifftshift(psf))
        amp = np.abs(otf)
        keep = np.maximum(amp.max(axis=0), amp.max(axis=1)) > tol * amp[0, 0]
        idx = np.flatnonzero(keep)
        freq = np.fft.fftfreq(n, d=pixel_scale)
        return cls(otf[np.ix_(idx, idx)], freq[idx], n)


def model_epsf(
    node: NodeTransform,
    cov: np.ndarray,
    detector_scale: float,
    size: int,
    oversampling: int,
) -> np.ndarray:
    """Pixel-integrated ``stretched prior (x) Gaussian(cov)`` on the oversampled ePSF grid.

    The spectrum ``OTF(f) exp(-2 pi^2 g^T C g) sinc(s g_x) sinc(s g_y)``, ``g = f / k``
    (``s`` the detector pixel, ``k`` the stretch: the prior stretched radially by
    ``k`` has the spectrum ``OTF(k g)`` at frequency ``g``), is summed directly
    (matrix DFT) at the ePSF samples, offsets ``j s / oversampling`` from the optical
    axis: exact for any ratio of the prior's sampling to the detector's.

    Parameters
    ----------
    node : NodeTransform
        The prior's transform at the field position.
    cov : array_like, shape (3,) or (4,)
        ``(cxx, cyy, cxy)`` [mas^2] of the correction kernel, optionally followed by
        the stretch ``k`` of the prior (default 1).
    detector_scale : float
        Detector pixel [mas].
    size : int
        ePSF footprint [pixel] (odd).
    oversampling : int

    Returns
    -------
    ndarray, shape (size * oversampling + 1,) * 2
        The ePSF (photutils convention), normalised so that its samples at integer
        pixel offsets sum to 1 over the footprint.
    """
    cxx, cyy, cxy = (float(v) for v in cov[:3])
    stretch = float(cov[3]) if len(cov) > 3 else 1.0
    if not 0.5 < stretch < 2.0:
        raise InputError(f"the PSF-R stretch diverged ({stretch}); expected 0.5-2")
    f = node.freq / stretch
    fx, fy = f[None, :], f[:, None]
    gauss = np.exp(-2 * np.pi**2 * (cxx * fx**2 + cyy * fy**2 + 2 * cxy * fx * fy))
    box = np.sinc(detector_scale * f)
    spec = node.otf * np.minimum(gauss, 1e6) * box[None, :] * box[:, None]
    n_os = size * oversampling + 1
    p = (np.arange(n_os) - (n_os - 1) / 2.0) * detector_scale / oversampling
    a = np.exp(2j * np.pi * np.outer(p, f)) / node.n
    epsf = np.real(a @ spec @ a.T)
    total = epsf[::oversampling, ::oversampling].sum()
    if not np.isfinite(total) or total <= 0:
        raise InputError("the PSF-R model ePSF has no positive flux (correction kernel diverged)")
    return epsf / total


#: Prior width of the fitted stretch of the PSF-R prior (1-sigma, fractional): PSF-R
#: reconstructions are good to a few per cent in width; the stretch and a round kernel
#: are degenerate for a Gaussian prior, and this prior settles the split there.
STRETCH_PRIOR = 0.05


def _node_stamps(image, x, y, radius, bad):
    ny, nx = image.shape
    cx, cy = np.rint(x).astype(int), np.rint(y).astype(int)
    off = np.arange(-radius, radius + 1)
    rows = cy[:, None] + off
    cols = cx[:, None] + off
    inside = ((rows >= 0) & (rows < ny))[:, :, None] & ((cols >= 0) & (cols < nx))[:, None, :]
    rc, cc = np.clip(rows, 0, ny - 1), np.clip(cols, 0, nx - 1)
    data = image[rc[:, :, None], cc[:, None, :]]
    valid = inside & ~bad[rc[:, :, None], cc[:, None, :]] & np.isfinite(data)
    return StampGeometry(cx, cy, radius), np.where(valid, data, 0.0), valid


def fit_kernel(
    transforms: list[NodeTransform],
    group: np.ndarray,
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    bad: np.ndarray,
    noise_floor: float,
    detector_scale: float,
    oversampling: int,
    radius: int,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Correction kernel ``(cxx, cyy, cxy)`` [mas^2] common to a set of PSF stars.

    Minimises the weighted residuals of the stars' stamps (half-width ``radius``),
    each star modelled as the prior at its nearest model node (``transforms[group]``)
    convolved with the trial kernel; each star's flux and sky plane (level, two
    slopes) are solved linearly for every trial kernel, its position held at ``x, y``
    (a centro-symmetric kernel does not move a star; the positions come from a fit
    with the current model).

    Parameters
    ----------
    transforms : list of NodeTransform
        The prior at the model nodes.
    group : ndarray of int
        Model node of each star (index into ``transforms``).
    image : ndarray
        Sky-subtracted frame [electron].
    x, y : ndarray
        PSF-star positions [pixel].
    bad : ndarray of bool
    noise_floor : float
        Background variance per pixel [electron^2].
    detector_scale : float
        Detector pixel [mas].
    oversampling : int
    radius : int
        Fit stamp half-width [pixel].
    start : array_like (4,), optional
        Starting kernel [mas^2] and stretch (default ``(s/3)^2`` on the diagonal, 1).

    Returns
    -------
    cov : ndarray (4,)
        The kernel ``(cxx, cyy, cxy)`` [mas^2] and the stretch of the prior.
    chi2 : float
        Reduced chi^2 of the stamps at the solution.
    """
    geom, data, valid = _node_stamps(image, x, y, radius, bad)
    off = np.arange(-radius, radius + 1, dtype=float)
    px, py = np.meshgrid(off, off)
    var = np.abs(data) + noise_floor
    sw = np.where(valid, 1.0 / np.sqrt(var), 0.0)
    size = 2 * radius + 3
    scale = detector_scale**2
    groups = [(g, np.flatnonzero(group == g)) for g in np.unique(group)]
    fixed = (
        np.stack([np.broadcast_to(b, data.shape) for b in (np.ones_like(px), px, py)], axis=-1)
        * sw[..., None]
    )
    b = (data * sw).reshape(len(x), -1)

    def residuals(p):
        model = np.empty(data.shape)
        par = np.concatenate([p[:3] * scale, [1.0 + p[3]]])
        for g, idx in groups:
            epsf = model_epsf(transforms[g], par, detector_scale, size, oversampling)
            sub = StampGeometry(geom.cx[idx], geom.cy[idx], radius)
            model[idx] = constant_epsf(epsf, oversampling).evaluate(
                x[idx], y[idx], sub, derivatives=False
            )
        a = np.concatenate([(model * sw)[..., None], fixed], axis=-1).reshape(len(x), -1, 4)
        ata = np.einsum("nki,nkj->nij", a, a) + 1e-12 * np.eye(4)
        atb = np.einsum("nki,nk->ni", a, b)
        coef = np.linalg.solve(ata, atb[..., None])[..., 0]
        res = (b - np.einsum("nki,ni->nk", a, coef)).ravel()
        return np.append(res, p[3] / STRETCH_PRIOR)

    if start is None:
        p0 = np.array([1 / 9, 1 / 9, 0.0, 0.0])
    else:
        p0 = np.concatenate([np.asarray(start[:3], float) / scale, [float(start[3]) - 1.0]])
    sol = optimize.least_squares(residuals, p0, x_scale=0.05, diff_step=1e-3, max_nfev=50)
    dof = max(int(valid.sum()) - 4 * len(x) - 4, 1)
    out = np.concatenate([sol.x[:3] * scale, [1.0 + sol.x[3]]])
    return out, float(np.sum(sol.fun[:-1] ** 2) / dof)


def model_nodes(
    prior: PSFRPrior, correction_x: np.ndarray, correction_y: np.ndarray, to_pixel
) -> tuple[np.ndarray, np.ndarray]:
    """Nodes [pixel] of the model ePSF grid: the prior's, or the correction grid's.

    The prior is noise-free, so its field variation is kept at its own resolution
    (the MAVIS grid: 3" spacing, Strehl 0.30 at the centre and 0.04 in the corners);
    a static prior (one node) takes the correction grid.

    Parameters
    ----------
    prior : PSFRPrior
    correction_x, correction_y : ndarray
        Correction-kernel node columns / rows [pixel].
    to_pixel : callable
        Field position [arcsec] -> pixel.

    Returns
    -------
    gx, gy : ndarray
        Increasing node columns / rows [pixel].
    """
    if len(prior.nodes_x) < 2 or len(prior.nodes_y) < 2:
        return correction_x, correction_y
    gx, _ = to_pixel(prior.nodes_x, np.zeros(len(prior.nodes_x)))
    _, gy = to_pixel(np.zeros(len(prior.nodes_y)), prior.nodes_y)
    return np.asarray(gx, float), np.asarray(gy, float)


def model_transforms(
    prior: PSFRPrior, correction_x: np.ndarray, correction_y: np.ndarray, to_arcsec, to_pixel
) -> list[NodeTransform]:
    """The prior's transforms at the model nodes (:func:`model_nodes`), row-major.

    Parameters
    ----------
    prior : PSFRPrior
    correction_x, correction_y : ndarray
        Correction node columns / rows [pixel].
    to_arcsec, to_pixel : callable
        Pixel <-> field position [arcsec].

    Returns
    -------
    list of NodeTransform
    """
    gx, gy = model_nodes(prior, correction_x, correction_y, to_pixel)
    mx, my = np.meshgrid(gx, gy)
    ax, ay = to_arcsec(mx.ravel(), my.ravel())
    return [
        NodeTransform.of(prior.psf_at(float(a), float(b)), prior.pixel_scale)
        for a, b in zip(ax, ay)
    ]


def interpolate_kernels(
    kernels: np.ndarray, cx: np.ndarray, cy: np.ndarray, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Bilinear interpolation (clipped at the edge nodes) of per-node kernels.

    Parameters
    ----------
    kernels : ndarray (len(cy) * len(cx), C)
        Kernels on the correction grid, row-major [mas^2].
    cx, cy : ndarray
        Correction node columns / rows [pixel].
    x, y : ndarray
        Positions [pixel].

    Returns
    -------
    ndarray (len(x), 3)
    """
    out = np.empty((len(x), kernels.shape[1]))
    grid = kernels.reshape(len(cy), len(cx), kernels.shape[1])
    for n, (xi, yi) in enumerate(zip(np.asarray(x, float), np.asarray(y, float))):
        i, tx = _axis_weight(np.asarray(cx, float), xi)
        j, ty = _axis_weight(np.asarray(cy, float), yi)
        i1, j1 = min(i + 1, len(cx) - 1), min(j + 1, len(cy) - 1)
        out[n] = (1 - ty) * ((1 - tx) * grid[j, i] + tx * grid[j, i1]) + ty * (
            (1 - tx) * grid[j1, i] + tx * grid[j1, i1]
        )
    return out


def build_psfr_epsf(
    prior: PSFRPrior,
    image: np.ndarray,
    fit_positions,
    x_all: np.ndarray,
    y_all: np.ndarray,
    members: list[np.ndarray],
    correction_x: np.ndarray,
    correction_y: np.ndarray,
    to_arcsec,
    to_pixel,
    bad: np.ndarray,
    noise_floor: float,
    detector_scale: float,
    size: int,
    oversampling: int,
    radius: int,
    rounds: int = 2,
    start: np.ndarray | None = None,
    transforms: list[NodeTransform] | None = None,
    threads: int = 1,
) -> tuple[VariableEPSF, np.ndarray]:
    """The PSF-R model with its fitted correction kernels, as a gridded ePSF.

    Parameters
    ----------
    prior : PSFRPrior
    image : ndarray
        Sky-subtracted frame [electron].
    fit_positions : callable
        ``fit_positions(psf, index) -> (x, y)``: the PSF stars' positions [pixel] fitted
        with a model (the batched fitter).
    x_all, y_all : ndarray
        Start positions of all stars [pixel].
    members : list of ndarray
        PSF-star indices of each correction node (row-major over ``correction_y``,
        ``correction_x``).
    correction_x, correction_y : ndarray
        Correction node columns / rows [pixel].
    to_arcsec, to_pixel : callable
        Pixel <-> field position [arcsec].
    bad : ndarray of bool
    noise_floor : float
    detector_scale : float
        [mas]
    size, oversampling, radius : int
        ePSF footprint [pixel], oversampling, fit stamp half-width [pixel].
    rounds : int
        Kernel fit / position refit rounds.
    start : ndarray (K, 4), optional
        Starting kernels [mas^2] (e.g. the full set's, for the half sets).
    transforms : list of NodeTransform, optional
        The prior's transforms at the model nodes (:func:`model_transforms`; computed
        when not given: a build and its half sets share them).
    threads : int
        Threads of the model nodes' ePSFs and the correction nodes' kernel fits, each
        node on its own (0: every core; :mod:`~mavispm.measure.stars.chunk_pool`): the
        same results on any number.

    Returns
    -------
    psf : VariableEPSF
        The model ePSF on the model grid (:func:`model_nodes`).
    kernels : ndarray (K, 4)
        The fitted corrections on the correction grid: kernel ``(cxx, cyy, cxy)``
        [mas^2] and stretch of the prior.
    """
    gx, gy = model_nodes(prior, correction_x, correction_y, to_pixel)
    mx, my = np.meshgrid(gx, gy)
    mx, my = mx.ravel(), my.ravel()
    if transforms is None:
        transforms = model_transforms(prior, correction_x, correction_y, to_arcsec, to_pixel)
    k0 = [(detector_scale / 3) ** 2, (detector_scale / 3) ** 2, 0.0, 1.0]
    kernels = np.tile(k0, (len(members), 1)) if start is None else np.array(start, float)
    px, py = x_all.copy(), y_all.copy()

    pool = ChunkPool(resolve_threads(threads))

    def assemble():
        at_nodes = interpolate_kernels(kernels, correction_x, correction_y, mx, my)
        epsfs = np.array(
            pool.map(
                lambda tk: model_epsf(tk[0], tk[1], detector_scale, size, oversampling),
                list(zip(transforms, at_nodes)),
            )
        )
        if len(epsfs) == 1:
            return constant_epsf(epsfs[0], oversampling)
        return gridded_epsf(epsfs, gx, gy, oversampling)

    used = np.unique(np.concatenate(members))
    # the kernel of a correction node is fitted with the prior at its PSF stars' mean
    # position (one model per trial kernel; the prior's variation across the stars is
    # centro-symmetric and moves no star)
    local = []
    for m in members:
        a, b = to_arcsec(np.array([np.mean(x_all[m])]), np.array([np.mean(y_all[m])]))
        local.append(NodeTransform.of(prior.psf_at(float(a[0]), float(b[0])), prior.pixel_scale))

    def node_kernel(k):
        m = members[k]
        return fit_kernel(
            [local[k]],
            np.zeros(len(m), int),
            image,
            px[m],
            py[m],
            bad,
            noise_floor,
            detector_scale,
            oversampling,
            radius,
            start=kernels[k],
        )[0]

    # small products: BLAS threads cost 50x (the limit is the process's, all threads')
    with threadpool_limits(limits=1, user_api="blas"), pool:
        for _ in range(int(rounds)):
            fx, fy = fit_positions(assemble(), used)
            px[used], py[used] = fx, fy
            # each node's kernel from its own stars and start: independent
            kernels[:] = pool.map(node_kernel, range(len(members)))
        return assemble(), kernels
