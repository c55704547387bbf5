"""The cluster *catalogue* product: star lists per epoch with the truth.

Layout (kind ``"catalogue"``; see ``docs/formats.md``)::

    /                attrs: provenance + distance [kpc], ra_center, dec_center [deg],
                     field_size [arcsec], imbh_mass [solMass] (0 if none), model
    /epochs/<name>/  one table per epoch (names "e0", "e1", ... in epoch order);
                     attr epoch [yr]; columns per CATALOGUE_SPEC

Positions are in the *field frame*: arcsec from the field centre, x towards
increasing detector column, y towards increasing row; proper motions in mas/yr
along the same axes. Positions in group ``epochs/eN`` are those at that epoch.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import astropy.units as u
from astropy.table import QTable

from mavispm.core.errors import InputError
from mavispm.core.products import TableSpec, read_product, write_product

__all__ = [
    "Catalogue",
    "CATALOGUE_KIND",
    "CATALOGUE_SPEC",
    "read_catalogue",
    "write_catalogue",
]

CATALOGUE_KIND = "catalogue"
#: Values of the optional catalogue column ``kind`` (what the object is).
OBJECT_KINDS = ("star", "white_dwarf", "neutron_star", "black_hole", "imbh")

#: Columns of every epoch table. Required columns are what the renderer needs;
#: optional columns carry the dynamical truth.
CATALOGUE_SPEC = TableSpec(
    required={
        "id": "",  # int64, unique star identifier, shared across epochs
        "x": "arcsec",  # field-frame position at this epoch
        "y": "arcsec",
        "pm_x": "mas/yr",  # proper motion (relative to the cluster unless pm_sys set)
        "pm_y": "mas/yr",
        "mag": "mag",  # apparent V magnitude (Vega), extinction included
    },
    optional={
        "mass": "solMass",
        "r3d": "pc",  # 3-D distance from the cluster centre
        "z": "pc",  # line-of-sight offset from the cluster centre
        "vx": "km/s",  # velocity along x, y, and line of sight
        "vy": "km/s",
        "vz": "km/s",
        "luminous": "",  # bool; False for dark remnants (never rendered)
        "teff": "K",  # effective temperature of luminous stars (NaN for dark objects)
    },
    id_column="id",
    allow_nan=("teff",),
    text={"kind": OBJECT_KINDS},  # star, white_dwarf, neutron_star, black_hole, imbh
)


@dataclass
class Catalogue:
    """A catalogue product in memory.

    Parameters
    ----------
    epochs : dict of str to QTable
        Epoch name to star table (ordered by epoch).
    attrs : dict
        Root attributes (distance, imbh_mass, config, seed, ...).
    path : pathlib.Path or None
    """

    epochs: dict[str, QTable]
    attrs: dict
    path: Path | None = None

    def epoch_times(self) -> dict[str, u.Quantity]:
        """Epoch name to epoch time (yr)."""
        return {name: u.Quantity(t.meta["epoch"], u.yr) for name, t in self.epochs.items()}


def write_catalogue(
    path: str | os.PathLike,
    epochs: Mapping[str, QTable],
    *,
    attrs: Mapping | None = None,
    config: Mapping | None = None,
    seed: int | None = None,
) -> Path:
    """Validate and write a catalogue product atomically.

    Parameters
    ----------
    path : str or os.PathLike
    epochs : mapping of str to QTable
        Each table's ``meta["epoch"]`` (Quantity in yr, or float years) is required.
    attrs : mapping, optional
        Root attributes such as ``distance`` (Quantity).
    config, seed
        Provenance.
    """
    if not epochs:
        raise InputError("a catalogue needs at least one epoch", path=path)
    tables = {}
    for name, table in epochs.items():
        if "epoch" not in table.meta:
            raise InputError(f"epoch table '{name}' has no meta['epoch']", path=path)
        checked = _validate_epoch(table, path, name)
        checked.meta["epoch"] = u.Quantity(table.meta["epoch"], u.yr)
        tables[f"epochs/{name}"] = checked
    return write_product(path, CATALOGUE_KIND, tables=tables, attrs=attrs, config=config, seed=seed)


def _validate_epoch(table, path, name):
    from mavispm.core.products import validate_table

    return validate_table(table, CATALOGUE_SPEC, path=path, table_name=f"epochs/{name}")


def read_catalogue(path: str | os.PathLike) -> Catalogue:
    """Read and validate a catalogue product.

    Parameters
    ----------
    path : str or os.PathLike
        A ``catalogue`` product.

    Returns
    -------
    Catalogue
        Epoch tables in time order, root attributes, the path.

    Raises
    ------
    InputError
        If the file is not a valid catalogue; the message names file and column.
    """
    prod = read_product(path, CATALOGUE_KIND, specs={"epochs/*": CATALOGUE_SPEC})
    epochs = {}
    for name, table in prod.tables.items():
        if not name.startswith("epochs/"):
            continue
        if "epoch" not in table.meta:
            raise InputError(f"table '{name}' has no 'epoch' attribute", path=path)
        epochs[name.split("/", 1)[1]] = table
    order = sorted(epochs, key=lambda n: u.Quantity(epochs[n].meta["epoch"], u.yr).value)
    return Catalogue(epochs={n: epochs[n] for n in order}, attrs=prod.attrs, path=Path(path))
