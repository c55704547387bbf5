"""Cramér-Rao lower bound on star positions and fluxes (per star Fisher matrix).

For a star of flux ``F`` [electron] at ``(x0, y0)`` on a local sky ``s``
[electron/pixel] with read-noise variance ``rn2`` [electron^2] per pixel, the
pixel counts are (to an excellent approximation) Gaussian with mean
``m_i = F P_i(x0, y0) + s`` and variance ``v_i = m_i + rn2`` (Poisson + read
noise; the model, not the data, sets the variance). The Fisher matrix of the
parameters ``theta = (x0, y0, F, s)`` is

    I_kl = sum_i (d m_i / d theta_k)(d m_i / d theta_l) / v_i

(the small information in the variance itself is neglected, as in every
weighted-least-squares fitter), and the bound is ``sqrt(diag(I^-1))``.
"""

from __future__ import annotations

import numpy as np

from mavispm.measure.stars.variable_psf import StampGeometry, VariableEPSF

__all__ = [
    "BLEND_PARAMETERS",
    "PARAMETERS",
    "blend_crlb",
    "crlb",
    "fisher_matrix",
    "jacobian",
    "safe_inverse",
    "sky_plane_basis",
]

#: Parameter order of the Fisher matrices and covariances.
PARAMETERS = ("x", "y", "flux", "sky")

#: Parameter order of :func:`blend_crlb` (star 1, star 2, a common sky).
BLEND_PARAMETERS = ("x1", "y1", "flux1", "x2", "y2", "flux2", "sky")


def sky_plane_basis(size: int) -> np.ndarray:
    """Column and row offsets [pixel] of a ``size x size`` stamp from its centre, (2, size^2).

    Parameters
    ----------
    size : int
        Stamp side [pixel].

    Returns
    -------
    ndarray, shape (2, size**2)
        x offsets (fastest varying) and y offsets [pixel], row-major.
    """
    off = np.arange(size, dtype=float) - (size - 1) / 2
    return np.stack([np.tile(off, size), np.repeat(off, size)])


def jacobian(
    flux: np.ndarray,
    value: np.ndarray,
    dvx: np.ndarray,
    dvy: np.ndarray,
    sky_gradient: bool = False,
) -> np.ndarray:
    """Model derivatives d m / d (x0, y0, F, s[, s_x, s_y]) on stamps.

    Parameters
    ----------
    flux : ndarray, shape (N,)
        Star fluxes [electron].
    value, dvx, dvy : ndarray, shape (N, S, S)
        Unit-flux ePSF on the stamps and its position derivatives [1/pixel].
    sky_gradient : bool
        Also the derivatives by the slopes of a sky plane (:func:`sky_plane_basis`).

    Returns
    -------
    ndarray, shape (N, 4, S*S), or (N, 6, S*S) with ``sky_gradient``
    """
    n = value.shape[0]
    f = flux[:, None, None]
    jac = np.stack([f * dvx, f * dvy, value, np.ones_like(value)], axis=1).reshape(n, 4, -1)
    if not sky_gradient:
        return jac
    tilt = np.broadcast_to(sky_plane_basis(value.shape[-1]), (n, 2, jac.shape[-1]))
    return np.concatenate([jac, tilt], axis=1)


def fisher_matrix(jac: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Fisher (normal) matrices ``J W J^T`` of N stars.

    Parameters
    ----------
    jac : ndarray, shape (N, P, M)
        Derivatives of the model on M pixels.
    weight : ndarray, shape (N, M)
        Inverse variances [1/electron^2], zero for masked pixels.

    Returns
    -------
    ndarray, shape (N, P, P)
    """
    return np.einsum("nkm,nlm,nm->nkl", jac, jac, weight)


def safe_inverse(matrix: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Invert N small symmetric matrices, NaN where singular.

    Parameters
    ----------
    matrix : ndarray, shape (N, P, P)
    rcond : float
        Matrices with a reciprocal condition number (after diagonal scaling)
        below this are treated as singular.

    Returns
    -------
    inverse : ndarray, shape (N, P, P)
        NaN-filled for singular matrices.
    ok : ndarray of bool, shape (N,)
    """
    diag = np.einsum("nkk->nk", matrix)
    ok = np.all(np.isfinite(matrix), axis=(1, 2)) & np.all(diag > 0, axis=1)
    scale = np.where(ok[:, None], 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    scaled = matrix * scale[:, :, None] * scale[:, None, :]
    scaled[~ok] = np.eye(matrix.shape[1])
    # 2-norm condition number of a symmetric matrix from its eigenvalues (equal to
    # numpy's cond, which takes an SVD, at half the cost)
    eig = np.abs(np.linalg.eigvalsh(scaled))
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = eig.max(axis=1) / eig.min(axis=1)
    ok &= np.isfinite(cond) & (cond < 1.0 / rcond)
    scaled[~ok] = np.eye(matrix.shape[1])
    inv = np.linalg.inv(scaled) * scale[:, :, None] * scale[:, None, :]
    inv[~ok] = np.nan
    return inv, ok


def crlb(
    psf: VariableEPSF,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    sky: np.ndarray | float,
    read_noise_var: float,
    radius: int = 5,
    chunk: int = 4096,
) -> np.ndarray:
    """Cramér-Rao bound of isolated stars fitted for x, y, flux and local sky.

    Parameters
    ----------
    psf : VariableEPSF
        The true ePSF.
    x, y : ndarray, shape (N,)
        True positions [pixel].
    flux : ndarray, shape (N,)
        True fluxes [electron].
    sky : float or ndarray
        Sky level [electron/pixel].
    read_noise_var : float
        Read-noise variance per pixel of the (stacked) frame [electron^2].
    radius : int
        Stamp half-width [pixel], as used by the fitter.
    chunk : int
        Stars evaluated at once (memory ~ chunk x 10 kB).

    Returns
    -------
    ndarray, shape (N, 4)
        Bounds on (x [pixel], y [pixel], flux [electron], sky [electron]); NaN
        where the Fisher matrix is singular (zero flux).
    """
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    flux = np.broadcast_to(np.asarray(flux, dtype=float), x.shape)
    sky = np.broadcast_to(np.asarray(sky, dtype=float), x.shape)
    out = np.empty((len(x), 4))
    # in chunks: the stamps, Jacobians and weights of 1e5 stars at once took ~1 GB
    for lo in range(0, len(x), chunk):
        sl = slice(lo, lo + chunk)
        geom = StampGeometry(
            np.rint(x[sl]).astype(np.intp), np.rint(y[sl]).astype(np.intp), int(radius)
        )
        value, dvx, dvy = psf.evaluate(x[sl], y[sl], geom)
        jac = jacobian(flux[sl], value, dvx, dvy)
        model = flux[sl, None] * value.reshape(len(value), -1) + sky[sl, None]
        var = np.maximum(model, 0.0) + read_noise_var
        cov, _ = safe_inverse(fisher_matrix(jac, 1.0 / var))
        out[sl] = np.sqrt(np.einsum("nkk->nk", cov))
    return out


def blend_crlb(
    psf: VariableEPSF,
    x1: np.ndarray,
    y1: np.ndarray,
    flux1: np.ndarray,
    x2: np.ndarray,
    y2: np.ndarray,
    flux2: np.ndarray,
    sky: np.ndarray | float,
    read_noise_var: float,
    radius: int = 5,
    chunk: int = 2048,
) -> np.ndarray:
    """Cramér-Rao bound of a two-star blend, both positions and fluxes and the sky free.

    The pixels are a square stamp centred on the pair's midpoint, its half-width
    ``radius`` plus half the largest separation (rounded up), so that it holds both
    stars' stamps of ``radius``. A bound for any unbiased fitter of the pair; a star with
    more neighbours can only do worse (more free parameters).

    Parameters
    ----------
    psf : VariableEPSF
        The true ePSF.
    x1, y1, flux1, x2, y2, flux2 : ndarray, shape (N,)
        True positions [pixel] and fluxes [electron] of the two stars of each pair.
    sky : float or ndarray
        Sky level [electron/pixel].
    read_noise_var : float
        Read-noise variance per pixel [electron^2].
    radius : int
        Stamp half-width of one star [pixel].
    chunk : int
        Pairs evaluated at once.

    Returns
    -------
    ndarray, shape (N, 7)
        Bounds on :data:`BLEND_PARAMETERS` (pixel, electron); NaN where the Fisher
        matrix is singular (a zero flux, or the two stars at one position).
    """
    x1, y1, x2, y2 = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (x1, y1, x2, y2))
    f1 = np.broadcast_to(np.asarray(flux1, dtype=float), x1.shape)
    f2 = np.broadcast_to(np.asarray(flux2, dtype=float), x1.shape)
    sky = np.broadcast_to(np.asarray(sky, dtype=float), x1.shape)
    out = np.empty((len(x1), len(BLEND_PARAMETERS)))
    for lo in range(0, len(x1), chunk):
        sl = slice(lo, lo + chunk)
        half = 0.5 * np.hypot(x2[sl] - x1[sl], y2[sl] - y1[sl])
        geom = StampGeometry(
            np.rint(0.5 * (x1[sl] + x2[sl])).astype(np.intp),
            np.rint(0.5 * (y1[sl] + y2[sl])).astype(np.intp),
            int(radius) + int(np.ceil(half.max(initial=0.0))),
        )
        v1, dx1, dy1 = psf.evaluate(x1[sl], y1[sl], geom)
        v2, dx2, dy2 = psf.evaluate(x2[sl], y2[sl], geom)
        a = f1[sl, None, None]
        b = f2[sl, None, None]
        n = len(v1)
        jac = np.stack(
            [a * dx1, a * dy1, v1, b * dx2, b * dy2, v2, np.ones_like(v1)], axis=1
        ).reshape(n, len(BLEND_PARAMETERS), -1)
        model = (a * v1 + b * v2).reshape(n, -1) + sky[sl, None]
        var = np.maximum(model, 0.0) + read_noise_var
        cov, _ = safe_inverse(fisher_matrix(jac, 1.0 / var))
        out[sl] = np.sqrt(np.einsum("nkk->nk", cov))
    return out
