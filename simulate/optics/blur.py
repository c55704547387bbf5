"""Imager blur terms: CCD charge diffusion and telescope vibration (paper section 3.2).

Both are isotropic Gaussians added in quadrature to the TT kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavispm.core.config import unit_field

__all__ = [
    "BlurSettings",
    "blur_sigma",
]


@dataclass(frozen=True)
class BlurSettings:
    """Gaussian blur terms (TOML table ``[scene.optics.blur]``).

    Parameters
    ----------
    charge_diffusion : bool
        Include CCD charge diffusion.
    charge_diffusion_sigma : float
        Its Gaussian sigma (mas); 3 mas for the CCD250.
    vibration : bool
        Include the (pessimistic) telescope vibration term.
    vibration_sigma : float
        Its Gaussian sigma (mas); 3.5 mas.
    """

    charge_diffusion: bool = True
    charge_diffusion_sigma: float = unit_field(3.0, "mas", "charge diffusion sigma")
    vibration: bool = True
    vibration_sigma: float = unit_field(3.5, "mas", "vibration sigma")

    def __post_init__(self):
        if self.charge_diffusion_sigma < 0 or self.vibration_sigma < 0:
            raise ValueError("blur sigmas must be >= 0 mas")


def blur_sigma(settings: BlurSettings) -> float:
    """Quadrature sum (mas) of the enabled blur sigmas; 0 when both are off.

    Parameters
    ----------
    settings : BlurSettings
        Charge-diffusion and vibration switches and sigmas [mas].

    Returns
    -------
    float
        Gaussian sigma [mas].
    """
    terms = []
    if settings.charge_diffusion:
        terms.append(settings.charge_diffusion_sigma)
    if settings.vibration:
        terms.append(settings.vibration_sigma)
    return float(np.sqrt(np.sum(np.square(terms)))) if terms else 0.0
