"""Settings of the ``simulate cluster`` stage (one frozen dataclass, TOML table ``[cluster]``).

Every key is documented in ``docs/cluster.md``. Values left ``None`` take the
preset's value (or an automatic one, as noted per key). The accuracy and speed knobs (the
sampler's table sizes) are one object apart from the model, :class:`ClusterKnobs`
(``settings.knobs``, TOML table ``[cluster.knobs]``; the earlier ``[cluster.resolution]``
table is still accepted, see :mod:`mavispm.core.knobs`).

Example
-------
>>> from mavispm.simulate.cluster.cli import validate_settings
>>> s = validate_settings({"n_stars": 100, "knobs": {"n_rows": 64}})
>>> s.knobs.n_rows, s.knobs.n_energy, s.resolution is s.knobs
(64, 800, True)
>>> validate_settings({"resolution": {"n_rows": 64}, "n_stars": 100}) == s
True
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from mavispm.core.config import unit_field
from mavispm.simulate.cluster.field_sampler import SamplerResolution
from mavispm.simulate.cluster.population import MassFunction

__all__ = [
    "CLUSTER_KNOB_HOMES",
    "ClusterKnobs",
    "ClusterSettings",
    "DEFAULT_MARGIN",
    "ExternalInput",
    "MAX_SEGREGATION",
]

PM_CONVENTIONS = ("mas_per_yr", "arcsec_per_baseline")
#: Default margin around the field [arcsec] for simulated clusters and for MAVISIM lists
#: (MAVISIM's own buffer is 10.005").
DEFAULT_MARGIN = 1.0
MAVISIM_MARGIN = 10.0
#: Largest mass-segregation exponent accepted (scale radius ~ mass^-segregation).
MAX_SEGREGATION = 1.5


@dataclass(frozen=True)
class ClusterKnobs(SamplerResolution):
    """Accuracy and speed knobs of the cluster stage (``[cluster.knobs]``).

    The table sizes of the DF and of the field sampler's inverse-CDF tables: none changes
    the model, only how closely the drawn stars follow it and how fast they are drawn
    (``benchmarks/bench_cluster.py`` tabulates the Jeans agreement against them). Every
    value must be at least 8.

    Parameters
    ----------
    n_energy : int
        Energy grid of the Eddington DF table.
    n_rows : int
        Rows (conditioning values) of the line-of-sight and speed quantile tables.
    n_levels : int
        Probability levels per row.
    n_los : int
        Line-of-sight grid points per row used to build the z table.
    n_speed : int
        Speed grid points per row used to build the speed table.
    n_radius : int
        Points of the projected-radius CDF.
    """


#: Knob -> its home before ``[cluster.knobs]`` existed (the ``[cluster.resolution]`` table).
CLUSTER_KNOB_HOMES = {f.name: ("resolution",) for f in dataclasses.fields(ClusterKnobs)}


@dataclass(frozen=True)
class ExternalInput:
    """An external star list to use instead of the equilibrium model.

    Parameters
    ----------
    path : str or None
        File to read (None: simulate the model).
    format : {"auto", "csv", "ecsv", "fits", "hdf5", "mavisim"}
        File format; "auto" guesses from the extension (.csv, .ecsv, .fits/.fit,
        .h5/.hdf5); MAVISIM source lists must be named explicitly.
    pm_convention : {"", "mas_per_yr", "arcsec_per_baseline"}
        Meaning of MAVISIM ``PM_X``/``PM_Y`` (required for ``format="mavisim"``):
        proper motions in mas/yr, or displacements in arcsec over ``pm_baseline``
        (the published MAVISIM examples use 10-year displacements).
    pm_baseline : float
        Baseline of ``arcsec_per_baseline`` displacements [yr].
    column_units : dict of str to str
        Units for columns the file stores without units (CSV), e.g. ``{x = "pc"}``.
    columns : dict of str to str
        Renames applied first, file column -> mavispm column (``{X = "x"}``).
    hdf5_path : str or None
        Table path inside an HDF5 file (astropy ``Table.read(path=...)``).
    flux_zeropoint : float or None
        For MAVISIM lists without a magnitude column: ``mag = zp - 2.5 log10(Flux)``.
    dark_flux : float
        MAVISIM ``Flux`` below which an object is dark (``luminous = False``; MAVISIM
        lists give remnants tiny placeholder fluxes such as 1.8e-4) [photon/s].
    recenter : bool
        Subtract the mass-weighted mean position and velocity of 3-D snapshots.
    """

    path: str | None = None
    format: Literal["auto", "csv", "ecsv", "fits", "hdf5", "mavisim"] = "auto"
    pm_convention: Literal["", "mas_per_yr", "arcsec_per_baseline"] = ""
    pm_baseline: float = unit_field(10.0, "yr")
    column_units: dict = field(default_factory=dict)
    columns: dict = field(default_factory=dict)
    hdf5_path: str | None = None
    flux_zeropoint: float | None = None
    dark_flux: float = 1.0
    recenter: bool = False

    def __post_init__(self):
        if not self.dark_flux >= 0:
            raise ValueError(f"'dark_flux' must be >= 0 photon/s, got {self.dark_flux}")


@dataclass(frozen=True)
class ClusterSettings:
    """Settings of the cluster catalogue stage (see ``docs/cluster.md``, which gives every
    default and where the preset supplies a value left None).

    Parameters
    ----------
    preset : str
        Cluster preset (``"ngc3201"``, ``"ngc3201-nbody"``, ...).
    imbh_mass : float
        Central IMBH mass [solMass] (0: none).
    n_stars : int
        Luminous stars inside the field square.
    field_size : float
        Side of the square field [arcsec].
    margin : float or None
        Width of the populated frame around the field [arcsec] (None: 1, or 10 for MAVISIM
        lists).
    epochs : list of float
        Epochs written [yr].
    reference_epoch : float
        Epoch of the sampled positions [yr].
    tracer : {"plummer", "king"} or None
        Density profile of the stars.
    king_w0 : float or None
        King (1966) central potential W0, in [0.1, 20].
    stellar_mass : float or None
        Total stellar mass [solMass].
    half_light_radius : float or None
        Projected half-mass radius that sets the scale radius [arcmin].
    scale_radius : float or None
        Plummer ``a`` / King ``r0`` [pc]; overrides ``half_light_radius``.
    cusp_gamma : float or None
        Inner cusp slope, in [0, 2.5).
    cusp_radius : float or None
        Radius of the cusp [pc].
    distance : float or None
        Heliocentric distance [kpc].
    extinction_v : float or None
        V-band extinction A_V [mag].
    ra_center, dec_center : float or None
        Cluster centre [deg].
    offset_x, offset_y : float
        Field centre relative to the cluster centre, sky frame [arcsec].
    rotation : float
        Field rotation, counter-clockwise [deg].
    pm_sys_x, pm_sys_y : float
        Systemic proper motion added, field frame [mas/yr].
    include_remnants : bool
        Add dark remnants (white dwarfs, neutron stars, black holes).
    mass_min, mass_break, mass_max : float
        IMF lower limit, break and upper limit [solMass].
    alpha_low, alpha_high : float or None
        Mass-function slopes ``dN/dm ~ m^-alpha`` below and above the break, in [-1, 4].
    ns_retention, bh_retention : float or None
        Retained fractions of neutron stars and IMF black holes, in [0, 1].
    segregation : float or None
        Mass-segregation exponent (group scale radius ``~ m^-segregation``), in [0, 1.5].
    anisotropy_radius : float or None
        Osipkov-Merritt anisotropy radius [arcsec] (None: isotropic).
    anisotropy_beta : float
        Constant anisotropy, in (-0.5, 0.5); not with ``anisotropy_radius``.
    bh_subsystem_mass : float
        Total mass of a 10-20 solMass black-hole subsystem [solMass] (0 or >= 10).
    bh_subsystem_radius : float or None
        Scale radius of the black-hole subsystem [pc].
    core_collapse : bool
        Core-collapse-like cusp without IMBH.
    knobs : ClusterKnobs
        Accuracy and speed knobs (the sampler's table sizes); also readable as
        ``resolution``, their earlier name.
    external : ExternalInput
        An external star list used instead of the model.
    """

    preset: str = "ngc3201"
    imbh_mass: float = unit_field(0.0, "solMass")
    n_stars: int = 3500
    field_size: float = unit_field(30.0, "arcsec")
    margin: float | None = unit_field(None, "arcsec")
    epochs: list[float] = field(default_factory=lambda: [0.0, 10.0])
    reference_epoch: float = unit_field(0.0, "yr")
    tracer: Literal["plummer", "king"] | None = None
    king_w0: float | None = None
    stellar_mass: float | None = unit_field(None, "solMass")
    half_light_radius: float | None = unit_field(None, "arcmin")
    scale_radius: float | None = unit_field(None, "pc")
    cusp_gamma: float | None = None
    cusp_radius: float | None = unit_field(None, "pc")
    distance: float | None = unit_field(None, "kpc")
    extinction_v: float | None = unit_field(None, "mag")
    ra_center: float | None = unit_field(None, "deg")
    dec_center: float | None = unit_field(None, "deg")
    offset_x: float = unit_field(0.0, "arcsec")
    offset_y: float = unit_field(0.0, "arcsec")
    rotation: float = unit_field(0.0, "deg")
    pm_sys_x: float = unit_field(0.0, "mas/yr")
    pm_sys_y: float = unit_field(0.0, "mas/yr")
    include_remnants: bool = True
    mass_min: float = unit_field(MassFunction.mass_min, "solMass")
    mass_break: float = unit_field(MassFunction.mass_break, "solMass")
    mass_max: float = unit_field(MassFunction.mass_max, "solMass")
    alpha_low: float | None = None
    alpha_high: float | None = None
    ns_retention: float | None = None
    bh_retention: float | None = None
    segregation: float | None = None
    anisotropy_radius: float | None = unit_field(None, "arcsec")
    anisotropy_beta: float = 0.0
    bh_subsystem_mass: float = unit_field(0.0, "solMass")
    bh_subsystem_radius: float | None = unit_field(None, "pc")
    core_collapse: bool = False
    knobs: ClusterKnobs = field(default_factory=ClusterKnobs)
    external: ExternalInput = field(default_factory=ExternalInput)

    @property
    def resolution(self) -> ClusterKnobs:
        """The knobs under their earlier name (``[cluster.resolution]``)."""
        return self.knobs

    def __post_init__(self):
        if self.margin is None:  # MAVISIM lists carry a 10" buffer whose light reaches the field
            mavisim = bool(self.external.path) and self.external.format == "mavisim"
            object.__setattr__(self, "margin", MAVISIM_MARGIN if mavisim else DEFAULT_MARGIN)
        checks = [
            (self.imbh_mass >= 0, "imbh_mass", "must be >= 0 solMass"),
            (self.n_stars >= 0, "n_stars", "must be >= 0"),
            (self.field_size > 0, "field_size", "must be > 0 arcsec"),
            (self.margin >= 0, "margin", "must be >= 0 arcsec"),
            (len(self.epochs) >= 1, "epochs", "needs at least one epoch"),
            (len(set(self.epochs)) == len(self.epochs), "epochs", "must not repeat"),
            (
                self.cusp_gamma is None or 0 <= self.cusp_gamma < 2.5,
                "cusp_gamma",
                "must be in [0, 2.5)",
            ),
            (self.distance is None or self.distance > 0, "distance", "must be > 0 kpc"),
            (self.stellar_mass is None or self.stellar_mass > 0, "stellar_mass", "must be > 0"),
            (self.king_w0 is None or 0.1 <= self.king_w0 <= 20, "king_w0", "must be in [0.1, 20]"),
            (
                self.segregation is None or 0 <= self.segregation <= MAX_SEGREGATION,
                "segregation",
                f"must be in [0, {MAX_SEGREGATION:g}] (0 = none, N-body-like ~0.4)",
            ),
            (
                self.anisotropy_radius is None or self.anisotropy_radius > 0,
                "anisotropy_radius",
                "must be > 0 arcsec (omit it for isotropy)",
            ),
            (
                -0.5 < self.anisotropy_beta < 0.5,
                "anisotropy_beta",
                "must be in (-0.5, 0.5) (0 = isotropic)",
            ),
            (
                self.anisotropy_beta == 0 or self.anisotropy_radius is None,
                "anisotropy_beta",
                "cannot be combined with anisotropy_radius; give one of them",
            ),
            (
                self.bh_subsystem_mass == 0 or self.bh_subsystem_mass >= 10.0,
                "bh_subsystem_mass",
                "must be 0 (none) or at least one black hole (>= 10 solMass)",
            ),
            (
                self.bh_subsystem_radius is None or self.bh_subsystem_radius > 0,
                "bh_subsystem_radius",
                "must be > 0 pc",
            ),
            (
                self.ns_retention is None or 0 <= self.ns_retention <= 1,
                "ns_retention",
                "must be in [0, 1]",
            ),
            (
                self.bh_retention is None or 0 <= self.bh_retention <= 1,
                "bh_retention",
                "must be in [0, 1]",
            ),
            (
                self.alpha_low is None or -1 <= self.alpha_low <= 4,
                "alpha_low",
                "must be in [-1, 4]",
            ),
            (
                self.alpha_high is None or -1 <= self.alpha_high <= 4,
                "alpha_high",
                "must be in [-1, 4]",
            ),
        ]
        for ok, key, what in checks:
            if not ok:
                raise ValueError(f"'{key}' {what}")

    def replace(self, **changes) -> ClusterSettings:
        """Copy with some values changed.

        Parameters
        ----------
        **changes
            Field values by name (``resolution=`` is taken as ``knobs=``).

        Returns
        -------
        ClusterSettings
            The new settings (validated again).
        """
        if "resolution" in changes:
            changes["knobs"] = changes.pop("resolution")
        return dataclasses.replace(self, **changes)
