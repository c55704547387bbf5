"""Settings of the proper-motion stage (one frozen dataclass, every key documented).

:class:`ProperMotionSettings` holds the method (transformation model, reference epoch,
matching, reference-star selection, flags); its ``knobs`` (:class:`ProperMotionKnobs`,
GalSim's GSParams pattern, TOML table ``[propermotions.knobs]``) hold the accuracy and
speed knobs. The knobs may also be given as top-level keys of ``[propermotions]`` (the
earlier flat form; giving one both ways is an error) and read as settings attributes.

Example
-------
>>> s = validate_settings({"order": 2, "knobs": {"clip_iterations": 5}})
>>> s.knobs.clip_iterations, s.clip_iterations, s.knobs.match_tolerance
(5, 5, 0.02)
>>> validate_settings({"order": 2, "clip_iterations": 5}) == s
True
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from mavispm.core.config import from_mapping, unit_field
from mavispm.core.knobs import gather_knobs

__all__ = [
    "PM_KNOB_HOMES",
    "ProperMotionKnobs",
    "ProperMotionSettings",
    "validate_settings",
]


@dataclass(frozen=True)
class ProperMotionKnobs:
    """Accuracy and speed knobs of the proper-motion stage (``[propermotions.knobs]``).

    Parameters
    ----------
    match_tolerance : float
        Added to the positional search radius while the epoch transformation is not yet
        fitted [arcsec].
    clip_iterations : int
        Maximum number of fit-and-clip iterations per epoch (>= 1).
    """

    match_tolerance: float = unit_field(0.02, "arcsec", "search-radius allowance")
    clip_iterations: int = 10

    def __post_init__(self):
        if self.clip_iterations < 1:
            raise ValueError("clip_iterations must be at least 1")
        if not self.match_tolerance > 0:
            raise ValueError("match_tolerance must be > 0")


#: Knob -> its home before ``[propermotions.knobs]`` existed (a flat key of the table).
PM_KNOB_HOMES = {f.name: () for f in dataclasses.fields(ProperMotionKnobs)}


@dataclass(frozen=True)
class ProperMotionSettings:
    """Method of matching, alignment and the proper-motion fit, and its knobs.

    Parameters
    ----------
    order : int
        Order of the epoch-to-reference polynomial transformation: 1 (linear), 2, 3.
    conformal : bool
        With ``order = 1``: only shift + plate scale + rotation (4 parameters).
    reference : int
        Index (in time order) of the reference epoch; negative counts from the end.
    match : {"auto", "id", "position"}
        Cross-matching method; ``auto`` uses IDs when the epochs share them.
    max_pm : float
        Largest expected proper motion [mas/yr]; times the baseline it is the
        positional search radius.
    clip_sigma : float
        Sigma-clipping threshold for reference stars (high-velocity stars, mismatches).
    ref_max_error : float or None
        Reference stars need per-axis position errors below this in both epochs [mas].
    ref_mag_max : float or None
        Reference stars need a magnitude at most this [mag]: the measured ``mag_fit``
        when the epochs have it (the observer's), else the input ``mag``.
    distance : float or None
        Cluster distance [kpc] for km/s columns; default: the products' ``distance`` attr.
    center_x, center_y : float
        Cluster centre for radial/tangential components [arcsec].
    poor_fit_p : float
        Flag stars whose multi-epoch motion fits a straight line with chi-square p below this.
    knobs : ProperMotionKnobs
        Accuracy and speed knobs; also readable as attributes of the settings
        (``settings.clip_iterations`` is ``settings.knobs.clip_iterations``).
    """

    order: int = 1
    conformal: bool = False
    reference: int = 0
    match: Literal["auto", "id", "position"] = "auto"
    max_pm: float = unit_field(5.0, "mas/yr", "largest expected proper motion")
    clip_sigma: float = 4.0
    ref_max_error: float | None = unit_field(None, "mas", "reference-star error limit")
    ref_mag_max: float | None = unit_field(None, "mag", "reference-star faint limit")
    distance: float | None = unit_field(None, "kpc", "cluster distance")
    center_x: float = unit_field(0.0, "arcsec", "cluster centre x")
    center_y: float = unit_field(0.0, "arcsec", "cluster centre y")
    poor_fit_p: float = 1e-3
    knobs: ProperMotionKnobs = field(default_factory=ProperMotionKnobs)

    def __getattr__(self, name):
        # only called when normal lookup fails: the knobs read as settings attributes
        if name in PM_KNOB_HOMES:
            return getattr(self.knobs, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def replace(self, **changes) -> ProperMotionSettings:
        """A copy with ``changes`` applied; knob names go into :attr:`knobs`.

        Parameters
        ----------
        **changes
            Method settings and knobs by name.

        Returns
        -------
        ProperMotionSettings
            The new settings (validated again).
        """
        knobs = {k: changes.pop(k) for k in list(changes) if k in PM_KNOB_HOMES}
        if knobs:
            changes["knobs"] = dataclasses.replace(self.knobs, **knobs)
        return dataclasses.replace(self, **changes)

    def __post_init__(self):
        if self.order not in (1, 2, 3):
            raise ValueError(f"order must be 1, 2 or 3, got {self.order}")
        if self.conformal and self.order != 1:
            raise ValueError("conformal = true needs order = 1")
        if not self.clip_sigma > 1.0:
            raise ValueError(f"clip_sigma must be > 1, got {self.clip_sigma}")
        if self.max_pm < 0:
            raise ValueError("max_pm must be >= 0")
        if self.distance is not None and not self.distance > 0:
            raise ValueError(f"distance must be positive, got {self.distance} kpc")
        if self.ref_max_error is not None and not self.ref_max_error > 0:
            raise ValueError("ref_max_error must be positive")
        if not 0 <= self.poor_fit_p < 1:
            raise ValueError("poor_fit_p must be in [0, 1)")


def validate_settings(
    settings: Mapping | ProperMotionSettings | None = None, source: str | None = None
) -> ProperMotionSettings:
    """Build :class:`ProperMotionSettings` from a mapping (a TOML table).

    Parameters
    ----------
    settings : mapping or ProperMotionSettings, optional
        The ``[propermotions]`` table (None: defaults); a settings object is returned as is.
        The knobs may be given flat or in ``knobs``, not both for one knob.
    source : str, optional
        File named in error messages.

    Returns
    -------
    ProperMotionSettings
        The validated settings.

    Raises
    ------
    mavispm.core.errors.ConfigError
        Unknown keys, wrong types, bad units or impossible values, naming the key.
    """
    if isinstance(settings, ProperMotionSettings):
        return settings
    known = tuple(f.name for f in dataclasses.fields(ProperMotionSettings))
    mapping = gather_knobs(
        settings, PM_KNOB_HOMES, prefix="propermotions", source=source, known=known
    )
    return from_mapping(ProperMotionSettings, mapping, prefix="propermotions", source=source)
