"""Stellar population of an old metal-poor cluster: masses, V magnitudes, remnants.

* Masses from a broken power-law mass function
  ``dN/dm ~ m^-alpha_low`` below ``mass_break`` and ``m^-alpha_high`` above
  (Kroupa 2001 slopes by default; a flatter ``alpha_low`` mimics the
  present-day mass function of a dynamically evolved cluster).
* Stars with initial mass up to the RGB tip are luminous; their absolute V
  magnitude follows a mass-luminosity relation for a ~12 Gyr, [Fe/H] ~ -1.5
  population (main sequence, turn-off, sub-giant and red-giant branches; an
  approximation to Dartmouth/BaSTI isochrones, no horizontal branch).
* More massive stars are dark remnants from initial-final mass relations:
  white dwarfs (Kalirai et al. 2008, 0.49-1.2 solMass), neutron stars above
  8 solMass (1.3-1.4 solMass) and black holes above 25 solMass (5-30 solMass,
  the range of low-metallicity models, e.g. Belczynski et al. 2010). Neutron
  stars and black holes are kept with a retention fraction (natal kicks). They
  are in the truth with ``luminous=False`` and a placeholder magnitude
  :data:`DARK_MAGNITUDE`; they are never rendered.
* The objects are split into mass groups (:func:`mass_groups`), each of which
  gets its own density profile in a multi-mass model (``generator.py``).
* Apparent V = M_V + distance modulus + extinction A_V.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "BH_SUBSYSTEM_RANGE",
    "DARK_MAGNITUDE",
    "MASS_LUMINOSITY_TABLE",
    "MassFunction",
    "MIN_GROUP_NUMBER",
    "MassGroup",
    "NS_PROGENITOR_MIN",
    "STAR_GROUP_EDGES",
    "WD_GROUP_SPLIT",
    "absolute_v",
    "apparent_v",
    "black_hole_mass",
    "black_hole_subsystem",
    "distance_modulus",
    "kind_from_mass",
    "mass_groups",
    "neutron_star_mass",
    "remnant_kind",
    "remnant_mass",
    "tip_mass",
    "white_dwarf_mass",
]

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
        """Fraction of all stars (mass_min..mass_max) with mass in [lo, hi].

        Parameters
        ----------
        lo, hi : float
            Mass range [solMass] (clipped to the mass function's limits).

        Returns
        -------
        float
            Number fraction in [0, 1].
        """
        lo, hi = max(lo, self.mass_min), min(hi, self.mass_max)
        if hi <= lo:
            return 0.0
        part = sum(s[3] for s in self._pieces(lo, hi))
        return part / sum(s[3] for s in self._pieces(self.mass_min, self.mass_max))

    def sample(self, uniform: np.ndarray, lo: float | None = None, hi: float | None = None):
        """Masses [solMass] by inverse CDF of the mass function truncated to [lo, hi].

        Parameters
        ----------
        uniform : ndarray
            Uniform numbers in [0, 1], one per mass.
        lo, hi : float, optional
            Truncation [solMass] (default: the mass function's limits).

        Returns
        -------
        ndarray
            Initial masses [solMass].
        """
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

    Parameters
    ----------
    mass : ndarray
        Initial masses [solMass] (below the RGB tip).

    Returns
    -------
    ndarray
        M_V [mag], interpolated in log mass.
    """
    m = np.asarray(mass, float)
    lm = np.log(MASS_LUMINOSITY_TABLE[:, 0])
    mv = MASS_LUMINOSITY_TABLE[:, 1]
    slope = (mv[1] - mv[0]) / (lm[1] - lm[0])
    out = np.interp(np.log(m), lm, mv)
    low = m < MASS_LUMINOSITY_TABLE[0, 0]
    out[low] = mv[0] + slope * (np.log(m[low]) - lm[0])
    return out


#: Initial masses [solMass] separating white dwarfs, neutron stars and black holes.
NS_PROGENITOR_MIN = 8.0
BH_PROGENITOR_MIN = 25.0
#: Mass range [solMass] of the black holes of a black-hole subsystem (``bh_subsystem_mass``).
BH_SUBSYSTEM_RANGE = (10.0, 20.0)


def white_dwarf_mass(initial: ArrayLike) -> np.ndarray:
    """White-dwarf mass [solMass] (Kalirai et al. 2008 IFMR, capped at 1.2 solMass).

    Parameters
    ----------
    initial : array_like
        Progenitor masses [solMass].

    Returns
    -------
    ndarray
        ``min(0.109 m + 0.394, 1.2)`` [solMass].
    """
    return np.minimum(0.109 * np.asarray(initial, float) + 0.394, 1.2)


def neutron_star_mass(initial: ArrayLike) -> np.ndarray:
    """Neutron-star mass [solMass]: 1.3 at 8 solMass rising to 1.4 at 25 solMass.

    Parameters
    ----------
    initial : array_like
        Progenitor masses [solMass].

    Returns
    -------
    ndarray
        Masses [solMass], linear in the progenitor mass and clipped to [1.3, 1.4].
    """
    m = np.asarray(initial, float)
    t = (m - NS_PROGENITOR_MIN) / (BH_PROGENITOR_MIN - NS_PROGENITOR_MIN)
    return 1.3 + 0.1 * np.clip(t, 0.0, 1.0)


def black_hole_mass(initial: ArrayLike) -> np.ndarray:
    """Black-hole mass [solMass]: 5 at 25 solMass rising linearly to 30 at 100 solMass.

    Parameters
    ----------
    initial : array_like
        Progenitor masses [solMass].

    Returns
    -------
    ndarray
        Masses [solMass] clipped to [5, 30].
    """
    m = np.asarray(initial, float)
    return np.clip(5.0 + (m - BH_PROGENITOR_MIN) / 3.0, 5.0, 30.0)


def remnant_kind(initial: ArrayLike) -> np.ndarray:
    """Kind of the remnant of stars of initial ``mass`` above the RGB tip.

    Parameters
    ----------
    initial : array_like
        Progenitor masses [solMass].

    Returns
    -------
    ndarray of str
        ``white_dwarf`` below the neutron-star progenitor mass, ``neutron_star`` below the
        black-hole progenitor mass, else ``black_hole``.
    """
    m = np.asarray(initial, float)
    return np.where(
        m < NS_PROGENITOR_MIN,
        "white_dwarf",
        np.where(m < BH_PROGENITOR_MIN, "neutron_star", "black_hole"),
    )


def remnant_mass(initial: ArrayLike) -> np.ndarray:
    """Remnant mass [solMass] of stars of initial mass ``initial`` (WD, NS or BH).

    Parameters
    ----------
    initial : array_like
        Progenitor masses [solMass].

    Returns
    -------
    ndarray
        Remnant masses [solMass] from the relation of the remnant's kind.
    """
    m = np.asarray(initial, float)
    return np.where(
        m < NS_PROGENITOR_MIN,
        white_dwarf_mass(m),
        np.where(m < BH_PROGENITOR_MIN, neutron_star_mass(m), black_hole_mass(m)),
    )


def kind_from_mass(mass: ArrayLike, luminous: ArrayLike) -> np.ndarray:
    """Best guess of ``kind`` from a present-day mass [solMass] (external lists).

    Luminous objects are stars; dark ones are white dwarfs below 1.25 solMass,
    neutron stars up to 3 solMass and black holes above.

    Parameters
    ----------
    mass : array_like
        Present-day masses [solMass].
    luminous : array_like of bool
        Whether each object shines.

    Returns
    -------
    ndarray of str
        ``star``, ``white_dwarf``, ``neutron_star`` or ``black_hole``.
    """
    m = np.asarray(mass, float)
    dark = np.where(m < 1.25, "white_dwarf", np.where(m <= 3.0, "neutron_star", "black_hole"))
    return np.where(np.asarray(luminous, bool), "star", dark)


def distance_modulus(distance_kpc: float) -> float:
    """``5 log10(d / 10 pc)`` for a distance in kpc.

    Parameters
    ----------
    distance_kpc : float
        Distance [kpc] (> 0).

    Returns
    -------
    float
        Distance modulus [mag].

    Raises
    ------
    ValueError
        When the distance is not positive.
    """
    if not distance_kpc > 0:
        raise ValueError(f"distance must be positive, got {distance_kpc} kpc")
    return 5.0 * np.log10(distance_kpc * 100.0)


def apparent_v(mass: np.ndarray, distance_kpc: float, extinction_v: float) -> np.ndarray:
    """Apparent V [mag] of luminous stars of initial ``mass`` at ``distance_kpc``.

    Parameters
    ----------
    mass : ndarray
        Initial masses [solMass].
    distance_kpc : float
        Distance [kpc].
    extinction_v : float
        V-band extinction A_V [mag].

    Returns
    -------
    ndarray
        V [mag].
    """
    return absolute_v(mass) + distance_modulus(distance_kpc) + extinction_v


#: Upper initial-mass edges [solMass] of the luminous-star groups (the last ends at the tip).
STAR_GROUP_EDGES = (0.3, 0.5, 0.7)
#: Initial mass [solMass] splitting the white dwarfs into two groups (final mass 0.6 solMass).
WD_GROUP_SPLIT = 1.89


@dataclass(frozen=True)
class MassGroup:
    """One mass group of the multi-mass model (objects of one kind in a mass range).

    Parameters
    ----------
    kind : str
        ``star``, ``white_dwarf``, ``neutron_star`` or ``black_hole``.
    lo, hi : float
        Initial (progenitor) mass range [solMass] (for ``fixed_range`` groups: the
        final mass range).
    number : float
        Objects per star of the mass function (retention applied), or the absolute
        number for ``fixed_range`` groups.
    mass : float
        Their total mass, in the same normalisation as ``number`` [solMass].
    fixed_range : bool
        Final masses uniform in [lo, hi] (the black-hole subsystem) instead of
        the mass function and an initial-final mass relation.
    """

    kind: str
    lo: float
    hi: float
    number: float
    mass: float
    fixed_range: bool = False

    @property
    def luminous(self) -> bool:
        """Whether the group's objects shine (stars)."""
        return self.kind == "star"

    @property
    def mean_mass(self) -> float:
        """Mean present-day mass [solMass]."""
        return self.mass / self.number

    def sample_masses(self, mf: MassFunction, uniform: np.ndarray) -> np.ndarray:
        """Present-day masses [solMass] of objects of this group from uniforms.

        Parameters
        ----------
        mf : MassFunction
            The population's initial mass function.
        uniform : ndarray
            Uniform numbers in [0, 1], one per object.

        Returns
        -------
        ndarray
            Masses [solMass]: uniform in [lo, hi] for a fixed-range group, else initial masses
            drawn in [lo, hi] (remnant masses for dark groups).
        """
        u = np.asarray(uniform, float)
        if self.fixed_range:
            return self.lo + (self.hi - self.lo) * u
        initial = mf.sample(u, lo=self.lo, hi=self.hi)
        return initial if self.luminous else remnant_mass(initial)


def _final_mass(kind: str, initial: np.ndarray) -> np.ndarray:
    return initial if kind == "star" else remnant_mass(initial)


def _group_moments(mf: MassFunction, kind: str, lo: float, hi: float, n: int = 4001):
    """Number fraction and mass per mass-function star of the group [solMass]."""
    lo, hi = max(lo, mf.mass_min), min(hi, mf.mass_max)
    if hi <= lo:
        return 0.0, 0.0
    number = mf.number_fraction(lo, hi)
    levels = (np.arange(n) + 0.5) / n  # midpoint rule in the group's own quantile
    mean = float(np.mean(_final_mass(kind, mf.sample(levels, lo=lo, hi=hi))))
    return number, number * mean


#: Objects per mass-function star below which a group is empty (a retention of 1e-311 left a
#: black-hole group whose density underflowed to 0 and broke the DF; a 1e7-star cluster
#: would hold < 1e-8 objects of such a group).
MIN_GROUP_NUMBER = 1e-15


def mass_groups(
    mf: MassFunction,
    include_remnants: bool = True,
    ns_retention: float = 1.0,
    bh_retention: float = 1.0,
) -> list[MassGroup]:
    """Mass groups of a population, numbers and masses per mass-function star.

    Stars are split at :data:`STAR_GROUP_EDGES` up to the RGB tip, white dwarfs
    at a final mass of 0.6 solMass; neutron stars and black holes (retained
    fractions ``ns_retention``, ``bh_retention``) form one group each. Empty
    groups (fewer than :data:`MIN_GROUP_NUMBER` objects per mass-function star) are
    dropped.

    Parameters
    ----------
    mf : MassFunction
        The initial mass function.
    include_remnants : bool
        Add white-dwarf, neutron-star and black-hole groups.
    ns_retention, bh_retention : float
        Retained fractions of neutron stars and black holes, in [0, 1].

    Returns
    -------
    list of MassGroup
    """
    tip = tip_mass()
    edges = [mf.mass_min, *[e for e in STAR_GROUP_EDGES if mf.mass_min < e < tip], tip]
    spec = [("star", a, b, 1.0) for a, b in zip(edges[:-1], edges[1:])]
    if include_remnants:
        spec += [
            ("white_dwarf", tip, WD_GROUP_SPLIT, 1.0),
            ("white_dwarf", WD_GROUP_SPLIT, NS_PROGENITOR_MIN, 1.0),
            ("neutron_star", NS_PROGENITOR_MIN, BH_PROGENITOR_MIN, ns_retention),
            ("black_hole", BH_PROGENITOR_MIN, np.inf, bh_retention),
        ]
    groups = []
    for kind, lo, hi, keep in spec:
        number, mass = _group_moments(mf, kind, lo, hi)
        if number * keep > MIN_GROUP_NUMBER:
            lo, hi = max(lo, mf.mass_min), min(hi, mf.mass_max)
            groups.append(MassGroup(kind, lo, hi, float(number * keep), float(mass * keep)))
    return groups


def black_hole_subsystem(total_mass: float) -> MassGroup:
    """A black-hole group of ``total_mass`` [solMass], masses uniform in 10-20 solMass.

    Parameters
    ----------
    total_mass : float
        Total mass of the subsystem [solMass].

    Returns
    -------
    MassGroup
        A fixed-range group with ``number = total_mass / 15``.
    """
    lo, hi = BH_SUBSYSTEM_RANGE
    mean = 0.5 * (lo + hi)
    return MassGroup("black_hole", lo, hi, total_mass / mean, total_mass, fixed_range=True)
