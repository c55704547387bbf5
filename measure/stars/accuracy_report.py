"""Astrometric accuracy report in the magnitude bins of the paper's tab:simresults.

Per bin: input and recovered star counts, recovered fraction, the astrometric
dispersion of measured minus input positions after three iterations of
2-sigma clipping (as in the paper), the bias, the median Cramér-Rao bound and
median reported error. Written as ECSV and Markdown tables plus a PNG of
measured minus input x against magnitude (the style of fig:astromresiab-x3).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import astropy.units as u
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from astropy.stats import sigma_clip  # noqa: E402
from astropy.table import QTable, vstack  # noqa: E402

from mavispm.core.atomic import atomic_path  # noqa: E402
from mavispm.core.errors import InputError  # noqa: E402
from mavispm.core.products import read_product  # noqa: E402
from mavispm.measure.stars.measured_table import MEASURED_SPEC  # noqa: E402

__all__ = [
    "accuracy_table",
    "bin_label",
    "clipped_std",
    "EXCLUDE_FLAGS",
    "MAG_BINS",
    "truth_bin_counts",
    "write_report",
]

#: Bin edges of the paper's results table [mag].
MAG_BINS = (-np.inf, 16.0, 17.0, 18.0, 19.0, 20.0, 22.0, 24.0, 26.0, np.inf)

#: Flags that exclude a star from the dispersion (failed, no match).
EXCLUDE_FLAGS = 16 | 32


def truth_bin_counts(mags: np.ndarray) -> list[int]:
    """Number of input stars per :data:`MAG_BINS` bin."""
    mags = np.asarray(mags, float)
    return [
        int(np.count_nonzero((mags >= lo) & (mags < hi)))
        for lo, hi in zip(MAG_BINS[:-1], MAG_BINS[1:])
    ]


def bin_label(lo: float, hi: float) -> str:
    """Human label of a magnitude bin ("m<16", "[16,17)", "m>=26")."""
    if not np.isfinite(lo):
        return f"m<{hi:g}"
    if not np.isfinite(hi):
        return f"m>={lo:g}"
    return f"[{lo:g},{hi:g})"


def clipped_std(
    values: np.ndarray, sigma: float = 2.0, iterations: int = 3
) -> tuple[float, float, int]:
    """Mean, standard deviation and count after ``iterations`` of ``sigma`` clipping."""
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    if len(values) < 2:
        return float("nan"), float("nan"), len(values)
    kept = sigma_clip(values, sigma=sigma, maxiters=iterations, cenfunc="median", stdfunc="std")
    data = kept.compressed()
    if len(data) < 2:
        return float("nan"), float("nan"), len(data)
    return float(np.mean(data)), float(np.std(data, ddof=1)), len(data)


def accuracy_table(stars: QTable, n_input: Sequence[int] | None = None) -> QTable:
    """Per-magnitude-bin astrometric accuracy of a measured ``stars`` table.

    Parameters
    ----------
    stars : QTable
        Measured stars with truth columns (``x_true``, ``y_true``, ``mag``).
    n_input : sequence of int, optional
        Input stars per bin (for the recovered fraction); by default counted
        from the measured stars' truth magnitudes.

    Returns
    -------
    QTable
        Columns bin, mag_lo, mag_hi, n_input, n_recovered, recovered_fraction,
        n_used, sigma_x, sigma_y, sigma_1d, bias_x, bias_y [uas], crlb_x, err_x
        (medians) [uas].
    """
    for col in ("x", "y", "x_true", "y_true", "mag", "flag"):
        if col not in stars.colnames:
            raise InputError(f"accuracy report needs column '{col}' (truth known)", column=col)
    mag = np.asarray(
        stars["mag"].to_value(u.mag) if isinstance(stars["mag"], u.Quantity) else stars["mag"],
        float,
    )
    dx = (stars["x"] - stars["x_true"]).to_value(u.uas)
    dy = (stars["y"] - stars["y_true"]).to_value(u.uas)
    flag = np.asarray(stars["flag"], int)
    good = ((flag & EXCLUDE_FLAGS) == 0) & np.isfinite(dx) & np.isfinite(dy) & np.isfinite(mag)
    crlb_x = (
        stars["crlb_x"].to_value(u.uas)
        if "crlb_x" in stars.colnames
        else np.full(len(stars), np.nan)
    )
    err_x = stars["x_err"].to_value(u.uas)
    counts = truth_bin_counts(mag) if n_input is None else [int(c) for c in n_input]
    rows = []
    for (lo, hi), n_in in zip(zip(MAG_BINS[:-1], MAG_BINS[1:]), counts):
        inbin = good & (mag >= lo) & (mag < hi)
        n_rec = int(np.count_nonzero(inbin))
        mx, sx, nx_ = clipped_std(dx[inbin])
        my, sy, _ = clipped_std(dy[inbin])
        rows.append(
            (
                bin_label(lo, hi),
                lo,
                hi,
                n_in,
                n_rec,
                n_rec / n_in if n_in else np.nan,
                nx_,
                sx,
                sy,
                np.sqrt((sx**2 + sy**2) / 2),
                mx,
                my,
                np.nanmedian(crlb_x[inbin]) if np.any(np.isfinite(crlb_x[inbin])) else np.nan,
                np.nanmedian(err_x[inbin]) if np.any(np.isfinite(err_x[inbin])) else np.nan,
            )
        )
    names = (
        "bin", "mag_lo", "mag_hi", "n_input", "n_recovered", "recovered_fraction", "n_used",
        "sigma_x", "sigma_y", "sigma_1d", "bias_x", "bias_y", "crlb_x", "err_x",
    )  # fmt: skip
    table = QTable(rows=rows, names=names)
    for col in ("sigma_x", "sigma_y", "sigma_1d", "bias_x", "bias_y", "crlb_x", "err_x"):
        table[col].unit = u.uas
    for col in ("mag_lo", "mag_hi"):
        table[col].unit = u.mag
    return table


def _markdown(table: QTable, title: str) -> str:
    cols = [
        "bin",
        "n_input",
        "n_recovered",
        "recovered_fraction",
        "sigma_x",
        "sigma_y",
        "sigma_1d",
        "bias_x",
        "crlb_x",
        "err_x",
    ]
    head = (
        "| "
        + " | ".join(
            c
            if c not in ("sigma_x", "sigma_y", "sigma_1d", "bias_x", "crlb_x", "err_x")
            else f"{c} [uas]"
            for c in cols
        )
        + " |"
    )
    lines = [f"# {title}", "", "Dispersion after 3 iterations of 2-sigma clipping; "
             "crlb_x and err_x are bin medians.", "", head, "|" + "---|" * len(cols)]  # fmt: skip
    for row in table:
        cells = []
        for c in cols:
            v = row[c]
            v = v.value if isinstance(v, u.Quantity) else v
            if isinstance(v, str):
                cells.append(v)
            elif isinstance(v, (int, np.integer)):
                cells.append(str(int(v)))
            else:
                cells.append(
                    ""
                    if not np.isfinite(v)
                    else f"{v:.3g}"
                    if c == "recovered_fraction"
                    else f"{v:.2f}"
                )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plot(panels: list, path: Path, title: str) -> None:
    """One panel per epoch: measured - input x against magnitude, clipped sigma, CRLB.

    ``panels``: (panel title, stars, accuracy table) per epoch.
    """
    fig, axes = plt.subplots(
        len(panels), 1, figsize=(7, 3.6 * len(panels) + 0.6), squeeze=False, sharex=True
    )
    for ax, (name, stars, table) in zip(axes[:, 0], panels):
        _panel(ax, stars, table)
        ax.set_title(name, fontsize=9)
    axes[-1, 0].set_xlabel("input magnitude V [mag]")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def _panel(ax, stars: QTable, table: QTable) -> None:
    mag = stars["mag"].to_value(u.mag)
    dx = (stars["x"] - stars["x_true"]).to_value(u.mas)
    good = ((np.asarray(stars["flag"]) & EXCLUDE_FLAGS) == 0) & np.isfinite(dx)
    ax.scatter(mag[good], dx[good], s=3, alpha=0.5, color="k", label="unflagged stars")
    centres = [0.5 * (lo + hi) if np.isfinite(lo) and np.isfinite(hi) else (hi - 0.5 if np.isfinite(hi) else lo + 0.5)
               for lo, hi in zip(table["mag_lo"].value, table["mag_hi"].value)]  # fmt: skip
    sig = table["sigma_x"].to_value(u.mas)
    has = np.isfinite(sig)  # bins without stars are not drawn
    centres = np.asarray(centres)
    ax.errorbar(
        centres[has],
        np.zeros(int(has.sum())),
        yerr=sig[has],
        fmt="o",
        color="C3",
        capsize=3,
        label="clipped 1-sigma per bin",
    )
    crlb = table["crlb_x"].to_value(u.mas)
    if np.any(np.isfinite(crlb)):
        ax.plot(centres[has], crlb[has], "s--", color="C0", ms=4, label="Cramer-Rao bound (median)")
    lim = np.nanpercentile(np.abs(dx[good]), 99) if np.any(good) else 1.0
    ax.set_ylim(-1.2 * lim, 1.2 * lim)
    ax.set_ylabel("x measured - input [mas]")
    ax.legend(loc="upper left", fontsize=7)


def _epoch_name(prod) -> str:
    epoch = prod.attrs.get("epoch")
    return "epoch unknown" if epoch is None else f"epoch {u.Quantity(epoch, u.yr).value:g} yr"


def write_report(measured_paths: Sequence, outdir) -> list[Path]:
    """Accuracy report of one or more measured products, per epoch.

    Products of the same epoch (``epoch`` attribute) are pooled; each epoch gets
    its own table (rows of ``accuracy.ecsv`` carry an ``epoch`` column [yr]),
    Markdown section and plot panel.

    Parameters
    ----------
    measured_paths : sequence of path
        ``measured`` products with truth columns.
    outdir : path
        Output folder (created).

    Returns
    -------
    list of Path
        ``accuracy.ecsv``, ``accuracy.md``, ``astrometry_x.png``.
    """
    if isinstance(measured_paths, (str, Path)):
        measured_paths = [measured_paths]
    if not measured_paths:
        raise InputError("no measured products given for the accuracy report")
    products = [read_product(p, "measured", specs={"stars": MEASURED_SPEC}) for p in measured_paths]
    by_epoch: dict[str, list] = {}
    for prod in products:
        if "x_true" not in prod.tables["stars"].colnames:
            raise InputError(
                "no truth columns (x_true, y_true, mag): cannot report accuracy", path=prod.path
            )
        by_epoch.setdefault(_epoch_name(prod), []).append(prod)
    panels, tables, sections = [], [], []
    for name, group in by_epoch.items():
        counts = np.zeros(len(MAG_BINS) - 1, dtype=int)
        for prod in group:
            per_bin = prod.attrs.get("truth_bin_counts")
            mags = prod.tables["stars"]["mag"].to_value(u.mag)
            counts += np.asarray(
                per_bin if per_bin is not None else truth_bin_counts(mags), dtype=int
            )
        parts = [prod.tables["stars"] for prod in group]
        stars = vstack(parts) if len(parts) > 1 else parts[0]
        table = accuracy_table(stars, counts)
        sources = ", ".join(str(prod.attrs.get("frames", prod.path)) for prod in group)
        panel = f"{name} ({len(stars)} stars; frames {sources})"
        panels.append((panel, stars, table))
        # the epoch as a bold label, not a heading: the run report embeds this file
        sections.append(_markdown(table, name).replace(f"# {name}", f"**{name}**", 1))
        epoch = group[0].attrs.get("epoch")
        table.add_column(
            np.full(len(table), np.nan if epoch is None else u.Quantity(epoch, u.yr).value) * u.yr,
            name="epoch",
            index=0,
        )
        tables.append(table)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    title = "Astrometric accuracy per epoch: measured - input x against input magnitude"
    ecsv, md, png = outdir / "accuracy.ecsv", outdir / "accuracy.md", outdir / "astrometry_x.png"
    with atomic_path(ecsv) as tmp:
        (vstack(tables) if len(tables) > 1 else tables[0]).write(
            tmp, format="ascii.ecsv", overwrite=True
        )
    with atomic_path(md) as tmp:
        tmp.write_text(f"# {title}\n\n" + "\n".join(sections))
    _plot(panels, png, title)
    return [ecsv, md, png]
