"""Effective temperatures of the luminous stars of an old metal-poor cluster.

For colour-dependent terms of the error budget (atmospheric dispersion: hot stars are
displaced more than cool ones; ``simulate/optics/refraction.py``). The table follows the
same ~12 Gyr, [Fe/H] ~ -1.5 isochrone as the mass-luminosity relation of
``simulate/cluster/population.py`` (an approximation to the Dartmouth isochrones,
Dotter et al. 2008, ApJS 178, 89): M dwarfs near 3,100 K, the turn-off near 6,400 K
(0.78 solMass), then the sub-giant branch cooling to ~5,000 K at the base of the red-giant
branch and ~4,100 K at its tip.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["MASS_TEFF_TABLE", "effective_temperature"]

#: (initial mass [solMass], T_eff [K]) at the masses of the mass-luminosity table
MASS_TEFF_TABLE = np.array(
    [
        (0.10, 3100.0), (0.15, 3300.0), (0.20, 3450.0), (0.25, 3550.0), (0.30, 3650.0),
        (0.35, 3750.0), (0.40, 3900.0), (0.45, 4100.0), (0.50, 4300.0), (0.55, 4550.0),
        (0.60, 4850.0), (0.65, 5200.0), (0.70, 5600.0), (0.75, 6100.0),
        (0.78, 6400.0),  # turn-off
        (0.795, 5900.0), (0.800, 5300.0),  # sub-giant branch
        (0.805, 5050.0), (0.808, 4800.0), (0.810, 4550.0), (0.811, 4350.0),
        (0.812, 4100.0),  # red-giant-branch tip
    ]
)  # fmt: skip


def effective_temperature(initial_mass: ArrayLike) -> np.ndarray:
    """T_eff [K] of luminous stars of ``initial_mass`` [solMass]; NaN beyond the RGB tip.

    Below the table's lowest mass the temperature is held at its first value.

    Parameters
    ----------
    initial_mass : array_like
        Initial masses [solMass].

    Returns
    -------
    ndarray
        Effective temperatures [K], interpolated in log mass; NaN for masses <= 0 or above
        the table's last (RGB-tip) mass.
    """
    m = np.asarray(initial_mass, float)
    lm = np.log(MASS_TEFF_TABLE[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.interp(np.log(m), lm, MASS_TEFF_TABLE[:, 1])
    return np.where((m > 0) & (m <= MASS_TEFF_TABLE[-1, 0]), out, np.nan)
