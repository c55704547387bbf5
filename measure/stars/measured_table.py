"""The ``stars`` table of a ``measured`` product: its columns and units (docs/formats.md).

Kept apart from the pipeline (:mod:`~mavispm.measure.stars.measure_frame`) and
the accuracy report (:mod:`~mavispm.measure.stars.accuracy_report`), which both
read it, so neither imports the other.
"""

from __future__ import annotations

from mavispm.core.products import TableSpec

__all__ = ["MEASURED_SPEC"]

#: The measured ``stars`` table (docs/formats.md) plus this stage's optional columns.
MEASURED_SPEC = TableSpec(
    required={
        "id": "",
        "x_pix": "",
        "y_pix": "",
        "x": "arcsec",
        "y": "arcsec",
        "x_err": "arcsec",
        "y_err": "arcsec",
        "flux": "electron",
        "flux_err": "electron",
        "sky": "electron",
        "chi2": "",
        "flag": "",
    },
    optional={
        "x_true": "arcsec",
        "y_true": "arcsec",
        "mag": "mag",
        "mag_fit": "mag",
        "mag_fit_err": "mag",
        "match_dist": "arcsec",
        "flux_true": "electron",
        "crlb_x": "arcsec",
        "crlb_y": "arcsec",
        "x_err_fisher": "arcsec",
        "y_err_fisher": "arcsec",
        "flux_err_fisher": "electron",
        "err_epsf": "arcsec",
        "x_err_registration": "arcsec",
        "y_err_registration": "arcsec",
    },
    allow_nan=(
        "x_err",
        "y_err",
        "flux",
        "flux_err",
        "sky",
        "chi2",
        "x_true",
        "y_true",
        "mag",
        "mag_fit",
        "mag_fit_err",
        "match_dist",
        "flux_true",
        "crlb_x",
        "crlb_y",
        "x_err_fisher",
        "y_err_fisher",
        "flux_err_fisher",
        "err_epsf",
        "x_err_registration",
        "y_err_registration",
    ),
)
