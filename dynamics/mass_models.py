"""Enclosed mass ``M(<r)`` and potential ``Phi(r)`` of the fitted mass models, per posterior sample.

A mass model is the cluster (mass ``M`` with the tracer's profile shape and
scale radius ``a``), a central point mass ``M_bh`` and a dark Plummer sphere of
mass ``M_dark`` and scale ``b`` (any of them may be zero):

    M(<r)  = M m(r / a) + M_bh + M_dark (r/b)^3 (1 + (r/b)^2)^(-3/2)
    Phi(r) = -G int_r^inf M(<r') / r'^2 dr'
           = -G M psi(r / a) / a - G M_bh / r - G M_dark / sqrt(r^2 + b^2)

with ``psi(x) = int_x^inf m(x') / x'^2 dx'`` (``1 / sqrt(1 + x^2)`` for a Plummer
cluster; Gauss-Legendre quadrature in ``ln x`` up to ``1e6`` scale radii plus the
point-mass tail otherwise). ``Phi -> 0`` at infinity.

Use :func:`mass_model` to build one from a parameter dictionary of a fit (the
names of the posterior tables of a ``dynamics`` product) and
:func:`posterior_mass_models` for every sample of one model of a product.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import astropy.units as u
import numpy as np

from mavispm.dynamics.jeans import G_PC_KMS2_MSUN
from mavispm.dynamics.tracers import Plummer, make_tracer

__all__ = [
    "MassModel",
    "PC_PER_ARCSEC_KPC",
    "mass_model",
    "posterior_mass_models",
]

#: parsec per (arcsec * kpc)
PC_PER_ARCSEC_KPC = 1e3 * np.pi / (180.0 * 3600.0)
_X_FAR = 1.0e6
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(24)
_PANELS = 16


def _psi(tracer, x):
    """``int_x^inf m(x') / x'^2 dx'`` of a unit-mass profile (vectorised over ``x``)."""
    x = np.asarray(x, dtype=float)
    if isinstance(tracer, Plummer):
        return 1.0 / np.sqrt(1.0 + x * x)
    lx = np.log(np.maximum(x, 1e-12))
    l_far = np.log(_X_FAR)
    edges = np.linspace(0.0, 1.0, _PANELS + 1)
    mid, half = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
    t = (mid[:, None] + half[:, None] * _GL_NODES[None, :]).ravel()
    w = (half[:, None] * _GL_WEIGHTS[None, :]).ravel()
    span = np.maximum(l_far - lx, 0.0)
    ln_r = lx[..., None] + span[..., None] * t
    r = np.exp(ln_r)
    m = tracer.enclosed(r.ravel()).reshape(r.shape)
    inner = np.sum(m / r * w, axis=-1) * span  # int m / r d ln r
    return inner + 1.0 / np.maximum(x, _X_FAR)


@dataclass(frozen=True)
class MassModel:
    """Cluster + point mass + dark Plummer sphere.

    Parameters
    ----------
    cluster_mass : Quantity
        Cluster mass [solMass].
    scale_radius : Quantity
        Cluster (tracer) scale radius [pc].
    tracer : profile
        Unit-mass profile of :mod:`mavispm.dynamics.tracers` (shape of the cluster mass).
    bh_mass, dark_mass : Quantity
        Point mass and dark-component mass [solMass].
    dark_radius : Quantity
        Dark Plummer scale radius [pc].
    """

    cluster_mass: u.Quantity
    scale_radius: u.Quantity
    tracer: object = Plummer()
    bh_mass: u.Quantity = 0.0 * u.Msun
    dark_mass: u.Quantity = 0.0 * u.Msun
    dark_radius: u.Quantity = 1.0 * u.pc

    def _parts(self):
        return (
            self.cluster_mass.to_value(u.Msun),
            self.scale_radius.to_value(u.pc),
            self.bh_mass.to_value(u.Msun),
            self.dark_mass.to_value(u.Msun),
            self.dark_radius.to_value(u.pc),
        )

    def enclosed_mass(self, r: u.Quantity) -> u.Quantity:
        """``M(<r)`` [solMass] at 3-D radii ``r`` (length).

        Parameters
        ----------
        r : Quantity
            3-D radii (length).

        Returns
        -------
        Quantity
            Cluster, point and dark mass inside ``r`` [solMass].
        """
        r = u.Quantity(r).to_value(u.pc)
        m, a, mb, md, b = self._parts()
        dark = md * Plummer().enclosed(r / b) if md > 0 else 0.0
        return (m * self.tracer.enclosed(r / a) + mb + dark) * u.Msun

    def potential(self, r: u.Quantity) -> u.Quantity:
        """``Phi(r)`` [(km/s)^2], zero at infinity (the point mass diverges at r = 0).

        Parameters
        ----------
        r : Quantity
            3-D radii (length).

        Returns
        -------
        Quantity
            Potential [km2 / s2].
        """
        r = np.asarray(u.Quantity(r).to_value(u.pc), dtype=float)
        m, a, mb, md, b = self._parts()
        with np.errstate(divide="ignore"):
            phi = -G_PC_KMS2_MSUN * (
                m * _psi(self.tracer, r / a) / a
                + np.where(mb > 0, mb / r, 0.0)
                + md / np.sqrt(r * r + b * b)
            )
        return phi * (u.km / u.s) ** 2

    def escape_speed(self, r: u.Quantity) -> u.Quantity:
        """``sqrt(-2 Phi(r))`` [km/s].

        Parameters
        ----------
        r : Quantity
            3-D radii (length).

        Returns
        -------
        Quantity
            Escape speed [km/s].
        """
        return np.sqrt(-2.0 * self.potential(r))


def mass_model(
    params: dict,
    tracer: str = "plummer",
    concentration: float = 1.5,
    distance: u.Quantity | None = None,
):
    """Mass model of one parameter vector of a fit.

    Parameters
    ----------
    params : dict
        Physical parameters as in the posterior tables of a ``dynamics`` product:
        ``log_mass`` (log10 solMass), ``log_scale_radius`` (log10 arcsec), optional
        ``distance`` [kpc], ``gamma`` and ``log_cusp_radius`` (log10 arcsec; cusped
        Plummer/King62) or ``gamma`` (Dehnen), ``bh_mass`` [solMass], ``dark_mass``
        [solMass], ``log_dark_radius`` (log10 arcsec).
    tracer : {"plummer", "dehnen", "king62"}
    concentration : float
        King62 concentration.
    distance : float, optional
        Distance [kpc] when not in ``params``.

    Returns
    -------
    MassModel
    """
    d = float(params.get("distance", distance if distance is not None else np.nan))
    if not (np.isfinite(d) and d > 0):
        raise ValueError("mass_model needs a distance (parameter or argument), in kpc")
    pc = d * PC_PER_ARCSEC_KPC  # pc per arcsec
    a_arcsec = 10.0 ** params["log_scale_radius"]
    cusp = None
    if "log_cusp_radius" in params:
        cusp = 10.0 ** params["log_cusp_radius"] / a_arcsec
    profile = make_tracer(tracer, params.get("gamma", 1.0), concentration, cusp_radius=cusp)
    return MassModel(
        cluster_mass=10.0 ** params["log_mass"] * u.Msun,
        scale_radius=a_arcsec * pc * u.pc,
        tracer=profile,
        bh_mass=params.get("bh_mass", 0.0) * u.Msun,
        dark_mass=params.get("dark_mass", 0.0) * u.Msun,
        dark_radius=10.0 ** params.get("log_dark_radius", 0.0) * pc * u.pc,
    )


def posterior_mass_models(
    path: str | os.PathLike, model: str = "dark", max_samples: int | None = None
):
    """Mass models of every posterior sample of one model of a ``dynamics`` product.

    Parameters
    ----------
    path : path
        ``dynamics`` product.
    model : {"none", "imbh", "dark", "imbh_dark"}
        Which model's posterior (table ``posterior_<model>``).
    max_samples : int, optional
        Evenly thin to at most this many samples.

    Returns
    -------
    list of MassModel
    """
    from mavispm.core.errors import InputError
    from mavispm.core.products import read_product

    prod = read_product(path, "dynamics")
    key = f"posterior_{model}"
    if key not in prod.tables:
        raise InputError(f"no table {key!r} (models: {sorted(prod.tables)})", path=path)
    t = prod.tables[key]
    cfg = prod.attrs.get("config") or {}
    names = [c for c in t.colnames if c != "log_like"]
    rows = np.arange(len(t))
    if max_samples is not None and len(t) > max_samples:
        rows = np.linspace(0, len(t) - 1, max_samples).astype(int)
    dist = u.Quantity(prod.attrs["distance"], u.kpc).to_value(u.kpc)
    out = []
    for i in rows:
        params = {n: float(np.asarray(t[n])[i]) for n in names}
        out.append(
            mass_model(
                params,
                tracer=cfg.get("tracer", "plummer"),
                concentration=float(cfg.get("king_concentration", 1.5)),
                distance=dist,
            )
        )
    return out
