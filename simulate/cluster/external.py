"""External star lists: N-body snapshots and MAVISIM source lists.

Accepted inputs (``ExternalInput`` settings, ``docs/cluster.md``):

* **3-D snapshots** (CSV, ECSV, FITS, HDF5): columns ``x, y, z`` (length) and
  ``vx, vy, vz`` (velocity), cluster-centred, ``z`` along the line of sight;
  optional ``id``, ``mass`` [solMass], ``mag`` [mag], ``luminous``.
* **Projected lists**: ``x, y`` (angle, from the cluster centre) and
  ``pm_x, pm_y`` (angle/time), plus ``mag``; optional ``id``, ``mass``.
* **MAVISIM source lists** (``format="mavisim"``): columns ``Star, RA, Dec, X,
  Y, Flux, PM_X, PM_Y``; ``X, Y`` in arcsec; the meaning of ``PM_X, PM_Y`` is
  an explicit option (``pm_convention``): ``mas_per_yr``, or
  ``arcsec_per_baseline`` (displacement in arcsec over ``pm_baseline`` years,
  as in the published MAVISIM examples). Magnitudes come from a ``mag``/``V``
  column or from ``Flux`` with ``flux_zeropoint``.

CSV files carry no units: give them with ``column_units``. Every problem
(unreadable or empty file, missing or misspelled column, missing or wrong
unit, NaN, duplicate IDs) raises :class:`~mavispm.core.errors.InputError`
naming the file and the column.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import Table

from mavispm.core.catalogue import OBJECT_KINDS
from mavispm.core.errors import InputError
from mavispm.core.products import TableSpec, validate_table
from mavispm.simulate.cluster import population as pop
from mavispm.simulate.cluster.projection import in_square, pc_to_arcsec, sky_to_field
from mavispm.simulate.cluster.settings import ClusterSettings, ExternalInput

__all__ = [
    "detect_format",
    "read_external_stars",
    "read_table",
]

_FORMATS = {
    ".csv": "csv",
    ".ecsv": "ecsv",
    ".fits": "fits",
    ".fit": "fits",
    ".fits.gz": "fits",
    ".h5": "hdf5",
    ".hdf5": "hdf5",
}
_ASTROPY_FORMAT = {"csv": "ascii.csv", "ecsv": "ascii.ecsv", "fits": "fits", "hdf5": "hdf5"}

SPEC_3D = TableSpec(
    required={"x": "pc", "y": "pc", "z": "pc", "vx": "km/s", "vy": "km/s", "vz": "km/s"},
    optional={"id": "", "mass": "solMass", "mag": "mag", "luminous": ""},
    id_column="id",
    allow_empty=False,
    text={"kind": OBJECT_KINDS},
)
SPEC_PROJECTED = TableSpec(
    required={"x": "arcsec", "y": "arcsec", "pm_x": "mas/yr", "pm_y": "mas/yr"},
    optional={"id": "", "mass": "solMass", "mag": "mag", "luminous": ""},
    id_column="id",
    allow_empty=False,
    text={"kind": OBJECT_KINDS},
)
MAVISIM_COLUMNS = ("Star", "RA", "Dec", "X", "Y", "Flux", "PM_X", "PM_Y")


def detect_format(path: Path, fmt: str) -> str:
    """Resolve ``fmt="auto"`` from the file extension.

    Parameters
    ----------
    path : pathlib.Path
        The external file.
    fmt : str
        ``"auto"`` or an explicit format (returned unchanged).

    Returns
    -------
    str
        The format.

    Raises
    ------
    InputError
        When ``fmt`` is ``"auto"`` and the extension is not a known one.
    """
    if fmt != "auto":
        return fmt
    name = path.name.lower()
    for ext, kind in _FORMATS.items():
        if name.endswith(ext):
            return kind
    raise InputError(
        f"cannot tell the format from the extension; set external.format to one of "
        f"{sorted(set(_FORMATS.values()) | {'mavisim'})}",
        path=path,
    )


def read_table(ext: ExternalInput) -> tuple[Table, str]:
    """Read the external file into an astropy Table (renames and units applied).

    Parameters
    ----------
    ext : ExternalInput
        The ``[cluster.external]`` settings (path, format, column renames, units).

    Returns
    -------
    table : astropy.table.Table
    fmt : str
        The resolved format.
    """
    path = Path(ext.path)
    if not path.is_file():
        raise InputError("file does not exist", path=path)
    if path.stat().st_size == 0:
        raise InputError("file is empty", path=path)
    fmt = detect_format(path, ext.format)
    kwargs = {}
    if fmt == "hdf5" and ext.hdf5_path:
        kwargs["path"] = ext.hdf5_path
    astropy_fmt = _ASTROPY_FORMAT.get(fmt, "ascii")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            table = Table.read(path, format=astropy_fmt, **kwargs)
    except Exception as exc:  # astropy raises many types for unreadable files
        raise InputError(
            f"cannot read as {fmt} table ({type(exc).__name__}: {exc})", path=path
        ) from None
    if len(table) == 0:
        raise InputError("table has no rows", path=path)
    for old, new in ext.columns.items():
        if old not in table.colnames:
            raise InputError(
                f"column to rename not found; found {table.colnames}", path=path, column=old
            )
        table.rename_column(old, new)
    for name, unit in ext.column_units.items():
        if name not in table.colnames:
            raise InputError(
                f"column given in column_units not found; found {table.colnames}",
                path=path,
                column=name,
            )
        try:
            unit = u.Unit(unit)
        except ValueError:
            raise InputError(
                f"'{unit}' is not a valid unit (column_units)", path=path, column=name
            ) from None
        if table[name].unit is None or str(table[name].unit) == "":
            table[name].unit = unit
    return table, fmt


def _mavisim_to_projected(table: Table, ext: ExternalInput, path) -> Table:
    """Standard projected columns from a MAVISIM source list."""
    missing = [c for c in ("Star", "X", "Y", "PM_X", "PM_Y") if c not in table.colnames]
    if missing:
        raise InputError(
            f"MAVISIM source list needs columns {list(MAVISIM_COLUMNS)}; found {table.colnames}",
            path=path,
            column=missing[0],
        )
    if ext.pm_convention == "":
        raise InputError(
            "MAVISIM PM_X/PM_Y are ambiguous: set external.pm_convention to 'mas_per_yr' or "
            "'arcsec_per_baseline' (published examples: arcsec displacement over 10 yr)",
            path=path,
            column="PM_X",
        )
    out = Table()
    out["id"] = np.asarray(table["Star"])
    for src, dst in (("X", "x"), ("Y", "y")):
        out[dst] = _as_quantity(table[src], u.arcsec)
    for src, dst in (("PM_X", "pm_x"), ("PM_Y", "pm_y")):
        values = _as_quantity(
            table[src], u.arcsec if ext.pm_convention != "mas_per_yr" else u.mas / u.yr
        )
        if ext.pm_convention == "arcsec_per_baseline":
            values = values / (ext.pm_baseline * u.yr)
        out[dst] = values
    mass_col = next((c for c in ("mass", "Mass") if c in table.colnames), None)
    if mass_col:
        out["mass"] = _as_quantity(table[mass_col], u.solMass)
    dark = np.zeros(len(table), bool)
    if "Flux" in table.colnames:
        flux = np.asarray(table["Flux"], float)
        if np.any(~(flux >= 0)):
            raise InputError("Flux must be finite and non-negative", path=path, column="Flux")
        dark = flux < ext.dark_flux
        out["luminous"] = ~dark
    mag_col = next((c for c in ("mag", "V", "Vmag") if c in table.colnames), None)
    if mag_col:
        out["mag"] = _as_quantity(table[mag_col], u.mag)
    elif "Flux" in table.colnames and ext.flux_zeropoint is not None:
        mag = np.full(len(table), pop.DARK_MAGNITUDE)
        mag[~dark] = ext.flux_zeropoint - 2.5 * np.log10(flux[~dark])
        out["mag"] = mag * u.mag
    else:
        raise InputError(
            "no magnitude: add a 'mag' or 'V' column, or set external.flux_zeropoint "
            "(mag of a source with Flux = 1) to convert Flux",
            path=path,
            column="mag",
        )
    return out


def _as_quantity(col, default_unit):
    """Column as a Quantity, taking ``default_unit`` only where the column has none."""
    unit = getattr(col, "unit", None)
    if unit is None or str(unit) == "":
        return np.asarray(col, float) * default_unit
    return u.Quantity(np.asarray(col, float), unit)


def _magnitudes(table, path, distance, extinction_v):
    """mag and luminous from the table, or from masses with the population relation."""
    n = len(table)
    if "mag" in table.colnames:
        mag = np.asarray(
            table["mag"].value if hasattr(table["mag"], "value") else table["mag"], float
        )
        luminous = (
            np.asarray(table["luminous"], bool)
            if "luminous" in table.colnames
            else np.ones(n, bool)
        )
        return mag, luminous
    if "mass" not in table.colnames:
        raise InputError(
            "neither 'mag' nor 'mass' given; one is needed for magnitudes", path=path, column="mag"
        )
    mass = np.asarray(table["mass"].value, float)
    luminous = (mass > 0) & (mass <= pop.tip_mass())
    mag = np.full(n, pop.DARK_MAGNITUDE)
    mag[luminous] = pop.apparent_v(mass[luminous], distance, extinction_v)
    return mag, luminous


def read_external_stars(
    ext: ExternalInput, settings: ClusterSettings, distance: float, extinction_v: float
) -> dict:
    """Read an external list and keep the stars in the field plus margin.

    Parameters
    ----------
    ext : ExternalInput
    settings : ClusterSettings
        Field size, margin, offset and rotation.
    distance : float
        [kpc], to project 3-D snapshots.
    extinction_v : float
        [mag], used only when magnitudes come from masses.

    Returns
    -------
    dict of ndarray
        ``id``, ``x_arcsec, y_arcsec`` (sky, from the cluster centre), ``pm_x, pm_y``
        [mas/yr] or ``vx, vy, vz`` [km/s] with ``z, r3d`` [pc], ``mag``, ``luminous``,
        optional ``mass``.
    """
    path = Path(ext.path)
    table, fmt = read_table(ext)
    if fmt == "mavisim":
        table = _mavisim_to_projected(table, ext, path)
    spec = SPEC_PROJECTED if ("pm_x" in table.colnames or fmt == "mavisim") else SPEC_3D
    checked = validate_table(table, spec, path=path)
    mag, luminous = _magnitudes(checked, path, distance, extinction_v)
    n = len(checked)
    stars = {
        "id": np.asarray(checked["id"], np.int64) if "id" in checked.colnames else np.arange(n),
        "mag": mag,
        "luminous": luminous,
    }
    if "mass" in checked.colnames:
        stars["mass"] = checked["mass"].to_value(u.solMass)
    if "kind" in checked.colnames:
        stars["kind"] = np.asarray(checked["kind"], str)
        if np.any((stars["kind"] == "star") != luminous):
            raise InputError(
                "'kind' must be 'star' exactly for luminous objects", path=path, column="kind"
            )
    elif "mass" in stars:
        stars["kind"] = pop.kind_from_mass(stars["mass"], luminous)
    if spec is SPEC_3D:
        pos = {k: checked[k].to_value(u.pc) for k in ("x", "y", "z")}
        vel = {k: checked[k].to_value(u.km / u.s) for k in ("vx", "vy", "vz")}
        if ext.recenter:
            w = stars.get("mass", np.ones(n))
            pos = {k: v - np.average(v, weights=w) for k, v in pos.items()}
            vel = {k: v - np.average(v, weights=w) for k, v in vel.items()}
        stars.update(pos, **vel)
        stars["r3d"] = np.sqrt(pos["x"] ** 2 + pos["y"] ** 2 + pos["z"] ** 2)
        stars["x_arcsec"] = pc_to_arcsec(pos["x"], distance)
        stars["y_arcsec"] = pc_to_arcsec(pos["y"], distance)
    else:
        stars["x_arcsec"] = checked["x"].to_value(u.arcsec)
        stars["y_arcsec"] = checked["y"].to_value(u.arcsec)
        stars["pm_x"] = checked["pm_x"].to_value(u.mas / u.yr)
        stars["pm_y"] = checked["pm_y"].to_value(u.mas / u.yr)
    xf, yf, _, _ = sky_to_field(
        stars["x_arcsec"],
        stars["y_arcsec"],
        0.0,
        0.0,
        (settings.offset_x, settings.offset_y),
        settings.rotation,
    )
    keep = in_square(xf, yf, 0.5 * settings.field_size + settings.margin)
    if not np.any(keep):
        raise InputError(
            f'no star falls inside the {settings.field_size:g}" field plus {settings.margin:g}" '
            "margin (check units, distance and offset)",
            path=path,
        )
    return {k: np.asarray(v)[keep] for k, v in stars.items()}
