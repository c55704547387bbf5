"""Anchor a later epoch's ePSF centres to the earlier epoch's ePSF (observer mode).

An ePSF and the positions of the stars it was built from are degenerate: shift
the ePSF by ``s`` and every fitted position moves by ``-s``. The builder
(:func:`mavispm.measure.stars.epsf.build_epsf_fast`) fixes this by anchoring
each node's ePSF to the mean of its PSF stars' *start* positions. At the first
epoch these are the input list (the observer's catalogue); at a later epoch in
observer mode they are the earlier epoch's measurements moved by an affine
transform, so each node's anchor is off by the mean proper motion of its PSF
stars times the baseline, plus the transform's error. On the NGC 3201 frames
(0.27 px rms motion over 10 yr, ~150 PSF stars per node) that is ~0.02 px
(~150 uas) per node, interpolated between nodes: a non-affine pattern that the
proper-motion alignment cannot remove and that set the bright-star PM floor.

The fix: the later epoch's node ePSFs are shifted so that each matches the
earlier epoch's ePSF at the same place on the sky (least-squares shift over the
core), so both epochs share the first epoch's centre convention and the start
positions no longer enter the measured positions. Only the ePSFs are compared;
no truth is used. With a PSF that changes between epochs, the core's
least-squares shift is the observer's best estimate of the common centre.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from mavispm.core.errors import InputError
from mavispm.measure.stars.variable_psf import (
    VariableEPSF,
    constant_epsf,
    gridded_epsf,
    polynomial_from_basis,
)

__all__ = [
    "ANCHOR_RADIUS",
    "EarlierAnchor",
    "epsf_from_product",
    "epsf_shift",
    "shift_epsf",
]

#: Radius [pixel] of the core over which the ePSFs are matched.
ANCHOR_RADIUS = 2.5


def epsf_from_product(basis: np.ndarray, description: str | dict) -> VariableEPSF:
    """The ePSF of a ``measured`` product from its ``epsf_basis`` array and ``epsf`` attribute.

    Parameters
    ----------
    basis : ndarray, shape (K, ny, nx)
        The ``epsf_basis`` array.
    description : str or dict
        The ``epsf`` root attribute (JSON): ``kind``, ``oversampling`` and the
        variation's description (``nodes_x``, ``nodes_y`` or ``order``, ``shape``).

    Raises
    ------
    InputError
        An unknown kind or a description that does not fit the basis.
    """
    meta = json.loads(description) if isinstance(description, str) else dict(description)
    basis = np.asarray(basis, float)
    if basis.ndim == 2:
        basis = basis[None]
    kind, os_ = meta.get("kind"), int(meta.get("oversampling", 0))
    if os_ < 1:
        raise InputError(f"epsf attribute: 'oversampling' must be >= 1, got {os_}")
    if kind == "constant":
        return constant_epsf(basis[0], os_)
    if kind == "grid":
        return gridded_epsf(basis, np.asarray(meta["nodes_x"]), np.asarray(meta["nodes_y"]), os_)
    if kind == "polynomial":
        return polynomial_from_basis(basis, int(meta["order"]), tuple(meta["shape"]), os_)
    raise InputError(
        f"epsf attribute: unknown kind '{kind}'; expected constant, grid or polynomial"
    )


def _grid(n: int, oversampling: int) -> np.ndarray:
    """Offsets [pixel] of an oversampled ePSF axis of ``n`` samples from its centre."""
    return (np.arange(n) - (n - 1) / 2.0) / oversampling


def epsf_shift(
    reference: np.ndarray,
    reference_os: int,
    epsf: np.ndarray,
    oversampling: int,
    radius: float = ANCHOR_RADIUS,
    iterations: int = 6,
) -> tuple[float, float]:
    """Least-squares shift [pixel] of ``epsf`` relative to ``reference``.

    Finds ``(sx, sy)`` and an amplitude ``k`` minimising
    ``sum (epsf(p) - k reference(p - s))^2`` over the samples of ``epsf`` within
    ``radius`` of its centre (``reference`` interpolated with cubic splines; the
    two may have different oversampling). A star fitted with ``epsf`` comes out
    ``s`` lower than with ``reference``.

    Parameters
    ----------
    reference : ndarray
        The reference ePSF image.
    reference_os : int
        Its oversampling.
    epsf : ndarray
        The ePSF image whose shift is measured.
    oversampling : int
        Its oversampling.
    radius : float
        Core radius of the fit [pixel].
    iterations : int
        Gauss-Newton iterations.

    Returns
    -------
    sx, sy : float
        [pixel]; (0, 0) where the core holds no signal.
    """
    off = _grid(epsf.shape[0], oversampling)
    px, py = np.meshgrid(off, off)
    core = np.hypot(px, py) <= radius
    target = np.asarray(epsf, float)[core]
    coef = ndimage.spline_filter(np.asarray(reference, float), order=3)
    c_ref = (reference.shape[0] - 1) / 2.0
    sx = sy = 0.0
    for _ in range(iterations):
        u = (px[core] - sx) * reference_os + c_ref
        v = (py[core] - sy) * reference_os + c_ref

        def at(du, dv, u=u, v=v):
            return ndimage.map_coordinates(coef, [v + dv, u + du], order=3, prefilter=False)

        model = at(0.0, 0.0)
        h = 0.5  # oversampled samples, central differences
        gx = (at(h, 0.0) - at(-h, 0.0)) / (2 * h) * reference_os
        gy = (at(0.0, h) - at(0.0, -h)) / (2 * h) * reference_os
        if not np.any(model > 0):
            return 0.0, 0.0
        # epsf ~ k model - k sx gx - k sy gy: linear in (k, k dsx, k dsy)
        design = np.column_stack([model, -gx, -gy])
        sol, *_ = np.linalg.lstsq(design, target, rcond=None)
        if not np.isfinite(sol).all() or sol[0] <= 0:
            return 0.0, 0.0
        dsx, dsy = sol[1] / sol[0], sol[2] / sol[0]
        sx, sy = sx + float(np.clip(dsx, -0.5, 0.5)), sy + float(np.clip(dsy, -0.5, 0.5))
        if abs(dsx) < 1e-6 and abs(dsy) < 1e-6:
            break
    return sx, sy


def shift_epsf(epsf: np.ndarray, oversampling: int, sx: float, sy: float) -> np.ndarray:
    """The ePSF moved by ``(-sx, -sy)`` pixels (cubic spline), renormalised: undoes a shift
    ``(sx, sy)`` measured by :func:`epsf_shift`.

    Parameters
    ----------
    epsf : ndarray
        The ePSF image.
    oversampling : int
        Its oversampling.
    sx, sy : float
        The shift to undo [pixel].

    Returns
    -------
    ndarray
        The moved ePSF with the input's sum (the input itself for a zero shift).
    """
    if sx == 0.0 and sy == 0.0:
        return epsf
    moved = ndimage.shift(epsf, (-sy * oversampling, -sx * oversampling), order=3, mode="constant")
    total = moved.sum()
    return moved * (epsf.sum() / total) if total > 0 else epsf


@dataclass
class EarlierAnchor:
    """Anchors node ePSFs of a new frame to an earlier epoch's ePSF.

    Parameters
    ----------
    psf : VariableEPSF
        The earlier epoch's ePSF (its frame's pixels).
    a, b : ndarray, shape (3,)
        The affine map earlier -> new pixels
        (:class:`~mavispm.measure.stars.start_list.EpochTransform`).
    radius : float
        Core radius [pixel] of the match.
    shifts : list of tuple
        ``(x, y, sx, sy)`` [pixel] of every node anchored (diagnostics).
    centring : NodeCentring, optional
        The error of the earlier ePSF's node centring
        (:class:`~mavispm.measure.stars.node_centring.NodeCentring`); None: not known.
    """

    psf: VariableEPSF
    a: np.ndarray
    b: np.ndarray
    radius: float = ANCHOR_RADIUS
    shifts: list = field(default_factory=list)
    centring: object = None

    def centring_error(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Per-axis error [pixel] of the earlier ePSF's centre convention at new-frame
        positions ``x, y`` (zeros where its node centring is not known): a later epoch
        centred on the earlier ePSF's positions shares it.

        Parameters
        ----------
        x, y : ndarray
            Positions in the new frame [pixel].

        Returns
        -------
        ndarray, shape (N,)
        """
        if self.centring is None:
            return np.zeros(np.shape(x))
        return self.centring.error_at(self.psf, *self.to_earlier_many(x, y))

    def to_earlier(self, x: float, y: float) -> tuple[float, float]:
        """A new-frame position [pixel] in the earlier frame (inverse of the affine map).

        Parameters
        ----------
        x, y : float
            Position in the new frame [pixel].

        Returns
        -------
        tuple of float
            Position in the earlier frame [pixel].
        """
        m = np.array([[self.a[1], self.a[2]], [self.b[1], self.b[2]]])
        xe, ye = np.linalg.solve(m, [x - self.a[0], y - self.b[0]])
        return float(xe), float(ye)

    def to_earlier_many(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """New-frame positions [pixel] in the earlier frame (arrays).

        Parameters
        ----------
        x, y : ndarray
            Positions in the new frame [pixel].

        Returns
        -------
        tuple of ndarray
            Positions in the earlier frame [pixel].
        """
        m = np.array([[self.a[1], self.a[2]], [self.b[1], self.b[2]]])
        inv = np.linalg.inv(m)
        dx, dy = np.asarray(x, float) - self.a[0], np.asarray(y, float) - self.b[0]
        return inv[0, 0] * dx + inv[0, 1] * dy, inv[1, 0] * dx + inv[1, 1] * dy

    def mapped_psf(self) -> VariableEPSF:
        """The earlier epoch's ePSF as a model of the new frame: a star at new-frame
        position ``(x, y)`` gets the earlier ePSF at the same place on the sky."""
        earlier = self.psf

        def mixing(x, y):
            return earlier.mixing(*self.to_earlier_many(x, y))

        return VariableEPSF(earlier.basis, earlier.oversampling, mixing, earlier.kind, earlier.meta)

    def __call__(self, epsf: np.ndarray, x: float, y: float, oversampling: int) -> np.ndarray:
        """The node ePSF at new-frame position ``(x, y)`` [pixel], shifted onto the earlier
        epoch's ePSF there."""
        reference = self.psf.epsf_at(*self.to_earlier(x, y))
        sx, sy = epsf_shift(reference, self.psf.oversampling, epsf, oversampling, self.radius)
        self.shifts.append((float(x), float(y), sx, sy))
        return shift_epsf(epsf, oversampling, sx, sy)
