"""Synthetic multi-epoch inputs with injected truth for the proper-motion tests.

A truth catalogue (positions at the reference epoch, proper motions, magnitudes)
is observed at several epochs: each epoch's *measured* positions are the true
positions at that epoch pushed through the inverse of a known polynomial
transformation ``P_k`` (plate scale, rotation, shift and a quadratic/cubic
dynamic distortion), plus Gaussian noise with known per-star errors. The
pipeline must recover ``P_k`` (epoch frame -> reference frame) and the motions.
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.products import write_product
from mavispm.measure.propermotions.inputs import EpochCatalogue


@dataclass
class InjectedTransform:
    """``X = P(x)``: epoch frame -> reference frame, in arcsec.

    ``X = shift + (1 + scale) R(rot) (x, y) + dist(x, y)``, ``dist`` a polynomial
    distortion ``sum c_ij (x/L)^i (y/L)^j`` [arcsec] of order 2-3.
    """

    shift: tuple[float, float] = (0.0, 0.0)  # arcsec
    scale: float = 0.0
    rotation: float = 0.0  # rad
    dist_x: dict | None = None  # {(i, j): arcsec}
    dist_y: dict | None = None
    length: float = 15.0  # arcsec

    def apply(self, x, y):
        """Map epoch-frame positions to the reference frame [arcsec]."""
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        f = 1.0 + self.scale
        xx = self.shift[0] + f * (c * x - s * y)
        yy = self.shift[1] + f * (s * x + c * y)
        u_, v_ = x / self.length, y / self.length
        for (i, j), a in (self.dist_x or {}).items():
            xx = xx + a * u_**i * v_**j
        for (i, j), a in (self.dist_y or {}).items():
            yy = yy + a * u_**i * v_**j
        return xx, yy

    def invert(self, xr, yr, iterations: int = 8):
        """Epoch-frame positions that map onto ``(xr, yr)`` (fixed-point iteration)."""
        x, y = np.array(xr, float), np.array(yr, float)
        for _ in range(iterations):
            fx, fy = self.apply(x, y)
            x = x - (fx - xr)
            y = y - (fy - yr)
        return x, y


def distortion_transform(seed: int = 0, amplitude: float = 1e-3, order: int = 2):
    """A transformation with plate-scale, rotation and a dynamic distortion (~``amplitude`` arcsec)."""
    rng = np.random.default_rng(seed)
    terms = [(i, n - i) for n in range(2, order + 1) for i in range(n + 1)]
    return InjectedTransform(
        shift=tuple(rng.normal(0, 0.01, 2)),
        scale=float(rng.normal(0, 1e-4)),
        rotation=float(rng.normal(0, 1e-4)),
        dist_x={t: float(rng.normal(0, amplitude)) for t in terms},
        dist_y={t: float(rng.normal(0, amplitude)) for t in terms},
    )


@dataclass
class TruthCluster:
    """Injected truth: ids, reference-epoch positions [arcsec], PMs [mas/yr], mag, errors."""

    ids: np.ndarray
    x: np.ndarray
    y: np.ndarray
    pm_x: np.ndarray
    pm_y: np.ndarray
    mag: np.ndarray
    pos_err: np.ndarray  # arcsec, per axis, per epoch


def make_cluster(
    n: int = 2000,
    seed: int = 1,
    half_size: float = 14.0,
    sigma_pm: float = 0.25,
    pm_sys=(0.3, -0.2),
    err_range=(30e-6, 300e-6),
    n_fast: int = 0,
) -> TruthCluster:
    """Stars uniform in a square field with Gaussian internal motions.

    Parameters
    ----------
    n : int
    seed : int
    half_size : float
        Half the field size [arcsec].
    sigma_pm : float
        Internal PM dispersion per axis [mas/yr].
    pm_sys : tuple of float
        Systemic (bulk) motion [mas/yr], absorbed by the alignment.
    err_range : tuple of float
        Range of per-axis position errors [arcsec], log-uniform with magnitude.
    n_fast : int
        Number of high-velocity stars (~30x the dispersion).
    """
    rng = np.random.default_rng(seed)
    x = rng.uniform(-half_size, half_size, n)
    y = rng.uniform(-half_size, half_size, n)
    pm_x = rng.normal(pm_sys[0], sigma_pm, n)
    pm_y = rng.normal(pm_sys[1], sigma_pm, n)
    if n_fast:
        ang = rng.uniform(0, 2 * np.pi, n_fast)
        pm_x[:n_fast] = pm_sys[0] + 30 * sigma_pm * np.cos(ang)
        pm_y[:n_fast] = pm_sys[1] + 30 * sigma_pm * np.sin(ang)
    mag = rng.uniform(16, 27, n)
    lo, hi = np.log10(err_range[0]), np.log10(err_range[1])
    err = 10 ** (lo + (hi - lo) * (mag - 16) / 11)
    return TruthCluster(
        ids=np.arange(100, 100 + n, dtype=np.int64),
        x=x,
        y=y,
        pm_x=pm_x,
        pm_y=pm_y,
        mag=mag,
        pos_err=err,
    )


def observe(
    truth: TruthCluster,
    epochs,
    transforms=None,
    seed: int = 2,
    t_ref: float = 0.0,
) -> list[EpochCatalogue]:
    """Measured catalogues of ``truth`` at ``epochs`` [yr].

    Parameters
    ----------
    transforms : list of InjectedTransform or None
        Per epoch, the epoch->reference transformation (None: identity).
    """
    rng = np.random.default_rng(seed)
    out = []
    for k, t in enumerate(epochs):
        xt = truth.x + truth.pm_x * 1e-3 * (t - t_ref)
        yt = truth.y + truth.pm_y * 1e-3 * (t - t_ref)
        tr = None if transforms is None else transforms[k]
        xe, ye = (xt, yt) if tr is None else tr.invert(xt, yt)
        n = truth.ids.size
        out.append(
            EpochCatalogue(
                epoch=float(t),
                ids=truth.ids.copy(),
                x=xe + rng.normal(0, truth.pos_err, n),
                y=ye + rng.normal(0, truth.pos_err, n),
                x_err=truth.pos_err.copy(),
                y_err=truth.pos_err.copy(),
                flag=np.zeros(n, np.int64),
                mag=truth.mag.copy(),
                x_true=xt,
                y_true=yt,
            )
        )
    return out


def write_measured(path, ep: EpochCatalogue, distance=4.6, xy_unit="arcsec", extra_attrs=None):
    """Write an :class:`EpochCatalogue` as a ``measured`` product (docs/formats.md)."""
    pix = 7.36e-3  # arcsec
    stars = QTable()
    stars["id"] = ep.ids
    conv = u.arcsec.to(xy_unit) if u.Unit(xy_unit).is_equivalent(u.arcsec) else 1.0
    stars["x_pix"] = ep.x / pix + 2000.0
    stars["y_pix"] = ep.y / pix + 2000.0
    stars["x"] = ep.x * conv * u.Unit(xy_unit)
    stars["y"] = ep.y * conv * u.Unit(xy_unit)
    stars["x_err"] = ep.x_err * u.arcsec
    stars["y_err"] = ep.y_err * u.arcsec
    stars["flux"] = np.full(ep.ids.size, 1e5) * u.electron
    stars["flag"] = ep.flag
    if ep.ids_true is not None:
        stars["id_true"] = ep.ids_true
    if ep.mag is not None:
        stars["mag"] = ep.mag * u.mag
    if ep.x_true is not None:
        stars["x_true"] = ep.x_true * u.arcsec
        stars["y_true"] = ep.y_true * u.arcsec
    attrs = {"epoch": ep.epoch * u.yr, "pixel_scale": 7.36 * u.mas, "engine": "synthetic"}
    if distance is not None:
        attrs["distance"] = distance * u.kpc
    attrs.update(extra_attrs or {})
    return write_product(path, "measured", tables={"stars": stars}, attrs=attrs)
