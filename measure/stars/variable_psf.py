"""Field-variable effective PSF (ePSF): basis ePSFs mixed per star.

An ePSF is the pixel-integrated PSF sampled on a grid ``oversampling`` times
finer than the detector pixels (photutils convention: the ePSF value at an
offset ``(dx, dy)`` pixels from the star centre is the fraction of the flux
falling in a pixel centred there, so sampling at integer pixel offsets sums
to 1).

Field variability is represented by ``K`` *basis* ePSFs ``B_k`` and per-star
mixing weights ``w_k(x, y)``: the ePSF of a star at ``(x, y)`` is
``sum_k w_k(x, y) B_k``. Three variations share this representation:

* ``constant``: one ePSF (``K = 1``, ``w = 1``).
* ``grid``: ePSFs at the nodes of a regular grid (photutils
  ``GriddedPSFModel`` style), mixed by bilinear interpolation (4 non-zero weights).
* ``polynomial``: DAOPhot-style variable PSF, ``B_k`` are the coefficients of
  a polynomial of order ``p`` in the normalised field position (``p = 3`` is the
  cubically variable PSF), ``w_k`` the monomials.

Evaluation uses cubic B-spline interpolation of the oversampled grid
(prefiltered once), which is C2-continuous, so the position derivatives used by
the fitters are smooth. Stamps are evaluated by a compiled kernel
(:mod:`mavispm.measure.stars.stamp_kernel`); :meth:`VariableEPSF.evaluate_numpy`
is the numpy reference.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mavispm.core.errors import InputError
from mavispm.measure.stars.stamp_kernel import evaluate_stamps

__all__ = [
    "StampGeometry",
    "VariableEPSF",
    "constant_epsf",
    "gridded_epsf",
    "polynomial_epsf",
    "sample_epsf",
]

#: Zero padding (oversampled samples) added around each basis ePSF so that
#: stamps reaching beyond the ePSF read zeros.
_PAD = 4


def _bspline_weights(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline weights and their derivatives for taps at -1, 0, 1, 2.

    Parameters
    ----------
    t : ndarray
        Fractional position in [0, 1) between taps 0 and 1.

    Returns
    -------
    w, dw : ndarray, shape ``t.shape + (4,)``
        Weights and derivatives d w / d t.
    """
    t = np.asarray(t, dtype=float)
    s = 1.0 - t
    w = np.stack(
        [
            s**3 / 6.0,
            (3 * t**3 - 6 * t**2 + 4) / 6.0,
            (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6.0,
            t**3 / 6.0,
        ],
        axis=-1,
    )
    dw = np.stack(
        [-(s**2) / 2.0, (3 * t**2 - 4 * t) / 2.0, (-3 * t**2 + 2 * t + 1) / 2.0, t**2 / 2.0],
        axis=-1,
    )
    return w, dw


def _check_basis(basis: np.ndarray, oversampling: int) -> np.ndarray:
    basis = np.asarray(basis, dtype=float)
    if basis.ndim == 2:
        basis = basis[None]
    if basis.ndim != 3 or basis.shape[1] < 4 or basis.shape[2] < 4:
        raise InputError(
            f"ePSF basis must have shape (K, ny, nx) with ny, nx >= 4, got {basis.shape}"
        )
    if not np.all(np.isfinite(basis)):
        raise InputError("ePSF contains NaN or infinite values")
    if int(oversampling) < 1:
        raise InputError(f"oversampling must be a positive integer, got {oversampling}")
    return basis


@dataclass(frozen=True)
class StampGeometry:
    """Pixel stamps of ``N`` stars: integer centres and radius.

    Parameters
    ----------
    cx, cy : ndarray of int, shape (N,)
        Stamp centre pixels (column, row).
    radius : int
        Stamp half-width in pixels; stamps are ``(2 radius + 1)`` square.
    """

    cx: np.ndarray
    cy: np.ndarray
    radius: int

    @property
    def size(self) -> int:
        """Stamp side [pixel], ``2 radius + 1``."""
        return 2 * self.radius + 1

    def columns(self) -> np.ndarray:
        """Pixel columns of each stamp, shape (N, S)."""
        off = np.arange(-self.radius, self.radius + 1)
        return self.cx[:, None] + off[None, :]

    def rows(self) -> np.ndarray:
        """Pixel rows of each stamp, shape (N, S)."""
        off = np.arange(-self.radius, self.radius + 1)
        return self.cy[:, None] + off[None, :]


class VariableEPSF:
    """A field-variable ePSF evaluated on pixel stamps with position derivatives.

    Parameters
    ----------
    basis : ndarray, shape (K, ny, nx) or (ny, nx)
        Basis ePSFs on the oversampled grid; the star centre is at the array
        centre ``((nx - 1) / 2, (ny - 1) / 2)``.
    oversampling : int
        Oversampling factor of the ePSF grid relative to detector pixels.
    mixing : callable
        ``mixing(x, y) -> (index (N, M) int, weight (N, M) float)``: which basis
        ePSFs contribute to a star at pixel position ``(x, y)`` and how much.
    kind : str
        ``"constant"``, ``"grid"`` or ``"polynomial"`` (for reports).
    meta : dict, optional
        Description of the variation (grid nodes, polynomial scaling).
    """

    def __init__(
        self,
        basis: np.ndarray,
        oversampling: int,
        mixing: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
        kind: str = "constant",
        meta: dict | None = None,
    ):
        basis = _check_basis(basis, oversampling)
        self.basis = basis
        self.oversampling = int(oversampling)
        self.kind = kind
        self.meta = dict(meta or {})
        self._mixing = mixing
        padded = np.pad(basis, ((0, 0), (_PAD, _PAD), (_PAD, _PAD)))
        # cubic B-spline coefficients; the padded border keeps zeros outside
        self._coef = np.stack(
            [ndimage.spline_filter(b, order=3, mode="grid-constant") for b in padded]
        )
        self._coef[:, :2, :] = 0.0
        self._coef[:, -2:, :] = 0.0
        self._coef[:, :, :2] = 0.0
        self._coef[:, :, -2:] = 0.0
        self._ny, self._nx = padded.shape[1:]
        self._margin = 0
        self._coef_pad = self._coef.astype(np.float32)
        self._centre = ((self._nx - 1) / 2.0, (self._ny - 1) / 2.0)

    # ------------------------------------------------------------------ info
    @property
    def n_basis(self) -> int:
        """Number of basis ePSF images."""
        return self.basis.shape[0]

    @property
    def radius_pix(self) -> float:
        """Half-size of the ePSF footprint in detector pixels."""
        return (min(self.basis.shape[1:]) - 1) / 2.0 / self.oversampling

    def mixing(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Basis indices and weights for stars at pixel positions ``(x, y)``.

        Parameters
        ----------
        x, y : array_like
            Star positions [pixel].

        Returns
        -------
        idx : ndarray of int, shape (N, K)
            Basis images used by each star.
        weights : ndarray, shape (N, K)
            Their weights; a star's ePSF is ``sum_k weights[:, k] * basis[idx[:, k]]``.
        """
        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        return self._mixing(x, y)

    def epsf_at(self, x: float, y: float) -> np.ndarray:
        """The oversampled ePSF image of a star at pixel position ``(x, y)``.

        Parameters
        ----------
        x, y : float
            Star position [pixel].

        Returns
        -------
        ndarray
            The ePSF image at the ePSF's oversampling.
        """
        idx, w = self.mixing([x], [y])
        return np.tensordot(w[0], self.basis[idx[0]], axes=1)

    # ------------------------------------------------------------ evaluation
    def _stars_and_mix(self, x0, y0, mix):
        """Star centres as float arrays and their mixing (``mix``, or computed)."""
        x0 = np.atleast_1d(np.asarray(x0, dtype=float))
        y0 = np.atleast_1d(np.asarray(y0, dtype=float))
        idx, wmix = self.mixing(x0, y0) if mix is None else mix
        return x0, y0, idx, wmix

    def evaluate(
        self,
        x0: np.ndarray,
        y0: np.ndarray,
        geometry: StampGeometry,
        mix: tuple[np.ndarray, np.ndarray] | None = None,
        derivatives: bool = True,
    ):
        """ePSF values (unit flux) on each star's stamp, with position derivatives.

        Parameters
        ----------
        x0, y0 : ndarray, shape (N,)
            Star centres [pixel].
        geometry : StampGeometry
            Stamp of each star (N stamps of S x S pixels).
        mix : tuple, optional
            Precomputed ``self.mixing(x0, y0)`` (mixing weights vary slowly, the
            fitter fixes them at the starting positions).
        derivatives : bool
            Also return d value / d x0 and d value / d y0 [1/pixel].

        Returns
        -------
        value : ndarray, shape (N, S, S)
            Fraction of the flux in each stamp pixel, indexed [star, row, column].
        dx, dy : ndarray, shape (N, S, S)
            Derivatives with respect to x0 and y0 (only if ``derivatives``).
        """
        x0, y0, idx, wmix = self._stars_and_mix(x0, y0, mix)
        return evaluate_stamps(
            self._coef,
            idx,
            wmix,
            x0,
            y0,
            np.broadcast_to(geometry.cx, x0.shape),
            np.broadcast_to(geometry.cy, x0.shape),
            geometry.radius,
            self.oversampling,
            self._centre,
            derivatives=derivatives,
        )

    def evaluate_numpy(
        self,
        x0: np.ndarray,
        y0: np.ndarray,
        geometry: StampGeometry,
        mix: tuple[np.ndarray, np.ndarray] | None = None,
        derivatives: bool = True,
    ):
        """:meth:`evaluate` in numpy (float32 gathers): the reference of the compiled path.

        Parameters and returns as :meth:`evaluate`; agrees with it to float32 rounding
        (relative ~1e-6 of the peak).
        """
        x0, y0, idx, wmix = self._stars_and_mix(x0, y0, mix)
        os_ = self.oversampling
        # oversampled coordinate of each stamp column / row in the padded grid
        u = (geometry.columns() - x0[:, None]) * os_ + self._centre[0]
        v = (geometry.rows() - y0[:, None]) * os_ + self._centre[1]
        fu = np.floor(u[:, :1])
        fv = np.floor(v[:, :1])
        wx, dwx = _bspline_weights(u[:, 0] - fu[:, 0])
        wy, dwy = _bspline_weights(v[:, 0] - fv[:, 0])
        n, s = u.shape
        # taps of column j are (floor(u_j) - 1) + 0..3 with floor(u_j) = floor(u_0) + os j:
        # the S x 4 taps lie in one window of L = os (S - 1) + 4 samples per axis
        length = os_ * (s - 1) + 4
        c0 = fu[:, 0].astype(np.intp) - 1
        r0 = fv[:, 0].astype(np.intp) - 1
        coef, margin = self._padded(min(c0.min(), r0.min()), max(c0.max(), r0.max()) + length)
        ny, nx = coef.shape[1:]
        sel = (os_ * np.arange(s)[:, None] + np.arange(4)[None, :]).ravel()  # (S*4,)
        offs = (sel[:, None] * nx + sel[None, :]).ravel()  # window offsets, (S*4*S*4,)
        start = (r0 + margin) * nx + (c0 + margin)
        flat = coef.reshape(-1)
        plane = ny * nx
        gathered = np.zeros((n, s * 4 * s * 4), dtype=np.float32)
        for m in range(idx.shape[1]):
            base = idx[:, m] * plane + start
            gathered += wmix[:, m, None].astype(np.float32) * flat[base[:, None] + offs[None, :]]
        gathered = gathered.reshape(n, s, 4, s, 4)
        wx, dwx, wy, dwy = (w.astype(np.float32) for w in (wx, dwx, wy, dwy))
        # contract the x taps with the weights (and their derivative) in one pass
        wxs = np.stack([wx, dwx], axis=2) if derivatives else wx[:, :, None]
        ax_all = np.matmul(gathered.reshape(n, s * 4 * s, 4), wxs).reshape(n, s, 4, s, -1)
        ax = ax_all[..., 0]
        value = np.einsum("njai,na->nji", ax, wy)
        if not derivatives:
            return value.astype(float)
        dvx = -os_ * np.einsum("njai,na->nji", ax_all[..., 1], wy)
        dvy = -os_ * np.einsum("njai,na->nji", ax, dwy)
        return value.astype(float), dvx.astype(float), dvy.astype(float)

    def _padded(self, lo: int, hi: int) -> tuple[np.ndarray, int]:
        """Spline coefficients (float32) zero-padded to cover indices ``lo .. hi - 1``."""
        need = max(0, -lo, hi - min(self._ny, self._nx))
        if need > self._margin:
            self._margin = int(need) + 8
            m = self._margin
            self._coef_pad = np.pad(self._coef, ((0, 0), (m, m), (m, m))).astype(np.float32)
        return self._coef_pad, self._margin


# ---------------------------------------------------------------- builders
def constant_epsf(epsf: np.ndarray, oversampling: int) -> VariableEPSF:
    """A field-constant ePSF.

    Parameters
    ----------
    epsf : ndarray
        The oversampled ePSF image.
    oversampling : int
        Samples per detector pixel.

    Returns
    -------
    VariableEPSF
        An ePSF of kind ``"constant"`` (one basis image, weight 1 everywhere).
    """

    def mixing(x, y):
        n = x.shape[0]
        return np.zeros((n, 1), dtype=np.intp), np.ones((n, 1))

    return VariableEPSF(epsf, oversampling, mixing, kind="constant")


def gridded_epsf(
    epsfs: np.ndarray, nodes_x: np.ndarray, nodes_y: np.ndarray, oversampling: int
) -> VariableEPSF:
    """ePSFs on a regular grid of field positions, bilinearly interpolated.

    Parameters
    ----------
    epsfs : ndarray, shape (ny_nodes * nx_nodes, ny, nx)
        ePSFs ordered row-major over the nodes (node ``j * nx_nodes + i`` is at
        ``(nodes_x[i], nodes_y[j])``).
    nodes_x, nodes_y : ndarray
        Increasing node positions [pixel]. Stars outside the grid take the
        nearest edge value (constant extrapolation).
    oversampling : int
    """
    nodes_x = np.asarray(nodes_x, dtype=float)
    nodes_y = np.asarray(nodes_y, dtype=float)
    nxn, nyn = len(nodes_x), len(nodes_y)
    if epsfs.shape[0] != nxn * nyn:
        raise InputError(f"gridded ePSF needs {nxn * nyn} ePSFs for the grid, got {epsfs.shape[0]}")

    def axis_weights(p, nodes):
        if len(nodes) == 1:
            z = np.zeros(p.shape, dtype=np.intp)
            return z, z, np.zeros(p.shape)
        i = np.clip(np.searchsorted(nodes, p) - 1, 0, len(nodes) - 2)
        t = np.clip((p - nodes[i]) / (nodes[i + 1] - nodes[i]), 0.0, 1.0)
        return i, i + 1, t

    def mixing(x, y):
        i0, i1, tx = axis_weights(x, nodes_x)
        j0, j1, ty = axis_weights(y, nodes_y)
        idx = np.stack([j0 * nxn + i0, j0 * nxn + i1, j1 * nxn + i0, j1 * nxn + i1], axis=1)
        w = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], axis=1)
        return idx, w

    return VariableEPSF(
        epsfs,
        oversampling,
        mixing,
        kind="grid",
        meta={"nodes_x": nodes_x.tolist(), "nodes_y": nodes_y.tolist()},
    )


def _monomials(u: np.ndarray, v: np.ndarray, order: int) -> np.ndarray:
    """Monomials u^i v^j with i + j <= order, shape (N, K)."""
    terms = [u**i * v ** (d - i) for d in range(order + 1) for i in range(d, -1, -1)]
    return np.stack(terms, axis=1)


def polynomial_epsf(
    epsfs: np.ndarray,
    positions_x: np.ndarray,
    positions_y: np.ndarray,
    order: int,
    shape: tuple[int, int],
    oversampling: int,
) -> VariableEPSF:
    """DAOPhot-style polynomially variable ePSF fitted to ePSFs at sample positions.

    Each oversampled ePSF sample is a polynomial of order ``order`` in the
    normalised field coordinates ``u = (x - xc) / xh``, ``v = (y - yc) / yh``
    (``xc, xh`` half the frame size), fitted by least squares to ePSFs measured at
    ``(positions_x, positions_y)``.

    Parameters
    ----------
    epsfs : ndarray, shape (P, ny, nx)
        ePSFs measured at P field positions (P must be at least the number of
        polynomial terms, ``(order + 1)(order + 2) / 2``).
    positions_x, positions_y : ndarray, shape (P,)
        Their field positions [pixel].
    order : int
        Polynomial order (0 constant, 1 linear, 2 quadratic, 3 cubic).
    shape : (int, int)
        Frame shape (ny, nx) used to normalise the coordinates.
    oversampling : int
    """
    order = int(order)
    if order < 0:
        raise InputError(f"polynomial order must be >= 0, got {order}")
    ny, nx = shape
    xc, yc = (nx - 1) / 2.0, (ny - 1) / 2.0
    xh, yh = max(nx / 2.0, 1.0), max(ny / 2.0, 1.0)
    design = _monomials(
        (np.asarray(positions_x) - xc) / xh, (np.asarray(positions_y) - yc) / yh, order
    )
    nterm = design.shape[1]
    if design.shape[0] < nterm:
        raise InputError(
            f"a polynomial ePSF of order {order} needs ePSFs at >= {nterm} field positions, "
            f"got {design.shape[0]}; use a denser grid or a lower order"
        )
    p, ey, ex = epsfs.shape
    coef, *_ = np.linalg.lstsq(design, epsfs.reshape(p, -1), rcond=None)
    return polynomial_from_basis(coef.reshape(nterm, ey, ex), order, shape, oversampling)


def polynomial_from_basis(
    basis: np.ndarray, order: int, shape: tuple[int, int], oversampling: int
) -> VariableEPSF:
    """A polynomially variable ePSF from its coefficient ePSFs (:func:`polynomial_epsf`'s basis).

    Parameters
    ----------
    basis : ndarray, shape (nterm, ny, nx)
        Coefficients of the monomials ``u^i v^j`` (``i + j <= order``).
    order : int
    shape : (int, int)
        Frame shape (ny, nx) that normalises the coordinates.
    oversampling : int
    """
    order = int(order)
    ny, nx = shape
    xc, yc = (nx - 1) / 2.0, (ny - 1) / 2.0
    xh, yh = max(nx / 2.0, 1.0), max(ny / 2.0, 1.0)
    nterm = (order + 1) * (order + 2) // 2
    if basis.shape[0] != nterm:
        raise InputError(f"a polynomial ePSF of order {order} needs {nterm} basis ePSFs")

    def mixing(x, y):
        w = _monomials((x - xc) / xh, (y - yc) / yh, order)
        idx = np.broadcast_to(np.arange(nterm), w.shape)
        return idx, w

    return VariableEPSF(
        basis, oversampling, mixing, kind="polynomial", meta={"order": order, "shape": [ny, nx]}
    )


def sample_epsf(
    prf: Callable[[np.ndarray, np.ndarray], np.ndarray], size: int, oversampling: int
) -> np.ndarray:
    """Sample a known pixel-integrated PSF ("PRF") onto an oversampled ePSF grid.

    Parameters
    ----------
    prf : callable
        ``prf(dx, dy)``: fraction of a star's flux in a pixel whose centre is at
        offset ``(dx, dy)`` pixels from the star (arrays, broadcast).
    size : int
        ePSF footprint in detector pixels (odd).
    oversampling : int

    Returns
    -------
    ndarray, shape (size * oversampling + 1,) * 2
        The ePSF with the star at the array centre.
    """
    n = int(size) * int(oversampling) + 1
    off = (np.arange(n) - (n - 1) / 2.0) / oversampling
    return prf(off[None, :], off[:, None])
