"""Scene settings: everything that defines how an epoch catalogue becomes a frame.

A scene is one TOML document (see ``docs/render.md``)::

    exptime = "30 s"      # one sub-exposure
    nexp = 120            # sub-exposures per stack
    noise = true
    [detector]     ...    # DetectorSettings
    [photometry]   ...    # PhotometrySettings
    [render]       ...    # RenderParams (accuracy knobs)
    [optics]       ...    # passed unchanged to mavispm.simulate.optics.model.validate_settings
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from mavispm.core.config import from_mapping, unit_field
from mavispm.simulate.render.detector import DetectorSettings
from mavispm.simulate.render.stamps import RenderParams
from mavispm.simulate.render.zero_point import PhotometrySettings

__all__ = [
    "SceneSettings",
    "scene_from_mapping",
]


@dataclass(frozen=True)
class SceneSettings:
    """How a frame is exposed and rendered.

    Parameters
    ----------
    exptime : float
        One sub-exposure, s (30).
    nexp : int
        Sub-exposures summed into the frame (120 in the paper: 1 h).
    noise : bool
        Draw photon and read noise (false: the noise-free expectation, still
        saturated per sub-exposure).
    save_noiseless : bool
        Also store the noise-free stack (electron) as array ``noiseless``.
    detector : DetectorSettings
    photometry : PhotometrySettings
    render : RenderParams
    optics : dict
        The optics model's own settings, validated by the optics module.
    """

    exptime: float = unit_field(30.0, "s")
    nexp: int = 120
    noise: bool = True
    save_noiseless: bool = False
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    photometry: PhotometrySettings = field(default_factory=PhotometrySettings)
    render: RenderParams = field(default_factory=RenderParams)
    optics: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.exptime > 0:
            raise ValueError(f"exptime must be > 0 s, got {self.exptime}")
        if self.nexp < 1:
            raise ValueError(f"nexp must be >= 1, got {self.nexp}")


def scene_from_mapping(mapping: Mapping | None, source: str | None = None) -> SceneSettings:
    """Build :class:`SceneSettings` from a TOML mapping (ConfigError naming bad keys).

    Parameters
    ----------
    mapping : mapping, SceneSettings or None
        The ``[scene]`` table (docs/render.md).
    source : str, optional
        File name, for messages.

    Returns
    -------
    SceneSettings
    """
    if isinstance(mapping, SceneSettings):
        return mapping
    return from_mapping(SceneSettings, mapping, source=source)
