"""Generic HDF5 data products: tables of columns with units, arrays, provenance.

Every file mavispm writes between stages is an HDF5 *product* with this layout
(see ``docs/formats.md``)::

    /                    attrs: format="mavispm", kind, format_version,
                                mavispm_version, created (ISO 8601 UTC),
                                seed, config (JSON text), plus kind-specific attrs
    /<table>             one compound dataset per table (names may be nested,
                         "epochs/e0"), written by astropy's HDF5 table writer with
                         serialize_meta, so ``astropy.table.Table.read(file,
                         path="<table>")`` reads it with its units;
                         attrs: mavispm_table=True, nrows, table metadata
    /<table>.__table_column_meta__   astropy's column description (units, YAML)
    /<array>             n-D dataset, attr "unit"

Quantities in attributes are stored as the value plus an attribute
``<name>__unit``. Products of format version 1 (a group per table, one dataset
per column with a "unit" attribute) are still read. Writers are atomic (temporary file, then rename); readers
validate what they read against a :class:`TableSpec` and raise
:class:`~mavispm.core.errors.InputError` naming the file and column.
"""

from __future__ import annotations

import datetime as _dt
import difflib
import json
import os
import re
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import astropy.units as u
import h5py
import numpy as np
from astropy.table import QTable, Table

from mavispm.core.atomic import atomic_path
from mavispm.core.errors import InputError
from mavispm.core.malloc_policy import owns_memory, release_pages

__all__ = [
    "as_table",
    "COLUMN_META_SUFFIX",
    "EXPORT_FORMATS",
    "export_table",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "open_product",
    "Product",
    "provenance_attrs",
    "read_product",
    "read_table",
    "read_table_group",
    "TableSpec",
    "UNIT_SUFFIX",
    "validate_table",
    "write_product",
]

FORMAT_NAME = "mavispm"
FORMAT_VERSION = 2
#: Suffix of the dataset in which astropy describes a table's columns (units, YAML).
COLUMN_META_SUFFIX = ".__table_column_meta__"
UNIT_SUFFIX = "__unit"


@dataclass(frozen=True)
class TableSpec:
    """What a table must contain.

    Parameters
    ----------
    required : dict of str to str
        Column name to unit string ("" for dimensionless). Columns are converted
        to these units on read.
    optional : dict of str to str
        Columns that may be present; converted when present.
    id_column : str or None
        Column whose values must be unique, or None.
    allow_nan : tuple of str
        Columns in which NaN is allowed (for example errors of unmeasured stars).
    allow_empty : bool
        Whether a table with zero rows is valid.
    text : dict of str to tuple of str
        Text columns (no unit) and their allowed values (an empty tuple allows any).
    """

    required: Mapping[str, str]
    optional: Mapping[str, str] = field(default_factory=dict)
    id_column: str | None = "id"
    allow_nan: tuple[str, ...] = ()
    allow_empty: bool = True
    text: Mapping[str, tuple] = field(default_factory=dict)


@dataclass
class Product:
    """An HDF5 product read back into memory.

    Parameters
    ----------
    path : pathlib.Path
    kind : str
    attrs : dict
        Root attributes (quantities restored, ``config`` parsed from JSON).
    tables : dict of str to astropy.table.QTable
    arrays : dict of str to numpy.ndarray or astropy.units.Quantity
    """

    path: Path
    kind: str
    attrs: dict
    tables: dict[str, QTable]
    arrays: dict[str, Any]


def provenance_attrs(config: Mapping | None = None, seed: int | None = None) -> dict:
    """Root attributes recording how a product was made.

    Parameters
    ----------
    config : mapping, optional
        The full configuration used; stored as JSON text.
    seed : int, optional
        The random seed used (-1 is stored when there is none).
    """
    from mavispm import __version__

    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "mavispm_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "seed": -1 if seed is None else int(seed),
        "config": json.dumps(_jsonable(config or {}), sort_keys=True),
    }


def _jsonable(obj):
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, u.Quantity):
        return {"value": _jsonable(obj.value), "unit": str(obj.unit)}
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _write_attrs(h5obj, attrs: Mapping) -> None:
    for key, value in attrs.items():
        if value is None:
            continue
        if isinstance(value, u.Quantity):
            h5obj.attrs[key] = value.value
            h5obj.attrs[key + UNIT_SUFFIX] = str(value.unit)
        elif isinstance(value, (dict, list, tuple)) and not _is_numeric_seq(value):
            h5obj.attrs[key] = json.dumps(_jsonable(value), sort_keys=True)
        else:
            h5obj.attrs[key] = value


def _is_numeric_seq(value) -> bool:
    if isinstance(value, dict):
        return False
    try:
        arr = np.asarray(value)
    except Exception:
        return False
    return arr.dtype.kind in "iufb" and arr.ndim == 1


def _read_attrs(h5obj) -> dict:
    out = {}
    keys = set(h5obj.attrs.keys())
    for key in keys:
        if key.endswith(UNIT_SUFFIX) or key == "mavispm_table":
            continue
        value = h5obj.attrs[key]
        if isinstance(value, bytes):
            value = value.decode()
        if isinstance(value, np.generic):
            value = value.item()
        if key + UNIT_SUFFIX in keys:
            unit = h5obj.attrs[key + UNIT_SUFFIX]
            value = u.Quantity(value, unit)
        elif key == "config" and isinstance(value, str):
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                pass
        out[key] = value
    return out


def _column_values(col):
    """Return (ndarray, unit string) for a table column or array-like."""
    if isinstance(col, u.Quantity):
        return np.asarray(col.value), str(col.unit)
    unit = getattr(col, "unit", None)
    arr = np.asarray(col)
    if arr.dtype.kind == "U":
        arr = arr.astype("S")
    if arr.dtype == object:
        raise InputError("object columns cannot be stored; use numbers or strings")
    return arr, ("" if unit is None else str(unit))


def write_product(
    path: str | os.PathLike,
    kind: str,
    *,
    tables: Mapping[str, Any] | None = None,
    arrays: Mapping[str, Any] | None = None,
    attrs: Mapping[str, Any] | None = None,
    config: Mapping | None = None,
    seed: int | None = None,
    compression: str | None = None,
    release: Collection[str] = (),
) -> Path:
    """Write an HDF5 product atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; replaced atomically, never left half-written.
    kind : str
        Product kind ("catalogue", "frames", "measured", "propermotions", "dynamics", ...).
    tables : mapping of str to table, optional
        Tables (astropy Table/QTable or mapping of column to array/Quantity). A
        table's ``meta`` scalars and quantities become group attributes.
    arrays : mapping of str to array or Quantity, optional
        N-dimensional datasets (images, PSF grids).
    attrs : mapping, optional
        Extra root attributes (quantities allowed).
    config, seed
        Provenance; see :func:`provenance_attrs`.
    compression : str, optional
        h5py compression filter for arrays (for example "gzip").
        Without one, a boolean array with no True value (the saturation mask of most
        frames) is created without data: HDF5 reads its fill value, False, so it reads
        back the same, and 16 MB less is written for a 4000 x 4000 mask.
    release : collection of str
        Names of ``arrays`` the caller hands over: each is written a block of rows at a
        time and each block's memory pages go back to the kernel once written, so that
        the file's page cache reuses them instead of taking fresh memory (on a VM whose
        host reclaims free memory, fresh pages cost ~2 ms per MB of system time). Their
        contents are undefined (zeros) afterwards, in every array sharing their memory.
        Only a writeable C-contiguous array owning its memory (or a view of one) is
        released (``core.malloc_policy.owns_memory``), sharing no memory with the
        product's other arrays, and only without compression; others are written as
        usual. The file is the same either way.

    Returns
    -------
    pathlib.Path
        The final path.
    """
    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        _write_attrs(f, provenance_attrs(config, seed))
        f.attrs["kind"] = kind
        _write_attrs(f, attrs or {})
        for name, table in (tables or {}).items():
            _write_table(f, name, table)
        for name, arr in (arrays or {}).items():
            if isinstance(arr, u.Quantity):
                data, unit = np.asarray(arr.value), str(arr.unit)
            else:
                data, unit = np.asarray(arr), ""
            if compression is None and data.dtype == np.bool_ and not data.any():
                ds = f.create_dataset(name, shape=data.shape, dtype=data.dtype, fillvalue=False)
            elif name in release and compression is None and _releasable(name, data, arrays):
                ds = f.create_dataset(name, shape=data.shape, dtype=data.dtype)
                _write_releasing(ds, data)
            else:
                ds = f.create_dataset(name, data=data, compression=compression)
            ds.attrs["unit"] = unit
    return path


def _releasable(name: str, data: np.ndarray, arrays: Mapping[str, Any]) -> bool:
    """Whether ``arrays[name]`` (as ``data``) may be released behind its write.

    Its own memory (``core.malloc_policy.owns_memory``), shared with no other array of
    the product (which would read zeros when written after it).
    """
    if not owns_memory(data):
        return False
    for other_name, other in arrays.items():
        if other_name != name:
            other = other.value if isinstance(other, u.Quantity) else other
            if isinstance(other, np.ndarray) and np.may_share_memory(data, other):
                return False
    return True


#: Bytes of an array written per step by :func:`_write_releasing`.
RELEASE_BLOCK = 4 << 20


def _write_releasing(ds, data: np.ndarray) -> None:
    """Write ``data`` into ``ds`` a block of rows at a time, releasing each block's pages.

    After each block of about :data:`RELEASE_BLOCK` bytes is written, its memory pages go
    back to the kernel (:func:`~mavispm.core.malloc_policy.release_pages`), so the file's
    page cache for the next block takes them instead of fresh pages. ``data`` reads as
    zeros afterwards (wholly or partly).
    """
    if data.ndim == 0 or data.size == 0:
        ds[...] = data
        return
    row = data.nbytes // data.shape[0]
    step = max(1, RELEASE_BLOCK // max(row, 1))
    for r0 in range(0, data.shape[0], step):
        r1 = min(r0 + step, data.shape[0])
        ds[r0:r1] = data[r0:r1]
        release_pages(data, 0, r1 * row)  # the earlier blocks again: nothing left there


def _write_table(f: h5py.File, name: str, table) -> None:
    """Write one table as a compound dataset astropy reads (units in its column meta)."""
    meta = dict(getattr(table, "meta", {}) or {})
    colnames = list(table.colnames) if hasattr(table, "colnames") else list(table)
    columns = {}
    nrows = None
    for cname in colnames:
        arr, unit = _column_values(table[cname])
        if arr.ndim != 1:
            raise InputError(
                f"table '{name}' column must be 1-D, got shape {arr.shape}", column=cname
            )
        if nrows is None:
            nrows = len(arr)
        elif len(arr) != nrows:
            raise InputError(f"table '{name}' has columns of different lengths", column=cname)
        columns[cname] = (arr, unit)
    if columns:
        header = _simple_table_header(columns)
        if header is not None:  # what astropy writes, without importing its YAML machinery
            data = np.empty(nrows, dtype=[(c, arr.dtype) for c, (arr, _) in columns.items()])
            for cname, (arr, _) in columns.items():
                data[cname] = arr
            f.create_dataset(name, data=data)
            f.create_dataset(name + TABLE_META_SUFFIX, data=np.array(header))
        else:
            from astropy.io.misc.hdf5 import write_table_hdf5

            out = Table()
            for cname, (arr, unit) in columns.items():
                out[cname] = arr
                if unit:
                    out[cname].unit = unit
            write_table_hdf5(out, f, path=name, serialize_meta=True)
        obj = f[name]
    else:  # no columns: an empty group (astropy cannot store a table without columns)
        obj = f.create_group(name)
    obj.attrs["mavispm_table"] = True
    obj.attrs["nrows"] = 0 if nrows is None else nrows
    _write_attrs(obj, {k: v for k, v in meta.items() if _attr_ok(v)})


#: Suffix of the dataset holding astropy's YAML column description of a table.
TABLE_META_SUFFIX = ".__table_column_meta__"

_PLAIN_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_PLAIN_UNIT = re.compile(r"[A-Za-z][A-Za-z0-9_ /().*]*[A-Za-z0-9)]\Z|[A-Za-z]\Z")
#: Plain words that YAML reads as booleans or null (astropy's dumper quotes them; it
#: writes ``y`` and ``n`` unquoted, as PyYAML reads them as strings: the column ``y`` of
#: every truth and catalogue table stays on the fast path).
_YAML_WORDS = {"yes", "no", "true", "false", "on", "off", "null"}


def _plain_yaml(text: str, pattern) -> bool:
    return bool(pattern.match(text)) and text.lower() not in _YAML_WORDS and "  " not in text


def _simple_table_header(columns: Mapping[str, tuple[np.ndarray, str]]) -> list[bytes] | None:
    """astropy's ``__table_column_meta__`` lines for a table of plain columns, or None.

    ``astropy.io.misc.hdf5.write_table_hdf5(..., serialize_meta=True)`` stores the
    column names, units and types as YAML (``datatype:`` then one
    ``- {name: x, unit: arcsec, datatype: float64}`` per column); producing it imports
    ``astropy.io.misc.yaml`` and with it ``astropy.coordinates`` (~0.2-0.9 s of every
    process that writes a product). For 1-D numeric, boolean and byte-string columns
    whose names and units YAML writes unquoted, the lines are written here (equal to
    astropy's, tested); anything else returns None and goes through astropy.
    """
    lines = [b"datatype:"]
    for cname, (arr, unit) in columns.items():
        kind = arr.dtype.kind
        if kind not in "biufS" or not _plain_yaml(cname, _PLAIN_NAME):
            return None
        datatype = "string" if kind == "S" else arr.dtype.name
        item = f"name: {cname}"
        if unit:
            text = u.Unit(unit, parse_strict="silent").to_string()
            if not _plain_yaml(text, _PLAIN_UNIT):
                return None
            item += f", unit: {text}"
        lines.append(f"- {{{item}, datatype: {datatype}}}".encode())
    return lines


def _attr_ok(value) -> bool:
    return isinstance(value, (str, int, float, bool, np.generic, u.Quantity, list, tuple, dict))


def open_product(path: str | os.PathLike, kind: str | None = None) -> h5py.File:
    """Open a product for reading after checking that it is one.

    Parameters
    ----------
    path : str or os.PathLike
        The product file.
    kind : str, optional
        Required product kind.

    Returns
    -------
    h5py.File
        Open for reading; close it (use it as a context manager).

    Raises
    ------
    InputError
        If the file is missing, not HDF5, not a mavispm product, or of another kind.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("file does not exist", path=path)
    if path.is_dir():
        raise InputError(f"is a folder; expected a '{kind or 'mavispm'}' product file", path=path)
    if path.stat().st_size == 0:
        raise InputError("file is empty", path=path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"not a readable HDF5 file ({exc})", path=path) from None
    fmt = f.attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode()
    if fmt != FORMAT_NAME:
        f.close()
        raise InputError("not a mavispm product (root attribute format != 'mavispm')", path=path)
    found = f.attrs.get("kind")
    if isinstance(found, bytes):
        found = found.decode()
    if kind is not None and found != kind:
        f.close()
        raise InputError(f"expected a '{kind}' product, found kind '{found}'", path=path)
    return f


def _table_groups(f: h5py.File) -> list[str]:
    """Names of the tables of a product (compound datasets or, version 1, groups)."""
    names: list[str] = []

    def visit(name, obj):
        if obj.attrs.get("mavispm_table", False):
            names.append(name)

    f.visititems(visit)
    return names


def _array_datasets(f: h5py.File) -> list[str]:
    names: list[str] = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            parent = obj.parent
            table_part = (
                obj.attrs.get("mavispm_table", False)
                or name.endswith(COLUMN_META_SUFFIX)
                or parent.attrs.get("mavispm_table", False)
            )
            if not table_part:
                names.append(name)

    f.visititems(visit)
    return names


def read_table_group(
    obj: h5py.Dataset | h5py.Group, path: str | os.PathLike | None = None
) -> QTable:
    """Read one table (compound dataset or, format version 1, group) into a QTable.

    Columns with units become Quantities; the table's attributes become ``meta``.

    Parameters
    ----------
    obj : h5py.Dataset or h5py.Group
        The table.
    path : path, optional
        File name, for messages.

    Returns
    -------
    QTable
    """
    if isinstance(obj, h5py.Dataset):
        table = _read_astropy_table(obj, path)
    else:
        table = _read_column_group(obj, path)
    table.meta.update(_read_attrs(obj))
    table.meta.pop("nrows", None)
    return table


_PLAIN_ITEM = re.compile(
    r"- \{name: (?P<name>[^,{}]+)(?:, unit: (?P<unit>[^,{}]+))?, datatype: (?P<dtype>[a-z0-9]+)\}\Z"
)


def _read_simple_table(ds: h5py.Dataset) -> QTable | None:
    """The table of a compound dataset whose column meta is a plain header, or None.

    The inverse of :func:`_simple_table_header` for numeric and boolean columns: when
    every line of the stored header is one astropy writes unquoted (``datatype:`` then
    ``- {name: x, unit: arcsec, datatype: float64}``, nothing else) the columns are read
    directly, sparing the process ``astropy.io.misc.yaml`` and ``astropy.coordinates``
    (~0.2 s); the table equals the one read through astropy (tested). Anything else
    (strings, other metadata) returns None and goes through astropy.
    """
    meta_name = ds.name + TABLE_META_SUFFIX
    if ds.dtype.names is None or meta_name not in ds.file:
        return None
    lines = [b.decode() if isinstance(b, bytes) else str(b) for b in ds.file[meta_name][()]]
    if not lines or lines[0] != "datatype:" or len(lines) - 1 != len(ds.dtype.names):
        return None
    columns = []
    for line, cname in zip(lines[1:], ds.dtype.names):
        m = _PLAIN_ITEM.match(line)
        if m is None or m["name"] != cname or not _plain_yaml(cname, _PLAIN_NAME):
            return None
        unit = m["unit"]
        if unit is not None and not _plain_yaml(unit, _PLAIN_UNIT):
            return None
        kind = ds.dtype[cname].kind
        if kind not in "biuf" or m["dtype"] != ds.dtype[cname].name:
            return None
        columns.append((cname, unit))
    data = ds[()]
    table = QTable()
    for cname, unit in columns:
        col = np.ascontiguousarray(data[cname])
        if unit is not None and col.dtype.kind in "fiu":
            table[cname] = u.Quantity(col, u.Unit(unit, parse_strict="silent"), copy=False)
        else:
            table[cname] = col
    return table


def _read_astropy_table(ds: h5py.Dataset, path=None) -> QTable:
    simple = _read_simple_table(ds)
    if simple is not None:
        return simple
    return _read_astropy_table_general(ds, path)


def _read_astropy_table_general(ds: h5py.Dataset, path=None) -> QTable:
    from astropy.io.misc.hdf5 import read_table_hdf5

    try:
        plain = read_table_hdf5(ds.file, path=ds.name, character_as_bytes=False)
    except (ValueError, TypeError) as exc:
        raise InputError(f"table '{ds.name}' cannot be read ({exc})", path=path) from None
    table = QTable()
    for cname in plain.colnames:
        col = plain[cname]
        unit = col.unit
        if unit is not None and str(unit) != "" and col.dtype.kind in "fiu":
            table[cname] = u.Quantity(np.asarray(col), unit, copy=False)
        else:
            table[cname] = np.asarray(col)
    return table


def _read_column_group(grp: h5py.Group, path=None) -> QTable:
    table = QTable()
    for cname, ds in grp.items():
        if not isinstance(ds, h5py.Dataset):
            continue
        data = ds[()]
        if data.dtype.kind == "S":
            data = data.astype("U")
        unit = ds.attrs.get("unit", "")
        if isinstance(unit, bytes):
            unit = unit.decode()
        if unit and data.dtype.kind in "fiu":
            try:
                table[cname] = u.Quantity(data, unit)
            except ValueError:
                raise InputError(
                    f"unit '{unit}' is not a valid astropy unit", path=path, column=cname
                ) from None
        else:
            table[cname] = data
    return table


def read_table(path: str | os.PathLike, name: str | None = None, kind: str | None = None) -> QTable:
    """One table of a product as a QTable with units, its attributes in ``meta``.

    Parameters
    ----------
    path : str or os.PathLike
        A mavispm product.
    name : str, optional
        Table name ("stars", "truth", "epochs/e0", ...); default: the product's
        only table, or ``stars`` when there are several.
    kind : str, optional
        Required product kind.

    Returns
    -------
    QTable
        ``meta`` holds the table's attributes and, under keys not already
        taken, the product's root attributes (epoch, distance, ...).

    Raises
    ------
    InputError
        Not a product, or no table of that name (the message lists the tables).
    """
    path = Path(path)
    with open_product(path, kind) as f:
        names = _table_groups(f)
        if name is None:
            if len(names) == 1:
                name = names[0]
            elif "stars" in names:
                name = "stars"
            else:
                raise InputError(f"the product has tables {names}; choose one", path=path)
        if name not in names:
            raise InputError(f"no table '{name}'; the product has {names}", path=path)
        table = read_table_group(f[name], path)
        for key, value in _read_attrs(f).items():
            table.meta.setdefault(key, value)
    return table


#: Formats of :func:`export_table` by file suffix.
EXPORT_FORMATS = {".fits": "fits", ".fit": "fits", ".ecsv": "ascii.ecsv", ".csv": "ascii.csv"}


def export_table(
    path: str | os.PathLike, output: str | os.PathLike, name: str | None = None
) -> Path:
    """Write one table of a product as FITS, ECSV or CSV (by ``output``'s suffix), atomically.

    Parameters
    ----------
    path : str or os.PathLike
        A mavispm product.
    output : str or os.PathLike
        ``.fits`` (units in TUNITn, root attributes as header cards where they
        fit), ``.ecsv`` (units and attributes in the YAML header) or ``.csv``
        (values only).
    name : str, optional
        Table name (see :func:`read_table`).

    Returns
    -------
    pathlib.Path
        ``output``.

    Raises
    ------
    InputError
        An unknown suffix, a missing table.
    """
    output = Path(output)
    fmt = EXPORT_FORMATS.get(output.suffix.lower())
    if fmt is None:
        raise InputError(
            f"unknown table format '{output.suffix}'; expected one of {sorted(EXPORT_FORMATS)}",
            path=output,
        )
    table = read_table(path, name)
    meta = {k: _export_meta(v) for k, v in table.meta.items() if v is not None}
    if fmt == "fits":  # as "HIERARCH MAVISPM <KEY>" cards (no clash with EPOCH, DATE ...)
        meta = {
            f"MAVISPM {k.upper()}": v
            for k, v in meta.items()
            if isinstance(v, (int, float, bool)) or (isinstance(v, str) and len(v) <= 50)
        }
    table.meta = meta
    with atomic_path(output) as tmp:
        if fmt == "fits":
            import warnings

            from astropy.io.fits.verify import VerifyWarning

            with warnings.catch_warnings():  # long keys become HIERARCH cards
                warnings.simplefilter("ignore", VerifyWarning)
                table.write(tmp, format=fmt, overwrite=True)
        else:
            table.write(tmp, format=fmt, overwrite=True)
    return output


def _export_meta(value):
    """A metadata value as ECSV/FITS can hold it (quantities as "value unit" text)."""
    if isinstance(value, u.Quantity):
        return value.value.tolist() if value.ndim else f"{value.value.item()!r} {value.unit}"
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(_jsonable(value), sort_keys=True)
    return value


def read_product(
    path: str | os.PathLike,
    kind: str | None = None,
    specs: Mapping[str, TableSpec] | None = None,
    load_arrays: bool = True,
) -> Product:
    """Read and validate a product.

    Parameters
    ----------
    path : str or os.PathLike
    kind : str, optional
        Required product kind.
    specs : mapping of str to TableSpec, optional
        Validation spec per table; a key ending in ``/*`` applies to every table
        below that group (``"epochs/*"``). Tables named without a wildcard must exist.
    load_arrays : bool
        Whether to load array datasets (set False to skip large images).

    Returns
    -------
    Product
    """
    path = Path(path)
    specs = dict(specs or {})
    with open_product(path, kind) as f:
        attrs = _read_attrs(f)
        tables = {name: read_table_group(f[name], path) for name in _table_groups(f)}
        arrays = {}
        if load_arrays:
            for name in _array_datasets(f):
                ds = f[name]
                unit = ds.attrs.get("unit", "")
                if isinstance(unit, bytes):
                    unit = unit.decode()
                data = ds[()]
                arrays[name] = u.Quantity(data, unit, copy=False) if unit else data
    for key, spec in specs.items():
        if key.endswith("/*"):
            prefix = key[:-1]
            matched = [n for n in tables if n.startswith(prefix)]
            if not matched:
                raise InputError(f"no tables under '{prefix}' found", path=path)
        else:
            if key not in tables:
                raise InputError(f"table '{key}' missing", path=path)
            matched = [key]
        for name in matched:
            tables[name] = validate_table(tables[name], spec, path=path, table_name=name)
    return Product(
        path=path, kind=attrs.get("kind", kind or ""), attrs=attrs, tables=tables, arrays=arrays
    )


def validate_table(
    table: Table,
    spec: TableSpec,
    path: str | os.PathLike | None = None,
    table_name: str | None = None,
) -> QTable:
    """Check a table against a spec and convert its columns to the spec's units.

    Parameters
    ----------
    table : astropy.table.Table or QTable
    spec : TableSpec
    path : optional
        File name used in error messages.
    table_name : str, optional
        Table name used in error messages.

    Returns
    -------
    QTable
        A copy with columns converted to the spec's units.

    Raises
    ------
    InputError
        Naming the file and column: missing or misspelled columns, wrong or
        missing units, NaN/inf values, duplicate IDs, an empty table.
    """
    where = f" (table '{table_name}')" if table_name else ""
    qt = QTable(table) if not isinstance(table, QTable) else table.copy(copy_data=False)
    if len(qt) == 0 and not spec.allow_empty:
        raise InputError(f"table is empty{where}; at least one row is needed", path=path)
    colnames = list(qt.colnames)
    for cname in spec.required:
        if cname not in colnames:
            close = difflib.get_close_matches(cname, colnames, n=1, cutoff=0.6)
            close = (
                difflib.get_close_matches(
                    cname.lower(), [c.lower() for c in colnames], n=1, cutoff=0.6
                )
                or close
            )
            hint = f"; did you mean '{close[0]}'?" if close else f"; found {colnames}"
            raise InputError(f"required column missing{where}{hint}", path=path, column=cname)
    wanted = {**spec.optional, **spec.required}
    for cname, unit in wanted.items():
        if cname not in colnames:
            continue
        qt[cname] = _convert_column(qt[cname], unit, path, cname, where)
        values = qt[cname]
        arr = values.value if isinstance(values, u.Quantity) else np.asarray(values)
        if arr.dtype.kind == "f" and cname not in spec.allow_nan and not np.all(np.isfinite(arr)):
            nbad = int(np.count_nonzero(~np.isfinite(arr)))
            raise InputError(
                f"{nbad} NaN or infinite value(s){where}; all values must be finite",
                path=path,
                column=cname,
            )
    for cname, allowed in spec.text.items():
        if cname in colnames:
            qt[cname] = _text_column(qt[cname], allowed, path, cname, where)
    if spec.id_column and spec.id_column in colnames and len(qt) > 0:
        ids = np.asarray(qt[spec.id_column])
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            dup = uniq[counts > 1][:5].tolist()
            raise InputError(f"duplicate IDs{where}: {dup}", path=path, column=spec.id_column)
    return qt


def _text_column(col, allowed, path, cname: str, where: str) -> np.ndarray:
    """A text column as a numpy str array, checked against its allowed values."""
    arr = np.asarray(col)
    if arr.dtype.kind == "S":
        arr = np.char.decode(arr, "utf-8")
    elif arr.dtype.kind == "O":
        arr = arr.astype(str)
    if arr.dtype.kind != "U":
        raise InputError(f"expected text{where}, found dtype {arr.dtype}", path=path, column=cname)
    if allowed:
        bad = sorted(set(np.unique(arr).tolist()) - set(allowed))
        if bad:
            raise InputError(
                f"unknown value(s) {bad[:5]}{where}; expected one of {list(allowed)}",
                path=path,
                column=cname,
            )
    return arr


def _convert_column(col, unit: str, path, cname: str, where: str):
    target = u.Unit(unit) if unit else u.dimensionless_unscaled
    if isinstance(col, u.Quantity):
        try:
            return col.to(target)
        except u.UnitConversionError:
            raise InputError(
                f"unit '{col.unit}' cannot be converted to '{target}'{where}",
                path=path,
                column=cname,
            ) from None
    col_unit = getattr(col, "unit", None)
    if col_unit is not None and str(col_unit) != "":
        try:
            return u.Quantity(np.asarray(col), col_unit).to(target)
        except (u.UnitConversionError, ValueError):
            raise InputError(
                f"unit '{col_unit}' cannot be converted to '{target}'{where}",
                path=path,
                column=cname,
            ) from None
    if unit:
        raise InputError(
            f"column has no unit{where}; expected a unit convertible to '{target}'",
            path=path,
            column=cname,
        )
    arr = np.asarray(col)
    if arr.dtype.kind not in "iufb":
        raise InputError(
            f"expected numbers{where}, found dtype {arr.dtype}", path=path, column=cname
        )
    return arr


def as_table(obj: Table | Mapping) -> Table:
    """Return ``obj`` as an astropy Table (accepts mappings of columns).

    Parameters
    ----------
    obj : Table or mapping of str to array-like
        A table, or columns by name.

    Returns
    -------
    astropy.table.Table
    """
    if isinstance(obj, Table):
        return obj
    return QTable(dict(obj))
