"""The VLT pupil: 8 m primary, central obstruction and optional spiders."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavispm.core.config import unit_field

__all__ = [
    "PupilSettings",
    "pupil_mask",
]


@dataclass(frozen=True)
class PupilSettings:
    """Telescope pupil geometry (TOML table ``[scene.optics.pupil]``).

    Parameters
    ----------
    diameter : float
        Primary mirror diameter D (m).
    obscuration : float
        Diameter of the central obstruction (m); 0 for an unobstructed pupil.
    spiders : bool
        Whether to draw the four secondary-mirror support vanes.
    spider_width : float
        Width of each vane (m).
    """

    diameter: float = unit_field(8.0, "m", "primary diameter")
    obscuration: float = unit_field(1.28, "m", "central obstruction diameter")
    spiders: bool = False
    spider_width: float = unit_field(0.05, "m", "spider vane width")

    def __post_init__(self):
        if not self.diameter > 0:
            raise ValueError(f"pupil diameter must be > 0 m, got {self.diameter}")
        if not 0 <= self.obscuration < self.diameter:
            raise ValueError(f"obscuration must be in [0, diameter) m, got {self.obscuration}")
        if not 0 <= self.spider_width < self.diameter / 4:
            raise ValueError(f"spider_width must be in [0, D/4) m, got {self.spider_width}")

    @property
    def obscuration_ratio(self) -> float:
        """Linear obscuration ratio epsilon (dimensionless)."""
        return self.obscuration / self.diameter


def pupil_mask(settings: PupilSettings, n: int, dx: float, supersample: int = 3) -> np.ndarray:
    """Transmission of the pupil on an ``n`` x ``n`` grid of pitch ``dx`` (m).

    The grid point ``(n//2, n//2)`` is the pupil centre, so the mask is
    symmetric under index reversal modulo ``n`` (a real, even OTF follows).
    Edge pixels hold the covered area fraction (``supersample``^2 sub-samples).

    Parameters
    ----------
    settings : PupilSettings
        Diameter [m], obscuration ratio and spiders.
    n : int
        Grid size.
    dx : float
        Grid pitch [m].
    supersample : int
        Sub-samples per pixel side for the edge fractions.

    Returns
    -------
    ndarray, shape (n, n), float64 in [0, 1]
    """
    s = supersample
    sub = (np.arange(s) - (s - 1) / 2) / s
    coords = (np.arange(n) - n // 2)[:, None] + sub[None, :]
    x = (coords.ravel() * dx)[None, :]
    y = (coords.ravel() * dx)[:, None]
    r = np.hypot(x, y)
    inside = (r <= settings.diameter / 2) & (r >= settings.obscuration / 2)
    if settings.spiders and settings.spider_width > 0:
        half = settings.spider_width / 2
        inside &= (np.abs(x) > half) & (np.abs(y) > half)
    return inside.reshape(n, s, n, s).mean(axis=(1, 3))
