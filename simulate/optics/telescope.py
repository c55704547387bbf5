"""Telescope terms of the astrometric budget: plate-scale variations and field distortion.

Both act before the AO module, so the AO module's calibration mask
(``simulate/optics/calibration_mask.py``) does not see them (paper tab:astrobudget,
"Telescope Plate Scale Variations" and "Telescope Field Distortion").

Plate-scale variations
    The telescope's focal length breathes with temperature and focus: each epoch has its
    own plate scale ``1 + epsilon``, ``epsilon`` drawn from a normal distribution of RMS
    ``plate_scale_rms`` [ppm], seeded by (``seed``, epoch). A star at field position
    ``(x, y)`` moves by ``epsilon (x, y)``. A per-epoch linear alignment removes it
    exactly; a fixed-scale alignment does not.

Field distortion
    The telescope's own field distortion at the Nasmyth focus, a cubic radial term
    ``d = k r^2 (x, y)`` with amplitude ``field_distortion_corner`` [mas] at the corner
    (15", 15") of the field, the same in every epoch (so it cancels in proper motions
    of an unchanged pointing and rotation, and shows in single-epoch astrometry).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from mavispm.core.config import unit_field

__all__ = ["TelescopeSettings", "telescope_displacement", "plate_scale_change"]

#: field corner radius [arcsec] at which the field distortion amplitude is given
_CORNER = 15.0 * np.sqrt(2.0)


@dataclass(frozen=True)
class TelescopeSettings:
    """Telescope astrometric terms (TOML table ``[scene.optics.telescope]``).

    Parameters
    ----------
    plate_scale_rms : float
        RMS of the per-epoch relative plate-scale change [ppm] (0: none).
    field_distortion_corner : float
        Telescope field distortion at the field corner (15", 15") [mas] (0: none).
    seed : int
        Seed of the per-epoch plate-scale draws.
    """

    plate_scale_rms: float = 0.0
    field_distortion_corner: float = unit_field(0.0, "mas", "at (15, 15) arcsec")
    seed: int = 0

    def __post_init__(self):
        if not 0.0 <= self.plate_scale_rms <= 1e4:
            raise ValueError(f"plate_scale_rms must be 0 to 1e4 ppm, got {self.plate_scale_rms}")
        if not abs(self.field_distortion_corner) <= 1e4:
            raise ValueError("field_distortion_corner must be within +-1e4 mas")

    @property
    def enabled(self) -> bool:
        """Whether any telescope term is on."""
        return self.plate_scale_rms != 0.0 or self.field_distortion_corner != 0.0


def plate_scale_change(settings: TelescopeSettings, epoch: float) -> float:
    """The relative plate-scale change ``epsilon`` of ``epoch`` [yr] (dimensionless).

    Parameters
    ----------
    settings : TelescopeSettings
        ``plate_scale_rms`` [ppm] and ``seed``.
    epoch : float
        Epoch [yr] (with the seed, it fixes the draw).

    Returns
    -------
    float
        ``epsilon`` (Gaussian with RMS ``plate_scale_rms`` 1e-6); 0 when the RMS is 0.
    """
    if settings.plate_scale_rms == 0.0:
        return 0.0
    digest = hashlib.sha256(f"{settings.seed}:{float(epoch)!r}".encode()).digest()
    rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
    return float(settings.plate_scale_rms * 1e-6 * rng.standard_normal())


def telescope_displacement(x: ArrayLike, y: ArrayLike, epoch: float, settings: TelescopeSettings):
    """Displacement [arcsec] of images at field positions ``x, y`` [arcsec] at ``epoch`` [yr].

    Plate-scale change ``epsilon r`` plus a cubic field distortion ``k r^2 r`` that reaches
    ``field_distortion_corner`` at the field corner.

    Parameters
    ----------
    x, y : array_like
        Field positions [arcsec].
    epoch : float
        Epoch [yr].
    settings : TelescopeSettings
        The telescope terms.

    Returns
    -------
    dx, dy : ndarray
        Displacements [arcsec].
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    eps = plate_scale_change(settings, epoch)
    k = settings.field_distortion_corner / 1000.0 / _CORNER**3  # arcsec per arcsec^3
    r2 = x * x + y * y
    return eps * x + k * r2 * x, eps * y + k * r2 * y
