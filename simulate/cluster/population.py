"""Stellar population of an old metal-poor cluster: masses, V magnitudes, remnants.

* Masses from a broken power-law initial mass function
  ``dN/dm ~ m^-alpha_low`` below ``mass_break`` and ``m^-alpha_high`` above
  (Kroupa 2001 slopes by default).
* Stars with initial mass up to the RGB tip are luminous; their absolute V
  magnitude follows a mass-luminosity relation for a ~12 Gyr, [Fe/H] ~ -1.5
  population (main sequence, turn-off, sub-giant and red-giant branches; an
  approximation to Dartmouth/BaSTI isochrones, no horizontal branch).
* More massive stars are dark remnants (white dwarfs by the Kalirai et al.
  2008 initial-final mass relation, neutron stars above 8 solMass, black holes
  above 25 solMass). They are kept in the truth with ``luminous=False`` and
  a placeholder magnitude :data:`DARK_MAGNITUDE`; they are never rendered.
* Apparent V = M_V + distance modulus + extinction A_V.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Magnitude stored for dark remnants (never rendered; fainter than anything real).
DARK_MAGNITUDE = 99.0

#: (initial mass [solMass], M_V [mag]) for an old metal-poor population.
MASS_LUMINOSITY_TABLE = np.array(
    [
        (0.10, 14.6),
        (0.15, 12.9),
        (0.20, 11.7),
        (0.25, 10.8),
        (0.30, 10.1),
        (0.35, 9.5),
        (0.40, 9.0),
        (0.45, 8.5),
        (0.50, 8.0),
        (0.55, 7.4),
        (0.60, 6.8),
        (0.65, 6.1),
        (0.70, 5.3),
        (0.75, 4.4),
        (0.78, 3.9),  # turn-off
        (0.795, 3.3),  # sub-giant branch
        (0.800, 2.8),
        (0.805, 2.0),  # red-giant branch
        (0.808, 1.0),
        (0.810, 0.0),
        (0.811, -1.0),
        (0.812, -2.3),  # RGB tip
    ]
)


@dataclass(frozen=True)
class MassFunction:
    """Broken power-law initial mass function.

    Parameters
    ----------
    mass_min, mass_break, mass_max : float
        Lower limit, break and upper limit [solMass].
    alpha_low, alpha_high : float
        Slopes ``dN/dm ~ m^-alpha`` below and above the break.
    """

    mass_min: float = 0.15
    mass_break: float = 0.5
    mass_max: float = 100.0
    alpha_low: float = 1.3
    alpha_high: float = 2.3

    def __post_init__(self):
        if not 0 < self.mass_min < self.mass_max:
            raise ValueError(
                f"need 0 < mass_min < mass_max, got {self.mass_min}, {self.mass_max} solMass"
            )
        if not self.mass_break > 0:
            raise ValueError(f"mass_break must be positive, got {self.mass_break}")

    def _pieces(self, lo: float, hi: float):
        """Segments (a, b, alpha, weight) of the mass function between lo and hi."""
        segs = []
        brk = self.mass_break
        # continuity at the break: c_high = c_low * brk^(alpha_high - alpha_low)
        for a, b, alpha, c in (
            (lo, min(hi, brk), self.alpha_low, 1.0),
            (max(lo, brk), hi, self.alpha_high, brk ** (self.alpha_high - self.alpha_low)),
        ):
            if b > a:
                segs.append((a, b, alpha, c * _power_integral(a, b, alpha)))
        return segs

    def number_fraction(self, lo: float, hi: float) -> float:
        """Fraction of all stars (mass_min..mass_max) with mass in [lo, hi]."""
        lo, hi = max(lo, self.mass_min), min(hi, self.mass_max)
        if hi <= lo:
            return 0.0
        part = sum(s[3] for s in self._pieces(lo, hi))
        return part / sum(s[3] for s in self._pieces(self.mass_min, self.mass_max))

    def sample(self, uniform: np.ndarray, lo: float | None = None, hi: float | None = None):
        """Masses [solMass] by inverse CDF of the mass function truncated to [lo, hi]."""
        lo = self.mass_min if lo is None else max(lo, self.mass_min)
        hi = self.mass_max if hi is None else min(hi, self.mass_max)
        segs = self._pieces(lo, hi)
        weights = np.array([s[3] for s in segs])
        edges = np.concatenate([[0.0], np.cumsum(weights) / weights.sum()])
        u = np.asarray(uniform, float)
        seg = np.searchsorted(edges[1:-1], u, side="right")
        out = np.empty_like(u)
        for i, (a, b, alpha, _) in enumerate(segs):
            sel = seg == i
            frac = np.clip((u[sel] - edges[i]) / (edges[i + 1] - edges[i]), 0.0, 1.0)
            out[sel] = _power_quantile(a, b, alpha, frac)
        return out


def _power_integral(a, b, alpha):
    if abs(alpha - 1.0) < 1e-12:
        return np.log(b / a)
    return (b ** (1 - alpha) - a ** (1 - alpha)) / (1 - alpha)


def _power_quantile(a, b, alpha, frac):
    if abs(alpha - 1.0) < 1e-12:
        return a * (b / a) ** frac
    k = 1 - alpha
    return (a**k + frac * (b**k - a**k)) ** (1 / k)


def tip_mass() -> float:
    """Largest initial mass still luminous (RGB tip) [solMass]."""
    return float(MASS_LUMINOSITY_TABLE[-1, 0])


def absolute_v(mass: np.ndarray) -> np.ndarray:
    """Absolute V magnitude of luminous stars of initial ``mass`` [solMass].

    Below the table's lowest mass the main sequence is extrapolated linearly in
    log mass.
    """
    m = np.asarray(mass, float)
    lm = np.log(MASS_LUMINOSITY_TABLE[:, 0])
    mv = MASS_LUMINOSITY_TABLE[:, 1]
    slope = (mv[1] - mv[0]) / (lm[1] - lm[0])
    out = np.interp(np.log(m), lm, mv)
    low = m < MASS_LUMINOSITY_TABLE[0, 0]
    out[low] = mv[0] + slope * (np.log(m[low]) - lm[0])
    return out


def remnant_mass(initial: np.ndarray) -> np.ndarray:
    """Remnant mass [solMass]: WD (Kalirai et al. 2008), NS (1.4) or BH (10 % of M_init)."""
    m = np.asarray(initial, float)
    wd = np.minimum(0.109 * m + 0.394, 1.35)
    return np.where(m < 8.0, wd, np.where(m < 25.0, 1.4, 0.1 * m))


def distance_modulus(distance_kpc: float) -> float:
    """``5 log10(d / 10 pc)`` for a distance in kpc."""
    if not distance_kpc > 0:
        raise ValueError(f"distance must be positive, got {distance_kpc} kpc")
    return 5.0 * np.log10(distance_kpc * 100.0)


def apparent_v(mass: np.ndarray, distance_kpc: float, extinction_v: float) -> np.ndarray:
    """Apparent V [mag] of luminous stars of initial ``mass`` at ``distance_kpc``."""
    return absolute_v(mass) + distance_modulus(distance_kpc) + extinction_v


def remnant_ratio(mf: MassFunction) -> float:
    """Number of dark remnants per luminous star for this mass function."""
    lum = mf.number_fraction(mf.mass_min, tip_mass())
    dark = mf.number_fraction(tip_mass(), mf.mass_max)
    return dark / lum if lum > 0 else 0.0
