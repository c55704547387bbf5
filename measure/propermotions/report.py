"""Accuracy report of a proper-motion catalogue against the injected truth.

Per star the PM error is ``d = pm - pm_true`` (both relative to the cluster's
mean motion, see docs/propermotions.md). Two accuracy measures are reported:

* ``|d|`` [microarcsec/yr], the proper-motion error per year. This is also the
  paper's statistic (sec. 5.2, fig. pmresults): the paper's per-axis
  ``sigma = sqrt(2) (mu_in - mu_meas) / 10`` over its ten-year baseline, taken
  as the rms over both axes, equals ``|d|`` in microarcsec/yr;
* ``|d| T / 2`` [microarcsec], the per-epoch, per-axis position error that a
  two-epoch measurement over the baseline ``T`` with this PM error implies.

Tables (ECSV): error statistics per magnitude bin (the paper's bins) and per
radius bin, with the fractions of stars within 50 and 150 microarcsec (per yr
and per epoch); a Markdown summary with the paper's statistic (stars with
``m <= 25`` and ``m > 25`` meeting 50 microarcsec; paper: 1182/1194 and 97/181
before filtering) and the normalised-residual distribution; PNG plots of the PM
error against magnitude and radius and of the normalised residuals.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.stats import mad_std
from astropy.table import QTable

from mavispm.core.atomic import atomic_path
from mavispm.core.errors import InputError
from mavispm.core.products import TableSpec, read_product

__all__ = [
    "AccuracyData",
    "MAG_EDGES",
    "PAPER_MAG_SPLIT",
    "THRESHOLDS",
    "accuracy_by_magnitude",
    "accuracy_by_radius",
    "load_accuracy",
    "paper_statistic",
    "residual_summary",
    "write_report",
]

#: Magnitude bin edges of the paper's Table (tab:simresults).
MAG_EDGES = (-np.inf, 16, 17, 18, 19, 20, 22, 24, 26, np.inf)
#: Accuracy thresholds [microarcsec] (and microarcsec/yr).
THRESHOLDS = (50.0, 150.0)
#: The paper's split magnitude for its statistic.
PAPER_MAG_SPLIT = 25.0
PAPER_NUMBERS = {"bright": (1182, 1194), "faint": (97, 181)}

PM_SPEC = TableSpec(
    required={
        "id": "",
        "x": "arcsec",
        "y": "arcsec",
        "R": "arcsec",
        "pm_x": "mas/yr",
        "pm_y": "mas/yr",
        "pm_x_err": "mas/yr",
        "pm_y_err": "mas/yr",
        "flag": "",
    },
    optional={"mag": "mag", "pm_x_true": "mas/yr", "pm_y_true": "mas/yr"},
    allow_nan=("pm_x_true", "pm_y_true", "mag"),
)

UAS_YR = u.microarcsecond / u.yr


@dataclass
class AccuracyData:
    """Per-star accuracy quantities of one propermotions product (truth known).

    Parameters
    ----------
    name : str
        Label of the product in plots and tables (its file name stem).
    mag : ndarray or None
        Magnitudes [mag] (None when the product has none).
    radius : ndarray
        Projected distance from the centre, the product's ``R`` column [arcsec].
    dx, dy : ndarray
        Measured minus true proper motion [microarcsec/yr].
    err_x, err_y : ndarray
        Reported proper-motion errors [microarcsec/yr].
    baseline : float
        Epoch baseline [yr].
    """

    name: str
    mag: np.ndarray | None
    radius: np.ndarray  # arcsec
    dx: np.ndarray  # microarcsec/yr
    dy: np.ndarray
    err_x: np.ndarray  # microarcsec/yr
    err_y: np.ndarray
    baseline: float  # yr

    @property
    def dpm(self) -> np.ndarray:
        """|pm - pm_true| [microarcsec/yr]."""
        return np.hypot(self.dx, self.dy)

    @property
    def dpos(self) -> np.ndarray:
        """Implied per-epoch per-axis position error ``|d| T / 2`` [microarcsec]."""
        return self.dpm * self.baseline / 2.0

    @property
    def z(self) -> np.ndarray:
        """Normalised residuals of both axes."""
        return np.concatenate([self.dx / self.err_x, self.dy / self.err_y])


def load_accuracy(path: str | os.PathLike) -> AccuracyData:
    """Read a propermotions product and compute per-star errors against the truth.

    Parameters
    ----------
    path : str or os.PathLike
        A propermotions product with truth columns.

    Returns
    -------
    AccuracyData
        Per-star errors [microarcsec/yr] and their normalised values.

    Raises
    ------
    InputError
        Not a propermotions product, or no truth columns ``pm_x_true``/``pm_y_true``.
    """
    path = Path(path)
    prod = read_product(path, "propermotions", specs={"stars": PM_SPEC}, load_arrays=False)
    s = prod.tables["stars"]
    if "pm_x_true" not in s.colnames or "pm_y_true" not in s.colnames:
        raise InputError(
            "no truth columns pm_x_true/pm_y_true: an accuracy report needs the truth "
            "(measured products with x_true/y_true, or --truth cluster.h5)",
            path=path,
        )
    known = np.isfinite(s["pm_x_true"].value) & np.isfinite(s["pm_y_true"].value)
    if not np.any(known):
        raise InputError("no star has a known true proper motion", path=path, column="pm_x_true")
    s = s[known]
    epochs = np.atleast_1d(u.Quantity(prod.attrs.get("epochs", [0.0, 1.0]), u.yr).value)
    baseline = float(np.ptp(epochs)) if epochs.size > 1 else 1.0

    def uas(name):
        return s[name].to_value(UAS_YR)

    return AccuracyData(
        name=path.stem,
        mag=s["mag"].to_value(u.mag) if "mag" in s.colnames else None,
        radius=s["R"].to_value(u.arcsec),
        dx=uas("pm_x") - uas("pm_x_true"),
        dy=uas("pm_y") - uas("pm_y_true"),
        err_x=uas("pm_x_err"),
        err_y=uas("pm_y_err"),
        baseline=baseline,
    )


def _bin_rows(data: AccuracyData, which: np.ndarray, edges) -> QTable:
    rows = []
    dpm, dpos = data.dpm, data.dpos
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (which >= lo) & (which < hi)
        n = int(np.count_nonzero(sel))
        row = {"lo": lo, "hi": hi, "n": n}
        if n:
            row["rms_dpm_axis"] = float(np.sqrt(0.5 * np.mean(dpm[sel] ** 2)))
            row["median_dpm"] = float(np.median(dpm[sel]))
            row["median_pm_err"] = float(
                np.median(np.sqrt(0.5 * (data.err_x[sel] ** 2 + data.err_y[sel] ** 2)))
            )
        else:
            row.update(rms_dpm_axis=np.nan, median_dpm=np.nan, median_pm_err=np.nan)
        for t in THRESHOLDS:
            row[f"frac_le_{t:g}uas_yr"] = float(np.mean(dpm[sel] <= t)) if n else np.nan
            row[f"frac_le_{t:g}uas"] = float(np.mean(dpos[sel] <= t)) if n else np.nan
        rows.append(row)
    table = QTable(rows=rows)
    for name in ("rms_dpm_axis", "median_dpm", "median_pm_err"):
        table[name].unit = UAS_YR
    return table


def accuracy_by_magnitude(data: AccuracyData) -> QTable | None:
    """Error statistics in the paper's magnitude bins (None without magnitudes).

    Parameters
    ----------
    data : AccuracyData
        From :func:`load_accuracy`.

    Returns
    -------
    QTable or None
        One row per magnitude bin (``mag_lo``, ``mag_hi`` [mag]).
    """
    if data.mag is None:
        return None
    table = _bin_rows(data, data.mag, MAG_EDGES)
    table.rename_columns(["lo", "hi"], ["mag_lo", "mag_hi"])
    table["mag_lo"].unit = table["mag_hi"].unit = u.mag
    return table


def accuracy_by_radius(data: AccuracyData, n_bins: int = 8) -> QTable:
    """Error statistics in equal-count bins of cluster-centric radius.

    Parameters
    ----------
    data : AccuracyData
        From :func:`load_accuracy`.
    n_bins : int
        Number of equal-count radial bins.

    Returns
    -------
    QTable
        One row per bin (``R_lo``, ``R_hi`` [arcsec]).
    """
    edges = np.unique(np.quantile(data.radius, np.linspace(0, 1, n_bins + 1)))
    edges[-1] = np.nextafter(edges[-1], np.inf)
    table = _bin_rows(data, data.radius, edges)
    table.rename_columns(["lo", "hi"], ["R_lo", "R_hi"])
    table["R_lo"].unit = table["R_hi"].unit = u.arcsec
    return table


def paper_statistic(data: AccuracyData, threshold: float = 50.0) -> dict:
    """Stars with ``m <= 25`` and ``m > 25`` meeting ``threshold`` microarcsec(/yr).

    Parameters
    ----------
    data : AccuracyData
        From :func:`load_accuracy`.
    threshold : float
        [microarcsec/yr]

    Returns
    -------
    dict
        ``bright``/``faint``: (meeting, total) star counts.
    """
    if data.mag is None:
        return {}
    ok = data.dpm <= threshold
    bright = data.mag <= PAPER_MAG_SPLIT
    return {
        "bright": (int(np.count_nonzero(ok & bright)), int(np.count_nonzero(bright))),
        "faint": (int(np.count_nonzero(ok & ~bright)), int(np.count_nonzero(~bright))),
    }


def residual_summary(data: AccuracyData) -> dict:
    """Mean, std, and outlier fractions of the normalised residuals.

    Parameters
    ----------
    data : AccuracyData
        From :func:`load_accuracy`.

    Returns
    -------
    dict
        ``n``, ``mean``, ``std``, ``robust_std`` (MAD), ``frac_gt3``.
    """
    z = data.z
    z = z[np.isfinite(z)]
    if z.size == 0:
        return {"n": 0, "mean": np.nan, "std": np.nan, "frac_gt3": np.nan}
    return {
        "n": int(z.size),
        "mean": float(np.mean(z)),
        "std": float(np.std(z)),
        "robust_std": float(mad_std(z)),
        "frac_gt3": float(np.mean(np.abs(z) > 3)),
    }


def _markdown(data, by_mag, by_r, paper, resid) -> str:
    lines = [f"# Proper-motion accuracy: {data.name}", ""]
    lines.append(f"Stars with truth: {data.dpm.size}; baseline {data.baseline:g} yr.")
    lines.append("")
    if paper:
        b, f = paper["bright"], paper["faint"]
        pb, pf = PAPER_NUMBERS["bright"], PAPER_NUMBERS["faint"]
        lines += [
            "## The paper's statistic (|pm - pm_true| <= 50 microarcsec/yr)",
            "",
            "| sample | this run | paper (before filtering) |",
            "|---|---|---|",
            f"| m <= 25 | {b[0]}/{b[1]} | {pb[0]}/{pb[1]} |",
            f"| m > 25 | {f[0]}/{f[1]} | {pf[0]}/{pf[1]} |",
            "",
        ]
    lines += [
        "## Normalised residuals (pm - pm_true) / pm_err, both axes",
        "",
        f"n = {resid['n']}, mean = {resid['mean']:.3f}, std = {resid['std']:.3f}, "
        f"robust std = {resid.get('robust_std', np.nan):.3f}, "
        f"fraction |z| > 3 = {resid['frac_gt3']:.4f} (Gaussian: 0.0027)",
        "",
    ]
    for title, table, cols in (
        ("By magnitude", by_mag, ("mag_lo", "mag_hi")),
        ("By radius [arcsec]", by_r, ("R_lo", "R_hi")),
    ):
        if table is None:
            continue
        lines += [
            f"## {title}",
            "",
            "| bin | n | rms per axis [uas/yr] | median pm_err [uas/yr] "
            "| <=50 uas/yr | <=150 uas/yr | <=50 uas | <=150 uas |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for row in table:
            lo, hi = (float(np.asarray(getattr(row[c], "value", row[c]))) for c in cols)
            vals = [
                float(getattr(row[c], "value", row[c])) for c in ("rms_dpm_axis", "median_pm_err")
            ]
            fr = [
                float(row[c])
                for c in (
                    "frac_le_50uas_yr",
                    "frac_le_150uas_yr",
                    "frac_le_50uas",
                    "frac_le_150uas",
                )
            ]
            lines.append(
                f"| [{lo:.4g}, {hi:.4g}) | {row['n']} | {vals[0]:.1f} | {vals[1]:.1f} | "
                + " | ".join(f"{v:.3f}" for v in fr)
                + " |"
            )
        lines.append("")
    return "\n".join(lines)


def _plot_errors(data: AccuracyData, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("R from the centre [arcsec]", data.radius)]
    if data.mag is not None:
        panels.insert(0, ("V (input) [mag]", data.mag))
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, 3.2 * len(panels)), squeeze=False)
    dpm = data.dpm
    within = [dpm <= THRESHOLDS[0], (dpm > THRESHOLDS[0]) & (dpm <= THRESHOLDS[1])]
    rest = dpm > THRESHOLDS[1]
    for ax, (label, xval) in zip(axes[:, 0], panels):
        ax.scatter(xval[rest], data.dx[rest], s=3, c="0.6", label=f"> {THRESHOLDS[1]:g}")
        ax.scatter(xval[within[1]], data.dx[within[1]], s=3, c="indigo", label="<= 150")
        ax.scatter(xval[within[0]], data.dx[within[0]], s=3, c="mediumpurple", label="<= 50")
        ax.axhline(0, c="k", lw=0.5)
        ax.set_xlabel(label)
        ax.set_ylabel(r"$\mu_{x}-\mu_{x,\rm true}$ [$\mu$as/yr]")
        lim = np.nanpercentile(np.abs(data.dx), 99) if data.dx.size else 1.0
        ax.set_ylim(-1.2 * lim, 1.2 * lim)
    axes[0, 0].legend(title=r"$|\Delta\mu|$ [$\mu$as/yr]", fontsize=8, markerscale=3)
    axes[0, 0].set_title(f"{data.name}: PM error (baseline {data.baseline:g} yr)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _plot_residuals(data: AccuracyData, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    z = data.z
    z = z[np.isfinite(z)]
    fig, ax = plt.subplots(figsize=(6, 4))
    bins = np.linspace(-5, 5, 61)
    ax.hist(np.clip(z, -5, 5), bins=bins, density=True, color="mediumpurple", label="measured")
    g = np.linspace(-5, 5, 400)
    ax.plot(g, np.exp(-0.5 * g**2) / np.sqrt(2 * np.pi), "k", label="N(0, 1)")
    ax.set_xlabel(r"$(\mu - \mu_{\rm true}) / \sigma_\mu$ (x and y)")
    ax.set_ylabel("density")
    ax.set_title(f"{data.name}: normalised PM residuals (baseline {data.baseline:g} yr)")
    ax.legend(title="residuals", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _write_ecsv(table: QTable, path: Path) -> None:
    with atomic_path(path) as tmp:
        table.write(tmp, format="ascii.ecsv", overwrite=True)


def write_report(
    pm_paths: str | os.PathLike | Sequence[str | os.PathLike], outdir: str | os.PathLike
) -> list[Path]:
    """Write the accuracy report of one or more propermotions products.

    Parameters
    ----------
    pm_paths : path or list of paths
        Propermotions products with truth columns.
    outdir : path
        Output folder (created).

    Returns
    -------
    list of pathlib.Path
        Files written: per product ``<stem>_pm_by_mag.ecsv``, ``<stem>_pm_by_radius.ecsv``,
        ``<stem>_pm_accuracy.md``, ``<stem>_pm_errors.png``, ``<stem>_pm_residuals.png``.
    """
    if isinstance(pm_paths, (str, os.PathLike)):
        pm_paths = [pm_paths]
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    for path in pm_paths:
        data = load_accuracy(path)
        by_mag = accuracy_by_magnitude(data)
        by_r = accuracy_by_radius(data)
        stem = outdir / data.name
        if by_mag is not None:
            _write_ecsv(by_mag, Path(f"{stem}_pm_by_mag.ecsv"))
            written.append(Path(f"{stem}_pm_by_mag.ecsv"))
        _write_ecsv(by_r, Path(f"{stem}_pm_by_radius.ecsv"))
        written.append(Path(f"{stem}_pm_by_radius.ecsv"))
        md = _markdown(data, by_mag, by_r, paper_statistic(data), residual_summary(data))
        with atomic_path(Path(f"{stem}_pm_accuracy.md")) as tmp:
            tmp.write_text(md)
        written.append(Path(f"{stem}_pm_accuracy.md"))
        _plot_errors(data, Path(f"{stem}_pm_errors.png"))
        _plot_residuals(data, Path(f"{stem}_pm_residuals.png"))
        written += [Path(f"{stem}_pm_errors.png"), Path(f"{stem}_pm_residuals.png")]
    return written
