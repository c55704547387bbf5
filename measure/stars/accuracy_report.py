"""Astrometric accuracy report in the magnitude bins of the paper's tab:simresults.

One table per frame (epoch), about the frame's common offset, which is shown
separately (the proper-motion alignment absorbs it). Per bin: input and recovered star counts, recovered fraction, the astrometric
dispersion of measured minus input positions after three iterations of
2-sigma clipping (as in the paper), the bias, the median Cramér-Rao bound and
median reported error. Written as ECSV and Markdown tables plus a PNG of
measured minus input x against magnitude (the style of fig:astromresiab-x3).
"""

from __future__ import annotations

import os
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
from mavispm.core.frame import on_detector  # noqa: E402
from mavispm.core.products import read_product  # noqa: E402
from mavispm.measure.stars.measured_table import MEASURED_SPEC  # noqa: E402

__all__ = [
    "EXCLUDE_FLAGS",
    "MAG_BINS",
    "OFFSET_MAG_LIMIT",
    "accuracy_table",
    "bin_label",
    "clipped_std",
    "frame_offset",
    "truth_bin_counts",
    "write_report",
]

#: Bin edges of the paper's results table [mag].
MAG_BINS = (-np.inf, 16.0, 17.0, 18.0, 19.0, 20.0, 22.0, 24.0, 26.0, np.inf)

#: Flags that exclude a star from the dispersion (failed, no match).
EXCLUDE_FLAGS = 16 | 32


def truth_bin_counts(mags: np.ndarray) -> list[int]:
    """Number of input stars per :data:`MAG_BINS` bin.

    Parameters
    ----------
    mags : ndarray
        Input (truth) magnitudes [mag].

    Returns
    -------
    list of int
        Count per bin, bins half-open ``[lo, hi)``.
    """
    mags = np.asarray(mags, float)
    return [
        int(np.count_nonzero((mags >= lo) & (mags < hi)))
        for lo, hi in zip(MAG_BINS[:-1], MAG_BINS[1:])
    ]


def bin_label(lo: float, hi: float) -> str:
    """Human label of a magnitude bin ("m<16", "[16,17)", "m>=26").

    Parameters
    ----------
    lo, hi : float
        Bin edges [mag] (``-inf``/``inf`` for the open end bins).

    Returns
    -------
    str
        The label.
    """
    if not np.isfinite(lo):
        return f"m<{hi:g}"
    if not np.isfinite(hi):
        return f"m>={lo:g}"
    return f"[{lo:g},{hi:g})"


def clipped_std(
    values: np.ndarray, sigma: float = 2.0, iterations: int = 3
) -> tuple[float, float, int]:
    """Mean, standard deviation and count after ``iterations`` of ``sigma`` clipping.

    Clipping is about the median (``astropy.stats.sigma_clip``); non-finite values are dropped
    first.

    Parameters
    ----------
    values : ndarray
        The values (any unit; the results share it).
    sigma : float
        Clipping threshold [standard deviations].
    iterations : int
        Maximum clipping iterations.

    Returns
    -------
    mean, std : float
        Of the kept values (``std`` with ddof = 1); NaN with fewer than two values.
    n : int
        Values kept.
    """
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    if len(values) < 2:
        return float("nan"), float("nan"), len(values)
    kept = sigma_clip(values, sigma=sigma, maxiters=iterations, cenfunc="median", stdfunc="std")
    data = kept.compressed()
    if len(data) < 2:
        return float("nan"), float("nan"), len(data)
    return float(np.mean(data)), float(np.std(data, ddof=1)), len(data)


#: Stars brighter than this [mag] define a frame's common offset.
OFFSET_MAG_LIMIT = 22.0


def _residuals(stars: QTable):
    """Truth magnitude, measured - true x and y [uas], and the usable-star mask."""
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
    return mag, dx, dy, good


def frame_offset(stars: QTable) -> tuple[float, float, int]:
    """Common offset of one frame's measured positions from the truth [uas].

    The median of measured - true x and y of the unflagged stars brighter than
    :data:`OFFSET_MAG_LIMIT` (a frame-wide shift: the epoch alignment of the
    proper-motion stage absorbs it, so the accuracy table is computed about it).

    Parameters
    ----------
    stars : astropy.table.QTable
        The measured stars with their truth columns.

    Returns
    -------
    offset_x, offset_y : float
        [uas]; 0 when no star qualifies.
    n : int
        Stars used.
    """
    mag, dx, dy, good = _residuals(stars)
    sel = good & (mag < OFFSET_MAG_LIMIT)
    if not np.any(sel):
        return 0.0, 0.0, 0
    return float(np.median(dx[sel])), float(np.median(dy[sel])), int(np.count_nonzero(sel))


def accuracy_table(
    stars: QTable,
    n_input: Sequence[int] | None = None,
    offset: tuple[float, float] = (0.0, 0.0),
    detector_shape: Sequence[int] | None = None,
) -> QTable:
    """Per-magnitude-bin astrometric accuracy of one frame's measured ``stars`` table.

    Parameters
    ----------
    stars : QTable
        Measured stars with truth columns (``x_true``, ``y_true``, ``mag``).
    n_input : sequence of int, optional
        Input stars per bin (for the recovered fraction); by default counted
        from the measured stars' truth magnitudes.
    offset : tuple of float
        The frame's common offset [uas] (:func:`frame_offset`), removed from the
        residuals before the dispersion and bias are computed.
    detector_shape : sequence of int, optional
        ``(ny, nx)`` of the frame: a star counts as recovered only with its measured
        centre on the detector (``n_input`` then counts the input stars with their true
        centres there; the measured product's ``truth_bin_counts`` does). None: every
        usable star counts.

    Returns
    -------
    QTable
        Columns bin, mag_lo, mag_hi, n_input, n_recovered, recovered_fraction,
        n_used, sigma_x, sigma_y, sigma_1d, bias_x, bias_y [uas] (about the
        frame offset), crlb_x, err_x (medians) [uas].
    """
    mag, dx, dy, good = _residuals(stars)
    if detector_shape is not None and "x_pix" in stars.colnames:
        shape = tuple(int(v) for v in detector_shape)
        good = good & on_detector(stars["x_pix"], stars["y_pix"], shape)
    dx = dx - offset[0]
    dy = dy - offset[1]
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


_UAS_COLS = ("sigma_x", "sigma_y", "sigma_1d", "bias_x", "crlb_x", "err_x")


def _markdown_table(table: QTable) -> list[str]:
    cols = ["bin", "n_input", "n_recovered", "recovered_fraction", *_UAS_COLS]
    head = "| " + " | ".join(c if c not in _UAS_COLS else f"{c} [uas]" for c in cols) + " |"
    lines = [head, "|" + "---|" * len(cols)]
    for row in table:
        cells = []
        for c in cols:
            v = row[c]
            v = v.value if isinstance(v, u.Quantity) else v
            if isinstance(v, str):
                cells.append(v)
            elif isinstance(v, (int, np.integer)):
                cells.append(str(int(v)))
            elif not np.isfinite(v):
                cells.append("")
            else:
                cells.append(f"{v:.3g}" if c == "recovered_fraction" else f"{v:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _markdown(sections: list[tuple[str, tuple[float, float, int], QTable]], title: str) -> str:
    lines = [
        f"# {title}",
        "",
        "One table per frame (epoch). Each frame's common offset (median measured - "
        f"true of its unflagged stars with m < {OFFSET_MAG_LIMIT:g}; the epoch alignment "
        "absorbs it) is shown separately and removed; dispersions after 3 iterations of "
        "2-sigma clipping; bias about the offset; crlb_x and err_x are bin medians.",
    ]
    for name, (ox, oy, n_off), table in sections:
        lines += [
            "",
            f"## {name}",
            "",
            f"Frame offset: x {ox:+.2f} uas, y {oy:+.2f} uas ({n_off} stars).",
            "",
            *_markdown_table(table),
        ]
    return "\n".join(lines) + "\n"


def _plot(
    frames: list[tuple[str, QTable, tuple[float, float, int]]],
    table: QTable,
    path: Path,
    title: str,
) -> None:
    """Measured - true x (each frame's offset removed) against magnitude; the
    clipped sigma and CRLB of the first frame's table."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    all_dx = []
    for k, (name, stars, (ox, _, _)) in enumerate(frames):
        mag, dx, _, good = _residuals(stars)
        dx = (dx - ox) / 1000.0
        ax.scatter(mag[good], dx[good], s=3, alpha=0.5, color=f"C{k % 10}", label=name)
        all_dx.append(dx[good])
    dx = np.concatenate(all_dx) if all_dx else np.zeros(0)
    good = np.isfinite(dx)
    centres = [0.5 * (lo + hi) if np.isfinite(lo) and np.isfinite(hi) else (hi - 0.5 if np.isfinite(hi) else lo + 0.5)
               for lo, hi in zip(table["mag_lo"].value, table["mag_hi"].value)]  # fmt: skip
    sig = table["sigma_x"].to_value(u.mas)
    ax.errorbar(
        centres,
        np.zeros(len(centres)),
        yerr=sig,
        fmt="o",
        color="C3",
        capsize=3,
        label="clipped 1-sigma (first frame)",
    )
    if np.any(np.isfinite(table["crlb_x"])):
        ax.plot(
            centres, table["crlb_x"].to_value(u.mas), "s--", color="C0", ms=4, label="CRLB (median)"
        )
    lim = np.nanpercentile(np.abs(dx[good]), 99) if np.any(good) else 1.0
    ax.set_ylim(-1.2 * lim, 1.2 * lim)
    ax.set_xlabel("input magnitude V [mag]")
    ax.set_ylabel("measured - input x - frame offset [mas]")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def write_report(measured_paths: Sequence, outdir: str | os.PathLike) -> list[Path]:
    """Accuracy report of one or more measured products, one table per frame (epoch).

    Each frame's common offset (:func:`frame_offset`) is reported separately and
    removed from that frame's residuals; frames are never pooled (each has its own
    offset, which the epoch alignment absorbs).

    Parameters
    ----------
    measured_paths : sequence of path
        ``measured`` products with truth columns.
    outdir : path
        Output folder (created).

    Returns
    -------
    list of Path
        ``accuracy.ecsv`` (the tables stacked, with columns ``frame``, ``epoch``
        [yr], ``offset_x`` and ``offset_y`` [uas]), ``accuracy.md``,
        ``astrometry_x.png``.
    """
    if isinstance(measured_paths, (str, Path)):
        measured_paths = [measured_paths]
    if not measured_paths:
        raise InputError("no measured products given for the accuracy report")
    products = [read_product(p, "measured", specs={"stars": MEASURED_SPEC}) for p in measured_paths]
    sections, frames, tables = [], [], []
    for path, prod in zip(measured_paths, products):
        stars = prod.tables["stars"]
        if "x_true" not in stars.colnames:
            raise InputError(
                "no truth columns (x_true, y_true, mag): cannot report accuracy", path=prod.path
            )
        per_bin = prod.attrs.get("truth_bin_counts")
        counts = per_bin if per_bin is not None else truth_bin_counts(stars["mag"].to_value(u.mag))
        offset = frame_offset(stars)
        shape = prod.attrs.get("detector_shape") if per_bin is not None else None
        table = accuracy_table(stars, counts, offset[:2], shape)
        epoch = prod.attrs.get("epoch")
        epoch = float(u.Quantity(epoch, u.yr).value) if epoch is not None else np.nan
        name = f"{Path(path).parent.name}/{Path(path).name}"
        name = f"{name} (epoch {epoch:g} yr)" if np.isfinite(epoch) else name
        table.add_column(name, name="frame", index=0)
        table.add_column(epoch * u.yr, name="epoch", index=1)
        table["offset_x"] = offset[0] * u.uas
        table["offset_y"] = offset[1] * u.uas
        sections.append((name, offset, table))
        frames.append((name, stars, offset))
        tables.append(table)
    table = vstack(tables) if len(tables) > 1 else tables[0]
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    title = "Astrometric accuracy per frame"
    ecsv, md, png = outdir / "accuracy.ecsv", outdir / "accuracy.md", outdir / "astrometry_x.png"
    with atomic_path(ecsv) as tmp:
        table.write(tmp, format="ascii.ecsv", overwrite=True)
    with atomic_path(md) as tmp:
        tmp.write_text(_markdown(sections, title))
    _plot(frames, tables[0], png, title)
    return [ecsv, md, png]
