"""Projection of cluster-frame stars to the field frame, proper motions and epochs.

Cluster frame: ``x, y`` in the sky plane and ``z`` along the line of sight
(away from the observer) [pc], velocities [km/s]. Field frame
(``docs/formats.md``): arcsec from the field centre, proper motions in mas/yr
along the same axes. The field frame is the sky frame shifted by the field
offset and rotated by ``rotation`` (counter-clockwise, degrees):
``(x_f, y_f) = R(-rotation) (x_sky - offset)``; proper motions rotate alike.

Positions at an epoch ``t`` are propagated linearly:
``x(t) = x(t_ref) + pm_x (t - t_ref)``. Over a 10-year baseline a star moves
~10 mas, negligible against its orbital radius for all but the innermost
~1e-4 pc, so orbital curvature is ignored.
"""

from __future__ import annotations

import astropy.units as u
import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "ARCSEC_PER_PC_KPC",
    "K_PM",
    "arcsec_to_pc",
    "in_square",
    "pc_to_arcsec",
    "pm_to_velocity",
    "propagate",
    "rotate",
    "sky_to_field",
    "velocity_to_pm",
]

#: km/s per (mas/yr * kpc): v = K_PM * mu * d
K_PM = float(
    (1 * u.mas / u.yr * u.kpc).to_value(u.km / u.s, equivalencies=u.dimensionless_angles())
)
#: arcsec per (pc / kpc)
ARCSEC_PER_PC_KPC = float(
    (1 * u.pc / u.kpc).to_value(u.arcsec, equivalencies=u.dimensionless_angles())
)


def pc_to_arcsec(length_pc: ArrayLike, distance_kpc: float):
    """Angle [arcsec] subtended by ``length_pc`` [pc] at ``distance_kpc`` (small angles).

    Parameters
    ----------
    length_pc : array_like
        Lengths [pc].
    distance_kpc : float
        Distance [kpc].

    Returns
    -------
    ndarray
        Angles [arcsec].
    """
    return np.asarray(length_pc) * ARCSEC_PER_PC_KPC / distance_kpc


def arcsec_to_pc(angle_arcsec: ArrayLike, distance_kpc: float):
    """Length [pc] at ``distance_kpc`` subtending ``angle_arcsec``.

    Parameters
    ----------
    angle_arcsec : array_like
        Angles [arcsec].
    distance_kpc : float
        Distance [kpc].

    Returns
    -------
    ndarray
        Lengths [pc].
    """
    return np.asarray(angle_arcsec) * distance_kpc / ARCSEC_PER_PC_KPC


def velocity_to_pm(v_kms: ArrayLike, distance_kpc: float):
    """Proper motion [mas/yr] of a transverse velocity [km/s] at ``distance_kpc``.

    Parameters
    ----------
    v_kms : array_like
        Velocities [km/s].
    distance_kpc : float
        Distance [kpc].

    Returns
    -------
    ndarray
        Proper motions [mas/yr].
    """
    return np.asarray(v_kms) / (K_PM * distance_kpc)


def pm_to_velocity(pm_masyr: ArrayLike, distance_kpc: float):
    """Transverse velocity [km/s] of a proper motion [mas/yr] at ``distance_kpc``.

    Parameters
    ----------
    pm_masyr : array_like
        Proper motions [mas/yr].
    distance_kpc : float
        Distance [kpc].

    Returns
    -------
    ndarray
        Velocities [km/s].
    """
    return np.asarray(pm_masyr) * K_PM * distance_kpc


def rotate(x: ArrayLike, y: ArrayLike, angle_deg: float):
    """Rotate vectors by ``angle_deg`` counter-clockwise.

    Parameters
    ----------
    x, y : array_like
        Vector components (any unit, kept).
    angle_deg : float
        Rotation angle [deg].

    Returns
    -------
    tuple of ndarray
        The rotated components.
    """
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    return c * x - s * y, s * x + c * y


def sky_to_field(
    x: ArrayLike,
    y: ArrayLike,
    pm_x: ArrayLike,
    pm_y: ArrayLike,
    offset: tuple[float, float] = (0.0, 0.0),
    rotation: float = 0.0,
    pm_sys: tuple[float, float] = (0.0, 0.0),
):
    """Sky-plane positions [arcsec] and PMs [mas/yr] to the field frame.

    Parameters
    ----------
    x, y : ndarray
        Sky-plane offsets from the cluster centre [arcsec].
    pm_x, pm_y : ndarray
        Internal proper motions [mas/yr].
    offset : (float, float)
        Field centre relative to the cluster centre, sky frame [arcsec].
    rotation : float
        Field rotation [deg], counter-clockwise from the sky axes.
    pm_sys : (float, float)
        Systemic proper motion added, field frame [mas/yr].

    Returns
    -------
    tuple of ndarray
        ``x_f, y_f`` [arcsec], ``pm_x_f, pm_y_f`` [mas/yr].
    """
    xf, yf = rotate(np.asarray(x) - offset[0], np.asarray(y) - offset[1], -rotation)
    pxf, pyf = rotate(np.asarray(pm_x), np.asarray(pm_y), -rotation)
    return xf, yf, pxf + pm_sys[0], pyf + pm_sys[1]


def propagate(
    x: ArrayLike,
    y: ArrayLike,
    pm_x: ArrayLike,
    pm_y: ArrayLike,
    epoch: float,
    reference_epoch: float = 0.0,
):
    """Positions [arcsec] at ``epoch`` [yr] from positions at ``reference_epoch``.

    Parameters
    ----------
    x, y : array_like
        Positions at the reference epoch [arcsec].
    pm_x, pm_y : array_like
        Proper motions [mas/yr].
    epoch : float
        Target epoch [yr].
    reference_epoch : float
        Epoch of ``x, y`` [yr].

    Returns
    -------
    tuple of ndarray
        Positions at ``epoch`` [arcsec].
    """
    dt = (epoch - reference_epoch) / 1000.0  # mas -> arcsec
    return np.asarray(x) + np.asarray(pm_x) * dt, np.asarray(y) + np.asarray(pm_y) * dt


def in_square(x: ArrayLike, y: ArrayLike, half_size: float):
    """Mask of points inside the square ``|x|, |y| <= half_size``.

    Parameters
    ----------
    x, y : array_like
        Positions (same unit as ``half_size``).
    half_size : float
        Half side of the square.

    Returns
    -------
    ndarray of bool
        True inside or on the edge.
    """
    return (np.abs(x) <= half_size) & (np.abs(y) <= half_size)
