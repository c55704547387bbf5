"""The ``propermotions`` stage: measured epochs in, a propermotions product out.

Command line::

    mavispm measure propermotions measured_e0.h5 measured_e1.h5 ... -o pm.h5 \
        [--distance 4.6kpc] [--order 1|2|3] [--conformal] [--reference N] \
        [--match auto|id|position] [--report DIR] [--truth cluster.h5]

Python (``docs/stages.md``): :func:`validate_settings`, :func:`run_stage`,
:func:`write_report`, :func:`register`.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import astropy.units as u
import numpy as np
from astropy.stats import mad_std

from mavispm.core.catalogue import Catalogue, read_catalogue
from mavispm.core.config import to_mapping
from mavispm.core.products import read_product, write_product
from mavispm.measure.propermotions.inputs import EpochCatalogue, epoch_catalogue, read_measured
from mavispm.measure.propermotions.pipeline import derive_proper_motions
from mavispm.measure.propermotions.report import write_report
from mavispm.measure.propermotions.settings import ProperMotionSettings, validate_settings

if TYPE_CHECKING:
    from astropy.table import QTable

__all__ = [
    "ProperMotionSettings",
    "proper_motions",
    "register",
    "run_stage",
    "truth_from_catalogue",
    "validate_settings",
    "write_report",
]


def truth_from_catalogue(catalogue: Catalogue | str | os.PathLike) -> dict:
    """True proper motions ``{"id", "pm_x", "pm_y"}`` [mas/yr] from a catalogue.

    Parameters
    ----------
    catalogue : path or Catalogue
        A ``catalogue`` product or one in memory (:func:`mavispm.simulate_cluster`).

    Returns
    -------
    dict
        ``id`` (int64), ``pm_x``, ``pm_y`` [mas/yr] of the first epoch's stars.
    """
    cat = catalogue if isinstance(catalogue, Catalogue) else read_catalogue(catalogue)
    first = next(iter(cat.epochs.values()))
    return {
        "id": np.asarray(first["id"], np.int64),
        "pm_x": first["pm_x"].to_value(u.mas / u.yr),
        "pm_y": first["pm_y"].to_value(u.mas / u.yr),
    }


def proper_motions(
    measured: Sequence,
    settings: Mapping | ProperMotionSettings | None = None,
    truth: Catalogue | str | os.PathLike | dict | None = None,
) -> QTable:
    """Match, align and fit proper motions of measured epochs in memory.

    Parameters
    ----------
    measured : sequence of QTable or EpochCatalogue
        Two or more epochs' measured ``stars`` tables (any order), each with
        ``meta["epoch"]`` [yr] (what :func:`mavispm.measure_stars` returns).
    settings : mapping or ProperMotionSettings, optional
        See :class:`~mavispm.measure.propermotions.settings.ProperMotionSettings`.
    truth : Catalogue, path or dict, optional
        True motions for scoring: a catalogue (in memory or a product) or
        ``{"id", "pm_x", "pm_y"}`` [mas/yr].

    Returns
    -------
    QTable
        The ``stars`` table of the ``propermotions`` product (docs/formats.md),
        ``pm_x``, ``pm_y`` ... [mas/yr]; ``meta`` holds the product's root
        attributes (epochs [yr], reference epoch, distance [kpc], transformation
        summary, matching counts, accuracy summaries).

    Examples
    --------
    Two epochs 10 yr apart of 40 stars moving by +-0.5 mas/yr along x; the
    motions are measured relative to the frame the alignment defines:

    >>> import numpy as np, astropy.units as u
    >>> from astropy.table import QTable
    >>> rng = np.random.default_rng(0)
    >>> x, y = rng.uniform(-2, 2, (2, 40))
    >>> pm_true = rng.choice([-0.5, 0.5], 40)
    >>> def epoch(t):
    ...     tab = QTable({"id": np.arange(40), "x": (x + pm_true * t / 1e3) * u.arcsec,
    ...                   "y": y * u.arcsec, "x_err": np.full(40, 0.1) * u.mas,
    ...                   "y_err": np.full(40, 0.1) * u.mas}, meta={"epoch": t * u.yr})
    ...     return tab
    >>> pm = proper_motions([epoch(0), epoch(10)], {"distance": "4.6 kpc"})
    >>> len(pm), pm["pm_x"].unit, pm.meta["reference_epoch"]
    (40, Unit("mas / yr"), <Quantity 0. yr>)
    >>> bool(np.corrcoef(pm["pm_x"].value, pm_true)[0, 1] > 0.99)
    True
    """
    cfg = validate_settings(settings)
    epochs = [m if isinstance(m, EpochCatalogue) else epoch_catalogue(m) for m in measured]
    truth_pm = truth if truth is None or isinstance(truth, dict) else truth_from_catalogue(truth)
    result = derive_proper_motions(epochs, cfg, truth_pm=truth_pm)
    frame_err = {
        f"{t:g}": fit.frame_error() * 1e3 for t, fit in zip(result.epochs, result.fits) if fit
    }
    stars = result.stars
    stars.meta.update(
        {
            "epochs": result.epochs * u.yr,
            "reference_epoch": result.reference_epoch * u.yr,
            "distance": None if result.distance is None else result.distance * u.kpc,
            "transform": result.transform_summary(),
            "match_method": result.match.method,
            "n_stars": len(result.stars),
            "n_unmatched": list(result.match.n_unmatched),
            "n_ambiguous": int(np.count_nonzero(result.match.ambiguous)),
            "n_dropped": result.n_dropped,
            "frame_error_mas": frame_err,
            "notes": "; ".join(result.notes),
            **accuracy_attrs(result.stars),
        }
    )
    return stars


def run_stage(
    measured: Sequence[str | os.PathLike],
    settings: Mapping | ProperMotionSettings | None,
    output: str | os.PathLike,
    truth: str | os.PathLike | None = None,
) -> Path:
    """Match, align and fit proper motions; write the propermotions product.

    Parameters
    ----------
    measured : list of path
        Two or more ``measured`` products (any order).
    settings : mapping or ProperMotionSettings
        See :class:`~mavispm.measure.propermotions.settings.ProperMotionSettings`.
    output : path
        The propermotions product (written atomically).
    truth : path, optional
        A ``catalogue`` product whose ``pm_x``, ``pm_y`` are the true motions.

    Returns
    -------
    pathlib.Path
    """
    cfg = validate_settings(settings)
    epochs = [read_measured(p) for p in measured]
    stars = proper_motions(epochs, cfg, truth=truth)
    from mavispm.measure.propermotions.pipeline import PMFlag

    attrs = {
        **stars.meta,
        "inputs": [str(p) for p in measured],
        "flag_reject_mask": int(PMFlag.REJECT),
    }
    stars.meta.clear()
    return write_product(
        output,
        "propermotions",
        tables={"stars": stars},
        attrs=attrs,
        config={"propermotions": to_mapping(cfg)},
    )


def accuracy_attrs(stars: QTable) -> dict:
    """Scalar accuracy summaries of a propermotions table (for sweep tables and plots).

    ``pm_err_median`` [mas/yr]: median per-axis reported PM error; with the truth
    columns also ``pm_rms_true`` [mas/yr], the robust (MAD) per-axis RMS of
    ``pm - pm_true`` after removing the median offset (measured PMs are relative to
    the cluster's mean motion), and ``pm_frac_50uas``, the fraction of stars with
    ``|pm - pm_true| <= 50 microarcsec/yr`` (the paper's statistic). Stars with
    non-finite values are left out; an empty selection gives NaN.

    Parameters
    ----------
    stars : QTable
        A propermotions ``stars`` table.

    Returns
    -------
    dict
        The summaries above (quantities).
    """
    mas_yr = u.mas / u.yr
    ex, ey = (stars[c].to_value(mas_yr) for c in ("pm_x_err", "pm_y_err"))
    err = np.sqrt(0.5 * (ex**2 + ey**2))
    err = err[np.isfinite(err)]
    out = {"pm_err_median": (float(np.median(err)) if err.size else np.nan) * mas_yr}
    if "pm_x_true" not in stars.colnames:
        return out
    d = np.stack(
        [stars[c].to_value(mas_yr) - stars[f"{c}_true"].to_value(mas_yr) for c in ("pm_x", "pm_y")]
    )
    d = d[:, np.all(np.isfinite(d), axis=0)]
    if d.shape[1] == 0:
        return {**out, "pm_rms_true": np.nan * mas_yr, "pm_frac_50uas": np.nan}
    d -= np.median(d, axis=1, keepdims=True)
    out["pm_rms_true"] = float(np.sqrt(np.mean(mad_std(d, axis=1) ** 2))) * mas_yr
    out["pm_frac_50uas"] = float(np.mean(np.hypot(d[0], d[1]) <= 0.05))
    return out


def summary_line(path: str | os.PathLike) -> str:
    """One-line summary of a propermotions product (stars, matching, clipping, notes).

    Parameters
    ----------
    path : path
        A propermotions product.

    Returns
    -------
    str
    """
    prod = read_product(path, "propermotions", load_arrays=False)
    a = prod.attrs
    transform = json.loads(a["transform"]) if isinstance(a.get("transform"), str) else {}
    clipped = [
        f"{t} yr: {v['n_ref']} ref, {v['n_clipped']} clipped"
        for t, v in transform.get("epochs", {}).items()
        if isinstance(v, dict)
    ]
    text = (
        f"{a.get('n_stars')} stars matched by {a.get('match_method')}; "
        f"unmatched per epoch {a.get('n_unmatched')}, ambiguous {a.get('n_ambiguous')}; "
        + "; ".join(clipped)
    )
    return text + (f" ({a['notes']})" if a.get("notes") else "")


def _handler(args) -> int:
    settings = {}
    for key in ("order", "reference", "match", "distance", "clip_sigma", "max_pm"):
        value = getattr(args, key, None)
        if isinstance(value, str):
            try:  # a bare number is in the setting's documented unit
                value = float(value)
            except ValueError:
                pass
        if value is not None:
            settings[key] = value
    if args.conformal:
        settings["conformal"] = True
    out = run_stage(args.measured, settings, args.output, truth=args.truth)
    print(f"wrote {out}")
    print(summary_line(out))
    if args.report is not None:
        for path in write_report([out], args.report):
            print(f"wrote {path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``propermotions`` sub-command.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The sub-parsers of the ``mavispm`` parser (or of its command group).
    """
    p = subparsers.add_parser(
        "propermotions",
        help="cross-match epochs, align them and fit proper motions",
        description="Cross-match measured epochs (by ID or position), fit each epoch's "
        "transformation to the reference epoch with sigma clipping, and fit proper motions "
        "by weighted least squares. Writes a propermotions product.",
    )
    p.add_argument("measured", nargs="+", type=Path, help="measured products, one per epoch")
    p.add_argument("-o", "--output", required=True, type=Path, help="propermotions product")
    p.add_argument("--distance", help="cluster distance, e.g. '4.6 kpc' (default: from inputs)")
    p.add_argument("--order", type=int, choices=(1, 2, 3), help="transformation order")
    p.add_argument("--conformal", action="store_true", help="order 1 as shift+scale+rotation only")
    p.add_argument("--reference", type=int, help="index of the reference epoch (time order)")
    p.add_argument("--match", choices=("auto", "id", "position"), help="matching method")
    p.add_argument("--clip-sigma", dest="clip_sigma", type=float, help="clipping threshold")
    p.add_argument("--max-pm", dest="max_pm", help="largest expected PM, e.g. '5 mas/yr'")
    p.add_argument("--report", type=Path, help="write the accuracy report to this folder")
    p.add_argument("--truth", type=Path, help="catalogue product with the true PMs")
    p.set_defaults(func=_handler)
    return p
