"""Read and check the ``measured`` products that go into the proper-motion stage."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import astropy.units as u
import numpy as np

from mavispm.core.errors import InputError
from mavispm.core.products import TableSpec, read_product, validate_table

if TYPE_CHECKING:
    from astropy.table import Table

__all__ = [
    "check_epochs",
    "epoch_catalogue",
    "EPOCH_TOLERANCE",
    "EpochCatalogue",
    "MEASURED_PM_SPEC",
    "read_measured",
]

#: Columns the proper-motion stage reads from a measured product's ``stars`` table.
MEASURED_PM_SPEC = TableSpec(
    required={"id": "", "x": "arcsec", "y": "arcsec", "x_err": "arcsec", "y_err": "arcsec"},
    optional={
        "flag": "",
        "mag": "mag",
        "mag_fit": "mag",
        "x_true": "arcsec",
        "y_true": "arcsec",
        "x_err_registration": "arcsec",
        "y_err_registration": "arcsec",
    },
    id_column="id",
    allow_nan=(
        "x_err",
        "y_err",
        "x_true",
        "y_true",
        "mag",
        "mag_fit",
        "x_err_registration",
        "y_err_registration",
    ),
)

#: Two epochs closer than this [yr] are the same epoch.
EPOCH_TOLERANCE = 1e-6


#: bits of the measure stage's flag that come from the truth match (scoring only)
TRUTH_SCORING_FLAGS = 16


@dataclass
class EpochCatalogue:
    """One epoch's measured stars, plain arrays in fixed units.

    Parameters
    ----------
    epoch : float
        [yr]
    ids : ndarray of int
    x, y, x_err, y_err : ndarray
        [arcsec]; errors may be NaN for stars the measurement flagged.
    flag : ndarray of int
        The measure stage's bitmask (0 = good).
    mag : ndarray or None
        Truth magnitude [mag].
    mag_fit : ndarray or None
        Measured magnitude [mag] (from the fitted flux).
    x_true, y_true : ndarray or None
        Truth positions [arcsec].
    distance : float or None
        [kpc], from the product's root attribute.
    path : pathlib.Path or None
    blind : bool
        The stars were found by blind detection: their ids are detection indices
        and must not be used to cross-match epochs.
    ids_true : ndarray of int or None
        The product's ``id_true`` column (truth id for scoring; -1 unmatched).
    x_err_registration, y_err_registration : ndarray or None
        The part of ``x_err``, ``y_err`` [arcsec] that is the registration to the
        reference list ``registration_reference`` (None: products without the
        columns, read as no shared part).
    registration_reference : str or None
        The product's ``registration_reference`` attribute: epochs naming the same
        list share that part (:mod:`~mavispm.measure.propermotions.shared_errors`).
    """

    epoch: float
    ids: np.ndarray
    x: np.ndarray
    y: np.ndarray
    x_err: np.ndarray
    y_err: np.ndarray
    flag: np.ndarray
    mag: np.ndarray | None = None
    mag_fit: np.ndarray | None = None
    x_true: np.ndarray | None = None
    y_true: np.ndarray | None = None
    distance: float | None = None
    path: Path | None = None
    blind: bool = False
    ids_true: np.ndarray | None = None
    x_err_registration: np.ndarray | None = None
    y_err_registration: np.ndarray | None = None
    registration_reference: str | None = None

    @property
    def label(self) -> str:
        """Name used in messages."""
        where = f"epoch {self.epoch:g} yr"
        return f"'{self.path}' ({where})" if self.path is not None else where


def _attr_quantity(attrs, key, unit, path, required):
    if key not in attrs:
        if required:
            raise InputError(f"root attribute '{key}' [{unit}] missing", path=path)
        return None
    value = attrs[key]
    try:
        q = u.Quantity(value, unit) if not isinstance(value, u.Quantity) else value.to(unit)
        out = float(q.value)
    except (u.UnitsError, TypeError, ValueError):
        raise InputError(
            f"root attribute '{key}' = {value!r} cannot be converted to {unit}", path=path
        ) from None
    if not np.isfinite(out):
        raise InputError(f"root attribute '{key}' is not finite", path=path)
    return out


def read_measured(path: str | os.PathLike) -> EpochCatalogue:
    """Read one ``measured`` product into an :class:`EpochCatalogue`.

    Parameters
    ----------
    path : str or os.PathLike
        A ``measured`` product.

    Returns
    -------
    EpochCatalogue

    Raises
    ------
    InputError
        Missing file, wrong kind, missing/misspelled columns, units that do not
        convert to arcsec, a missing ``epoch`` attribute; the message names the file.
    """
    path = Path(path)
    prod = read_product(path, "measured", specs={"stars": MEASURED_PM_SPEC}, load_arrays=False)
    return epoch_catalogue(prod.tables["stars"], prod.attrs, path=path)


def epoch_catalogue(
    stars: Table, attrs: Mapping | None = None, path: str | os.PathLike | None = None
) -> EpochCatalogue:
    """One epoch's measured stars (a ``measured`` ``stars`` table) as an :class:`EpochCatalogue`.

    Parameters
    ----------
    stars : Table or QTable
        Columns of :data:`MEASURED_PM_SPEC` (``id``, ``x``, ``y``, ``x_err``,
        ``y_err`` [arcsec], optional ``flag``, ``mag``, ``x_true``, ``y_true``,
        ``x_err_registration``, ``y_err_registration``).
    attrs : mapping, optional
        ``epoch`` [yr] (required), optional ``distance`` [kpc] and
        ``registration_reference``; default
        ``stars.meta`` (what :func:`mavispm.measure_stars` returns).
    path : path, optional
        Source file, for messages.

    Returns
    -------
    EpochCatalogue

    Raises
    ------
    InputError
        Missing or misspelled columns, units that do not convert, no ``epoch``.
    """
    attrs = stars.meta if attrs is None else attrs
    stars = validate_table(stars, MEASURED_PM_SPEC, path=path, table_name="stars")
    epoch = _attr_quantity(attrs, "epoch", "yr", path, required=True)
    distance = _attr_quantity(attrs, "distance", "kpc", path, required=False)

    def col(name):
        if name not in stars.colnames:
            return None
        c = stars[name]
        return np.asarray(c.value if isinstance(c, u.Quantity) else c, dtype=float)

    flag = (
        np.asarray(stars["flag"], dtype=np.int64)
        if "flag" in stars.colnames
        else np.zeros(len(stars), np.int64)
    )
    # the "no match to truth" bit is a score, not a measurement: an observer has no truth
    flag = flag & ~np.int64(TRUTH_SCORING_FLAGS)
    return EpochCatalogue(
        epoch=epoch,
        ids=np.asarray(stars["id"], dtype=np.int64),
        x=col("x"),
        y=col("y"),
        x_err=col("x_err"),
        y_err=col("y_err"),
        flag=flag,
        mag=col("mag"),
        mag_fit=col("mag_fit"),
        x_true=col("x_true"),
        y_true=col("y_true"),
        distance=distance,
        path=None if path is None else Path(path),
        blind=bool(attrs.get("blind", False)),
        ids_true=(
            np.asarray(stars["id_true"], dtype=np.int64) if "id_true" in stars.colnames else None
        ),
        x_err_registration=col("x_err_registration"),
        y_err_registration=col("y_err_registration"),
        registration_reference=attrs.get("registration_reference") or None,
    )


def check_epochs(epochs: list[EpochCatalogue], margin: float = 0.0) -> list[EpochCatalogue]:
    """Sort epochs in time and refuse duplicates, empty or non-overlapping catalogues.

    Parameters
    ----------
    epochs : list of EpochCatalogue
    margin : float
        Padding of each field's bounding box [arcsec] (the positional search radius)
        before the overlap test.

    Raises
    ------
    InputError
        Fewer than two epochs, the same file or the same epoch twice, an empty
        catalogue, or fields that do not overlap the first epoch's field.
    """
    if len(epochs) < 2:
        raise InputError(f"proper motions need at least two epochs, got {len(epochs)}")
    seen_paths = {}
    for ep in epochs:
        if ep.path is not None:
            key = Path(ep.path).resolve()
            if key in seen_paths:
                raise InputError("the same file is given twice as two epochs", path=ep.path)
            seen_paths[key] = ep
        if ep.ids.size == 0:
            raise InputError(f"{ep.label}: the catalogue has no stars")
    ordered = sorted(epochs, key=lambda e: e.epoch)
    for a, b in zip(ordered[:-1], ordered[1:]):
        if abs(b.epoch - a.epoch) < EPOCH_TOLERANCE:
            raise InputError(
                f"duplicate epoch {a.epoch:g} yr in {a.label} and {b.label}; "
                "each epoch must be given once (combine repeated frames first)"
            )
    first = ordered[0]
    for ep in ordered[1:]:
        if not _boxes_overlap(first, ep, margin):
            raise InputError(
                f"{ep.label}: field x [{ep.x.min():.2f}, {ep.x.max():.2f}], "
                f"y [{ep.y.min():.2f}, {ep.y.max():.2f}] arcsec does not overlap the field of "
                f"{first.label} (x [{first.x.min():.2f}, {first.x.max():.2f}], "
                f"y [{first.y.min():.2f}, {first.y.max():.2f}]); different pointings?"
            )
    return ordered


def _boxes_overlap(a: EpochCatalogue, b: EpochCatalogue, margin: float) -> bool:
    pad = 2.0 * margin
    x_ok = min(a.x.max(), b.x.max()) + pad >= max(a.x.min(), b.x.min())
    y_ok = min(a.y.max(), b.y.max()) + pad >= max(a.y.min(), b.y.min())
    return bool(x_ok and y_ok)
