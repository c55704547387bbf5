"""``mavispm export PRODUCT -o table.fits|.ecsv|.csv``: one table of a product for other tools.

The products are HDF5 files whose tables astropy reads directly
(``astropy.table.Table.read(file, path="stars")``); this command writes one of
them as FITS (units in ``TUNITn``), ECSV (units and attributes in the header) or
CSV (values only), atomically.
"""

from __future__ import annotations

import argparse

from mavispm.core.products import EXPORT_FORMATS, export_table

__all__ = ["register"]


def _handler(args: argparse.Namespace) -> int:
    out = export_table(args.product, args.output, args.table)
    print(f"wrote {out}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``export`` command.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The sub-parsers of the ``mavispm`` parser (or of its command group).
    """
    p = subparsers.add_parser(
        "export",
        help="write one table of a product as FITS, ECSV or CSV",
        description="Write one table of a mavispm product (HDF5) as FITS, ECSV or CSV, "
        "chosen by the output suffix (" + ", ".join(sorted(EXPORT_FORMATS)) + ").",
    )
    p.add_argument("product", help="a mavispm product (HDF5)")
    p.add_argument("-o", "--output", required=True, help="output table (.fits, .ecsv or .csv)")
    p.add_argument(
        "--table",
        default=None,
        help="table name (stars, truth, epochs/e0, ...); default: the only table, else 'stars'",
    )
    p.set_defaults(func=_handler)
    return p
